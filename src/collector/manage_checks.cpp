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

namespace {

// The state a client sees: a job whose image is being written is as good as done.
std::string_view shown_state(const JobRecord& job) { return job.finishing ? "done" : protocol::to_string(job.state); }

bool ended(const JobRecord& job) {
  return job.finishing || job.state == protocol::JobState::kDone || job.state == protocol::JobState::kCancelled;
}

}  // namespace

util::Result<ChangeAction, Refusal> check_pause(JobId id, const JobRecord* job, bool accepting_writes) {
  if (job == nullptr) return job_not_found(id);
  if (ended(*job)) return wrong_state(id, shown_state(*job), "only a queued or rendering job can be paused");
  if (job->state == protocol::JobState::kPaused) return ChangeAction::kAlready;
  if (!accepting_writes) return busy("the collector is stopping");
  return ChangeAction::kChange;
}

util::Result<ChangeAction, Refusal> check_resume(JobId id, const JobRecord* job, bool accepting_writes) {
  if (job == nullptr) return job_not_found(id);
  if (ended(*job)) return wrong_state(id, shown_state(*job), "only a paused job can be resumed");
  if (job->state != protocol::JobState::kPaused) return ChangeAction::kAlready;
  if (!accepting_writes) return busy("the collector is stopping");
  return ChangeAction::kChange;
}

util::Result<void, Refusal> check_delete(JobId id, const JobRecord* job, bool accepting_writes) {
  if (job == nullptr) return job_not_found(id);
  if (!ended(*job) || job->finishing) {
    return wrong_state(id, shown_state(*job),
                       job->finishing ? "its image is being written; delete it once it is done"
                                      : "only a done or cancelled job can be deleted (cancel it first)");
  }
  if (!accepting_writes) return busy("the collector is stopping");
  return {};
}

}  // namespace dtraced::collector
