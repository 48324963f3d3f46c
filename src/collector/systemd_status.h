// dtraced::collector systemd status: the one line `systemctl status dtraced-collector` shows
// (sd_notify STATUS=), from a metrics snapshot. A pure function: thread-safe.
#pragma once

#include <cstddef>
#include <optional>
#include <string>

#include "collector/metrics.h"

namespace dtraced::collector {

// "jobs: 2 queued, 1 rendering, 5 done, 0 cancelled", then "; workers: N seen" when the worker
// count is known (nullopt until the collector keeps a worker registry).
std::string systemd_status(const MetricsSnapshot& m, std::optional<std::size_t> workers_seen);

}  // namespace dtraced::collector
