// dtraced::util CPUs this process may run on: what "every core" means for a render.
//
// A worker started by a batch scheduler (Slurm), in a cgroup cpuset or a container, or under
// `taskset`, is given some of the machine's CPUs; its affinity mask says which. Threads beyond
// that mask only take turns on the same CPUs. So the default thread count is the mask's size,
// not std::thread::hardware_concurrency() (every CPU of the machine).
//
// Stateless; thread-safe.
#pragma once

#include <cstdint>

namespace dtraced::util {

// The CPUs in this process's affinity mask (sched_getaffinity), at least 1; the machine's CPU
// count where the mask cannot be read.
std::uint32_t usable_cpus();

}  // namespace dtraced::util
