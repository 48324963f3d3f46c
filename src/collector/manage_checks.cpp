#include "collector/manage_checks.h"

#include <fmt/format.h>

namespace dtraced::collector {

Refusal wrong_state(JobId id, std::string_view state, std::string_view what) {
  return Refusal{http::Status::conflict, util::Error(fmt::format("job {} is {}; {}", id, state, what)), {}};
}

util::Result<void, Refusal> check_priority(JobId id, const JobRecord* job, bool accepting_writes) {
  if (job == nullptr) return job_not_found(id);
  if (job->state == protocol::JobState::kDone || job->finishing) {
    return wrong_state(id, "done", "its priority no longer matters");
  }
  if (!accepting_writes) return busy("the collector is stopping");
  return {};
}

util::Result<void, Refusal> check_requeue(JobId id, const JobRecord* job, const Load& load,
                                          const CollectorConfig& config) {
  if (job == nullptr) return job_not_found(id);
  if (job->state != protocol::JobState::kCancelled) {
    return wrong_state(id, job->finishing ? "done" : protocol::to_string(job->state),
                       "only a cancelled job can be requeued");
  }
  if (auto slots = check_job_slots(load, config); !slots) return slots;
  return check_job_room(job->settings.width, job->settings.height, load, config);
}

}  // namespace dtraced::collector
