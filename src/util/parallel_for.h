// dtraced::util::parallel_for: calls fn(i) for every i in [0, count) on up to `threads` threads,
// the caller's among them, and returns when all are done. Which thread runs which i is left to
// chance, so fn(i) must write only what belongs to i. A thread that cannot be started leaves its
// share to the others (the caller's thread always works); the first exception fn throws on any
// thread (std::bad_alloc) is thrown here once every thread has stopped, the rest of the work
// skipped. Used by the BVH build's passes; owns no state.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace dtraced::util {

template <typename Fn>
void parallel_for(std::size_t count, unsigned threads, const Fn& fn) {
  const auto n = unsigned(std::min<std::size_t>(threads, count));
  if (n <= 1) {
    for (std::size_t i = 0; i < count; ++i) fn(i);
    return;
  }
  std::atomic<std::size_t> next{0};
  std::mutex failed_mutex;
  std::exception_ptr failed;
  const auto work = [&]() noexcept {
    try {
      for (std::size_t i = next.fetch_add(1); i < count; i = next.fetch_add(1)) fn(i);
    } catch (...) {
      next.store(count);  // the others stop at their next item
      std::lock_guard lock(failed_mutex);
      if (!failed) failed = std::current_exception();
    }
  };
  std::vector<std::thread> pool;
  try {
    pool.reserve(n - 1);
    for (unsigned k = 0; k + 1 < n; ++k) pool.emplace_back(work);
  } catch (const std::exception&) {
    // std::system_error or std::bad_alloc: fewer helpers, same result.
  }
  work();
  for (std::thread& t : pool) t.join();
  if (failed) std::rethrow_exception(failed);
}

}  // namespace dtraced::util
