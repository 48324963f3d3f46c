// dtraced::collector systemd status: the one line `systemctl status dtraced-collector` shows
// (sd_notify STATUS=), from a metrics snapshot. A pure function: thread-safe.
#pragma once

#include <cstddef>
#include <string>

#include "collector/metrics.h"

namespace dtraced::collector {

// The workers the registry knows (collector/workers.h): active ones asked within its quiet time.
struct WorkerCounts {
  std::size_t active = 0;
  std::size_t quiet = 0;
};

// "jobs: 2 queued, 1 rendering, 5 done, 0 cancelled; workers: 3 active, 1 quiet".
std::string systemd_status(const MetricsSnapshot& m, WorkerCounts workers);

}  // namespace dtraced::collector
