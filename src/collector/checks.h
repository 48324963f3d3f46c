// dtraced::collector checks: every refusal a handler can give before it changes anything, as pure
// functions of (what the collector knows, what the request carries) returning a verdict.
//
// Owns: the rules of README.md's "HTTP API" that decide 4xx and 503 answers: a submission's room
// (unfinished jobs and pixels), a cancellation's state rules, and a tile upload's six checks (the
// payload's format and finite, non-negative pixels; the URL against the payload; the job known and not
// cancelled; the tile in range; the rectangle the job's; the sample counts the job's). Each
// handler runs its check, then does one effectful step (store, queue, image), so adding a route
// means adding one check here and one small handler file. Nothing here touches the queue, the
// store or the loop: tests call these directly.
//
// Thread safety: pure functions. check_tile_payload also runs on the thread pool (large payloads).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string_view>

#include "collector/config.h"
#include "collector/jobs.h"
#include "collector/refusal.h"
#include "collector/routes.h"
#include "protocol/tile_payload.h"
#include "util/result.h"

namespace dtraced::collector {

// ---- submissions --------------------------------------------------------------------------------

// What the collector holds when a submission arrives.
struct Load {
  std::size_t unfinished_jobs = 0;
  std::uint64_t unfinished_pixels = 0;
  bool accepting_writes = true;  // the store writer runs and no stop has begun
};

// Before the body is parsed: 503 when the unfinished jobs are at config.max_unfinished_jobs.
util::Result<void, Refusal> check_job_slots(const Load& load, const CollectorConfig& config);

// Once the body is parsed: 413 (/width) for an image larger than all the pixels the collector may
// hold, 503 when the unfinished jobs hold too many already, 503 when the collector is stopping.
util::Result<void, Refusal> check_job_room(std::uint32_t width, std::uint32_t height, const Load& load,
                                           const CollectorConfig& config);

// ---- cancellation -------------------------------------------------------------------------------

enum class CancelAction {
  kCancel,            // record the cancellation, then apply it
  kAlreadyCancelled,  // answer the job's status, change nothing
};

// 404 for an unknown job, 409 for a finished one (done, or its image being written), 503 when the
// collector is stopping.
util::Result<CancelAction, Refusal> check_cancel(JobId id, const JobRecord* job, bool accepting_writes);

// ---- tile uploads --------------------------------------------------------------------------------

// What does not depend on the job (400): the payload's format and checksum, then finite and
// non-negative pixels. The renderer never produces NaN, infinity or negative radiance: such a tile
// comes from a broken worker, and accepting it would make it the stored truth.
util::Result<protocol::TilePayload, Refusal> check_tile_payload(std::string_view body);

enum class TileAction {
  kStore,    // a new result, or a duplicate for the store to compare
  kJobGone,  // the job is unknown or cancelled: answer job_gone (410)
};

// Given a payload that passed check_tile_payload: 400 when the URL and the payload disagree on job
// (/job) or tile (/tile); job_gone for an unknown or cancelled job; 400 when the tile is past the
// job's last (/tile), its rectangle is not the job's (/rect), or its sample counts do not fit the
// job (/spp).
util::Result<TileAction, Refusal> check_tile(const Route& route, const JobRecord* job,
                                             const protocol::TilePayload& payload);

}  // namespace dtraced::collector
