#include "util/cpus.h"

#include <sched.h>

#include <algorithm>
#include <cstddef>
#include <thread>

namespace dtraced::util {

std::uint32_t usable_cpus() {
  // The kernel refuses a mask smaller than its own (EINVAL): grow it up to a bound well past
  // any machine's CPU count.
  for (int cpus = 1024; cpus <= (1 << 18); cpus *= 4) {
    cpu_set_t* set = CPU_ALLOC(cpus);
    if (set == nullptr) break;
    const std::size_t bytes = CPU_ALLOC_SIZE(cpus);
    CPU_ZERO_S(bytes, set);
    const bool ok = ::sched_getaffinity(0, bytes, set) == 0;
    const int count = ok ? CPU_COUNT_S(bytes, set) : 0;
    CPU_FREE(set);
    if (ok && count > 0) return static_cast<std::uint32_t>(count);
    if (ok) break;
  }
  return std::max(1u, std::thread::hardware_concurrency());
}

}  // namespace dtraced::util
