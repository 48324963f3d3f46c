// dtraced::util::ThreadPool: threads started once and handed one loop at a time, for a computation
// that runs many short parallel loops (the BVH build's top levels run a few hundred). Starting a
// thread for each loop (util::parallel_for, gone since the wide collapse took the pool too in
// round 18) cost ~35 us of CPU a thread, and the loop then waited for that thread to be
// scheduled, start, find the work and be joined; here the workers sleep between loops, and a loop
// whose items the caller has all taken does not wait for a worker that has not woken yet.
//
// parallel_for(count, threads, fn) calls fn(i) for every i in [0, count) on up to `threads` of the
// pool's threads, the caller's among them, and returns when every fn(i) has returned. Which thread
// runs which i is left to chance, so fn(i) must write only what belongs to i. The first exception
// fn throws (std::bad_alloc) is thrown once the loop has stopped, the rest of its items skipped.
// A pool whose threads cannot be started has fewer (the caller's thread always works).
//
// One caller at a time, and not from inside fn (a loop does not nest). The destructor stops and
// joins the workers. Owns no global state.
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <mutex>
#include <thread>
#include <vector>

namespace dtraced::util {

class ThreadPool {
 public:
  // Starts threads - 1 workers (none for 0 or 1).
  explicit ThreadPool(unsigned threads) {
    try {
      for (unsigned k = 1; k < threads; ++k) workers_.emplace_back([this] { work(); });
    } catch (const std::exception&) {
      // std::system_error or std::bad_alloc: fewer workers, same results.
    }
  }
  ThreadPool(const ThreadPool&) = delete;
  ThreadPool& operator=(const ThreadPool&) = delete;
  ~ThreadPool() {
    {
      std::lock_guard lock(mutex_);
      quit_ = true;
    }
    wake_.notify_all();
    for (std::thread& t : workers_) t.join();
  }

  // Threads a loop may run on: the workers and the caller.
  unsigned size() const { return unsigned(workers_.size()) + 1; }

  template <typename Fn>
  void parallel_for(std::size_t count, unsigned threads, const Fn& fn) {
    if (threads <= 1 || count <= 1 || workers_.empty()) {
      for (std::size_t i = 0; i < count; ++i) fn(i);
      return;
    }
    Loop loop;
    loop.count = count;
    loop.run = [](const void* f, std::size_t i) { (*static_cast<const Fn*>(f))(i); };
    loop.fn = &fn;
    loop.helpers = std::min<std::size_t>(threads - 1, count - 1);
    {
      std::lock_guard lock(mutex_);
      loop_ = &loop;
      ++generation_;
    }
    if (loop.helpers == 1) {
      wake_.notify_one();
    } else {
      wake_.notify_all();
    }
    run(loop);
    {
      // Every item is taken: wait for the workers still running one, then retire the loop so that
      // a worker that wakes later does not look at it.
      std::unique_lock lock(mutex_);
      idle_.wait(lock, [this] { return active_ == 0; });
      loop_ = nullptr;
    }
    if (loop.failed) std::rethrow_exception(loop.failed);
  }

 private:
  struct Loop {
    std::atomic<std::size_t> next{0};
    std::size_t count = 0;
    void (*run)(const void*, std::size_t) = nullptr;
    const void* fn = nullptr;
    std::size_t helpers = 0;  // workers that may join (guarded by mutex_)
    std::mutex failed_mutex;
    std::exception_ptr failed;
  };

  static void run(Loop& loop) noexcept {
    try {
      for (std::size_t i = loop.next.fetch_add(1); i < loop.count; i = loop.next.fetch_add(1)) loop.run(loop.fn, i);
    } catch (...) {
      loop.next.store(loop.count);  // the others stop at their next item
      std::lock_guard lock(loop.failed_mutex);
      if (!loop.failed) loop.failed = std::current_exception();
    }
  }

  void work() {
    std::uint64_t seen = 0;
    std::unique_lock lock(mutex_);
    for (;;) {
      wake_.wait(lock, [&] { return quit_ || (loop_ != nullptr && generation_ != seen && loop_->helpers > 0); });
      if (quit_) return;
      seen = generation_;
      Loop& loop = *loop_;
      --loop.helpers;
      ++active_;
      lock.unlock();
      run(loop);
      lock.lock();
      if (--active_ == 0) idle_.notify_all();
    }
  }

  std::mutex mutex_;
  std::condition_variable wake_;  // a loop to join, or quit_
  std::condition_variable idle_;  // active_ fell to 0
  Loop* loop_ = nullptr;          // the loop being run, if any
  std::uint64_t generation_ = 0;  // loops handed out so far
  unsigned active_ = 0;           // workers inside a loop
  bool quit_ = false;
  std::vector<std::thread> workers_;
};

}  // namespace dtraced::util
