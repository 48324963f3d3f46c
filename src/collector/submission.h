// dtraced::collector submissions: a job from its request body to its stored row and its record.
//
// Owns: the steps a new job takes, whether it came over HTTP (POST /v1/jobs) or from the command
// line (the one-shot job, encoded to the same wire format so that it meets the same checks):
// decoding and digesting the body, the row the store keeps, storing scene and row in one
// transaction, and the JobRecord made from a stored row (also at start-up, for every stored job).
//
// Thread safety: pure functions, except insert_scene_and_job, which uses the Store it is given
// (on the store writer's thread, or before the loop runs).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "collector/jobs.h"
#include "protocol/messages.h"
#include "scene/description.h"
#include "store/store.h"
#include "util/result.h"

namespace dtraced::collector {

// A submission decoded, with what the loop needs. Done on the thread pool: a scene may be 64 MiB.
struct PreparedJob {
  protocol::JobSubmit submit;  // its scene is emptied once turned into text
  scene::RenderSettings settings;
  std::uint32_t tile_size = 0;
  std::uint32_t png_bit_depth = 0;
  std::optional<scene::TileRect> crop;  // inside settings' image (checked by the decoder)
  std::string scene_json;               // canonical
  std::string digest;                   // SHA-256 of scene_json, = scene::scene_digest
};

// The decoder's errors when the body is refused.
util::Result<PreparedJob, util::Errors> prepare_job(std::string_view body);

// The settings a prepared job is stored with (and its one-shot key made of).
protocol::JobSettings job_settings(const PreparedJob& job);

// The row a prepared job is stored as, queued, created at `created_unix`.
store::StoredJob job_row(const PreparedJob& job, std::int64_t created_unix);

// Stores a scene and a job in one transaction; returns the job's id.
util::Result<std::int64_t> insert_scene_and_job(store::Store& s, const store::StoredJob& row,
                                                std::string_view scene_json);

// A job record from its stored row (without its stored tiles or scene text); the error names the job
// and the problem.
util::Result<JobRecord> record_from_row(const store::StoredJob& row);

}  // namespace dtraced::collector
