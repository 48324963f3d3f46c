// dtraced::util huge pages: a hint that a large array about to be filled should be backed by 2 MiB
// pages. Filling memory the process has not touched yet costs one page fault per 4 KiB page, and
// on the virtual machines we run on a fault is expensive: a scene of 1M spheres touches ~350 MB
// (its description, shapes, materials and BVH), and the faults took about as long as the parsing.
// With transparent huge pages in "madvise" mode (the common default), madvise(MADV_HUGEPAGE) on the
// array's range before the first write makes it one fault per 2 MiB (measured: 2.3 s -> 0.8 s to
// touch 256 MiB here, under load). The result is unchanged either way; where the kernel does not
// support it, nothing happens.
//
// Owns no state: thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>

#if defined(__linux__)
#include <sys/mman.h>
#endif

namespace dtraced::util {

// Below this an array gains little (and a huge page could hold more untouched memory than it saves).
inline constexpr std::size_t kHugePageMinBytes = std::size_t(8) << 20;

// Advises that [data, data + bytes) will be written soon and should use huge pages: only the whole
// 2 MiB-aligned pages inside the range, so neighbouring allocations are not affected. Call it after
// allocating (reserve) and before the first write; afterwards it changes only later faults.
inline void advise_huge_pages(const void* data, std::size_t bytes) {
#if defined(__linux__) && defined(MADV_HUGEPAGE)
  if (data == nullptr || bytes < kHugePageMinBytes) return;
  constexpr std::uintptr_t kHuge = std::uintptr_t(2) << 20;
  const auto begin = reinterpret_cast<std::uintptr_t>(data);
  const std::uintptr_t first = (begin + kHuge - 1) & ~(kHuge - 1);
  const std::uintptr_t last = (begin + bytes) & ~(kHuge - 1);
  if (last > first) madvise(reinterpret_cast<void*>(first), last - first, MADV_HUGEPAGE);  // a hint: errors ignored
#else
  (void)data;
  (void)bytes;
#endif
}

// advise_huge_pages over the capacity of a vector (after reserve, before filling it).
template <typename Vector>
void advise_huge_pages_for(const Vector& v) {
  advise_huge_pages(v.data(), v.capacity() * sizeof(typename Vector::value_type));
}

}  // namespace dtraced::util
