#include "collector/systemd_status.h"

#include <fmt/format.h>

namespace dtraced::collector {

std::string systemd_status(const MetricsSnapshot& m, std::optional<std::size_t> workers_seen) {
  // jobs_by_state is in protocol::JobState's order: queued, rendering, done, cancelled.
  std::string line = fmt::format("jobs: {} queued, {} rendering, {} done, {} cancelled", m.jobs_by_state[0],
                                 m.jobs_by_state[1], m.jobs_by_state[2], m.jobs_by_state[3]);
  if (workers_seen) line += fmt::format("; workers: {} seen", *workers_seen);
  return line;
}

}  // namespace dtraced::collector
