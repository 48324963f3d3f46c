// dtraced::collector management checks: the refusals of the job-management endpoints (priority,
// requeue, pause, resume, delete), as pure functions of (what the collector knows, what the request carries), like
// checks.h for the others.
//
// Owns: the state rules of docs/http-api.md's "Managing jobs": which job states each change
// accepts (409 with a message naming the job's state otherwise), 404 for an unknown job, 503
// while the collector is stopping, and a requeued job's room among the unfinished ones.
//
// Thread safety: pure functions.
#pragma once

#include "collector/checks.h"
#include "collector/config.h"
#include "collector/jobs.h"
#include "collector/refusal.h"
#include "util/result.h"

namespace dtraced::collector {

// 404 for an unknown job, 409 for a done one (or one whose image is being written), 503 when the
// collector is stopping. A cancelled job's priority may change: a requeue keeps it.
util::Result<void, Refusal> check_priority(JobId id, const JobRecord* job, bool accepting_writes);

// 404 for an unknown job, 409 unless it is cancelled, then the room of a submission of its size
// (check_slots and check_job_room: 503 when the unfinished jobs are at their limits or the
// collector is stopping, 413 for an image over every limit).
util::Result<void, Refusal> check_requeue(JobId id, const JobRecord* job, const Load& load,
                                          const CollectorConfig& config);

// What a pause or resume request does to a job already in the state it asks for: nothing, and
// the answer is its status (so a retried request is harmless).
enum class ChangeAction { kChange, kAlready };

// 404 for an unknown job; kAlready for a paused one; 409 for a done (or finishing) or cancelled
// one; 503 when the collector is stopping.
util::Result<ChangeAction, Refusal> check_pause(JobId id, const JobRecord* job, bool accepting_writes);
// 404 for an unknown job; kAlready for a queued or rendering one; 409 for a done (or finishing)
// or cancelled one; 503 when the collector is stopping.
util::Result<ChangeAction, Refusal> check_resume(JobId id, const JobRecord* job, bool accepting_writes);
// 404 for an unknown job; 409 unless it is done (its image written) or cancelled; 503 when the
// collector is stopping.
util::Result<void, Refusal> check_delete(JobId id, const JobRecord* job, bool accepting_writes);

// 409 "job N is STATE; WHAT", the refusal of a change the job's state does not allow.
Refusal wrong_state(JobId id, std::string_view state, std::string_view what);

}  // namespace dtraced::collector
