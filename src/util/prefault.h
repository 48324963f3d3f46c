// dtraced::util prefault: maps the pages of large arrays that are about to be filled, on a thread of
// its own, so that the thread filling them finds their pages there. The first write to a fresh
// page is a fault in which the kernel zeroes it (a 2 MiB huge page at a time where
// advise_huge_pages applied); while one thread parses a large scene into its arrays, those faults
// took about 8 % of its time (1M spheres, perf). madvise(MADV_POPULATE_WRITE) (Linux 5.14) takes
// the same faults without writing the arrays' contents, so it is safe beside a thread that writes
// them; where it does not exist, nothing happens and the writer faults the pages as before.
//
// Thread-safety: one owner; start and join from the owner's thread. The owner must join (or
// destroy the Prefault) before it frees or reallocates a range it gave to start.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <thread>
#include <utility>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace dtraced::util {

// Below this a range is left to the writer's own faults (a thread costs more than it saves).
inline constexpr std::size_t kPrefaultMinBytes = std::size_t(8) << 20;

class Prefault {
 public:
  // A range: its start and length in bytes.
  using Range = std::pair<const void*, std::size_t>;

  Prefault() = default;
  Prefault(Prefault&&) noexcept = default;
  Prefault& operator=(Prefault&&) noexcept = default;
  ~Prefault() = default;  // std::jthread joins

  // Joins the previous thread, then maps the ranges of at least kPrefaultMinBytes on a new one (the
  // whole 4 KiB pages inside each range, so neighbouring allocations are not touched). No thread
  // starts when no range is that large or the kernel has no MADV_POPULATE_WRITE.
  void start(const std::array<Range, 2>& ranges) {
    join();
#if defined(__linux__) && defined(MADV_POPULATE_WRITE)
    std::array<Range, 2> pages{};
    bool any = false;
    for (std::size_t i = 0; i < ranges.size(); ++i) {
      const auto [data, bytes] = ranges[i];
      if (data == nullptr || bytes < kPrefaultMinBytes) continue;
      constexpr std::uintptr_t kPage = 4096;
      const auto begin = reinterpret_cast<std::uintptr_t>(data);
      const std::uintptr_t first = (begin + kPage - 1) & ~(kPage - 1);
      const std::uintptr_t last = (begin + bytes) & ~(kPage - 1);
      pages[i] = {reinterpret_cast<const void*>(first), last - first};
      any = true;
    }
    if (!any) return;
    thread_ = std::jthread([pages] {
      for (const auto& [data, bytes] : pages) {
        // A hint: on an error the writer takes its own faults.
        if (bytes > 0) madvise(const_cast<void*>(data), bytes, MADV_POPULATE_WRITE);
      }
    });
#else
    (void)ranges;
#endif
  }

  // Waits for the thread, if one runs.
  void join() {
    if (thread_.joinable()) thread_.join();
  }

 private:
  std::jthread thread_;
};

// A Prefault range over a vector's capacity (after reserve).
template <typename Vector>
Prefault::Range capacity_range(const Vector& v) {
  return {v.data(), v.capacity() * sizeof(typename Vector::value_type)};
}

}  // namespace dtraced::util
