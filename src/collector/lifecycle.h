// dtraced::collector job lifecycle: what happens to a job after its last tile, or its cancellation.
//
// Owns: finishing a job (its image written on the thread pool, then the job marked done in the
// store, then in memory; a failed write tried again after kFinishRetryDelay on the collector's
// clock), the one ordered path of job-state writes to the store, the informational "rendering"
// state sent to it, a cancellation applied in
// memory once the store recorded it, and the release of what an ended job no longer needs
// (scene text, the page view). Durability: a job is marked done in the store only after its image
// was renamed into place.
//
// Thread safety: on the loop only.
#pragma once

#include <chrono>
#include <cstdint>
#include <span>
#include <string_view>

#include "collector/context.h"
#include "store/store.h"
#include "util/result.h"

namespace dtraced::collector {

// A failed image write (disk full, output directory gone) is tried again after this long.
inline constexpr std::chrono::seconds kFinishRetryDelay{5};

// The job-state changes the collector writes to the store. Each is a compare-and-set from the
// states it may follow (store::Store::change_job_state), and all go through the one store writer
// in the order they were posted, so a later write never undoes an answered one: "rendering" only
// follows "queued" (so it never undoes a pause); "paused" follows "queued" or "rendering", and only
// a resume leaves it (to "queued": a restart derives "rendering" from the stored tiles);
// "cancelled" follows an unfinished state; "done" also follows "cancelled" (a cancellation that
// arrived while the last tile was being stored, answered as not applied: see cancel_job) and
// "paused" (the tiles out when it was paused completed the image); nothing but a requeue leaves
// "cancelled", and nothing leaves "done".
enum class StateWrite {
  kRendering,
  kCancelled,
  kDone,
  kRequeued,  // cancelled -> queued
  kPaused,    // queued or rendering -> paused
  kResumed,   // paused -> queued
};

// The store state a write sets, and the states it may replace.
std::string_view target_state(StateWrite write);
std::span<const std::string_view> source_states(StateWrite write);

// Runs `write` for job `id` on `s` (the writer's thread): changed, or the state that stayed.
util::Result<store::StateChange> record_state(store::Store& s, JobId id, StateWrite write, std::int64_t when);

// Tells the store the job is rendering, once (informational: a restart derives the state from
// the stored tiles), without waiting for it.
void persist_rendering(Context& c, JobRecord& job);

// Starts writing the images of an unfinished job's complete frames, in order from the first one not
// written (its next frame must be complete, and no write of the job running); the job is marked
// done once its last frame is written. Frames completed meanwhile are written by the same run.
void start_finish(Context& c, JobId id);

// Applies a cancellation the store has recorded at `when`: no more leases, the job's memory
// released, and an exit_when_done one-shot collector stopping with exit code 1 (once its workers
// have been told, linger.h).
void apply_cancel(Context& c, JobRecord& job, std::int64_t when);

// Frees what only an unfinished job needs.
void release(JobRecord& job);

}  // namespace dtraced::collector
