#include "collector/systemd_status.h"

#include <fmt/format.h>

#include "protocol/messages.h"

namespace dtraced::collector {

std::string systemd_status(const MetricsSnapshot& m, WorkerCounts workers) {
  const auto count = [&m](protocol::JobState s) { return m.jobs_by_state[static_cast<std::size_t>(s)]; };
  using protocol::JobState;
  // Paused jobs are named only when there are some: the line stays short in the common case.
  const std::uint64_t paused = count(JobState::kPaused);
  std::string line = fmt::format("jobs: {} queued, {} rendering, {}{} done, {} cancelled", count(JobState::kQueued),
                                 count(JobState::kRendering), paused > 0 ? fmt::format("{} paused, ", paused) : "",
                                 count(JobState::kDone), count(JobState::kCancelled));
  line += fmt::format("; workers: {} active, {} quiet", workers.active, workers.quiet);
  return line;
}

}  // namespace dtraced::collector
