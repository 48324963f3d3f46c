#include "collector/systemd_status.h"

#include <fmt/format.h>

namespace dtraced::collector {

std::string systemd_status(const MetricsSnapshot& m, WorkerCounts workers) {
  // jobs_by_state is in protocol::JobState's order: queued, rendering, done, cancelled.
  std::string line = fmt::format("jobs: {} queued, {} rendering, {} done, {} cancelled", m.jobs_by_state[0],
                                 m.jobs_by_state[1], m.jobs_by_state[2], m.jobs_by_state[3]);
  line += fmt::format("; workers: {} active, {} quiet", workers.active, workers.quiet);
  return line;
}

}  // namespace dtraced::collector
