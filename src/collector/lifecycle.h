// dtraced::collector job lifecycle: what happens to a job after its last tile, or its cancellation.
//
// Owns: finishing a job (its image written on the thread pool, then the job marked done in the
// store, then in memory; a failed write tried again after kFinishRetryDelay on the collector's
// clock), the informational "rendering" state sent to the store, a cancellation applied in
// memory once the store recorded it, and the release of what an ended job no longer needs
// (framebuffer, scene text). Durability: a job is marked done in the store only after its image
// was renamed into place.
//
// Thread safety: on the loop only.
#pragma once

#include <chrono>
#include <cstdint>

#include "collector/context.h"

namespace dtraced::collector {

// A failed image write (disk full, output directory gone) is tried again after this long.
inline constexpr std::chrono::seconds kFinishRetryDelay{5};

// Tells the store the job is rendering, once (informational: a restart derives the state from
// the stored tiles), without waiting for it.
void persist_rendering(Context& c, JobRecord& job);

// Starts writing the image of an unfinished job whose every tile is stored.
void start_finish(Context& c, JobId id);

// Applies a cancellation the store has recorded at `when`: no more leases, the job's memory
// released, and an exit_when_done one-shot collector stopping with exit code 1.
void apply_cancel(Context& c, JobRecord& job, std::int64_t when);

// Frees what only an unfinished job needs.
void release(JobRecord& job);

}  // namespace dtraced::collector
