#include "collector/linger.h"

#include <algorithm>

namespace dtraced::collector {

Duration linger_bound(const QueueConfig& queue) { return std::max(kFinishedLinger, 2 * queue.max_retry_after); }

std::vector<WorkerId> workers_to_tell(const WorkerRegistry& registry, TimePoint now) {
  std::vector<WorkerId> out;
  for (const WorkerView& w : registry.list(now)) {
    if (!w.quiet) out.push_back(w.id);
  }
  return out;
}

}  // namespace dtraced::collector
