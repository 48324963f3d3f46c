#include "collector/submission.h"

#include <utility>

#include <fmt/format.h>

#include "scene/digest.h"
#include "scene/tiling.h"
#include "util/log.h"
#include "util/sha256.h"

namespace dtraced::collector {

util::Result<PreparedJob, util::Errors> prepare_job(std::string_view body) {
  auto decoded = protocol::decode_job_submit(body);
  if (!decoded) return std::move(decoded).error();
  PreparedJob p;
  p.submit = std::move(decoded).value();
  p.settings = protocol::effective_settings(p.submit);
  p.tile_size = scene::tile_size_or_default(p.submit.overrides);
  p.png_bit_depth = scene::png_bit_depth_or_default(p.submit.overrides);
  p.crop = p.submit.overrides.crop;
  p.scene_json = scene::canonical_json(p.submit.scene);
  p.digest = util::sha256_hex(p.scene_json);  // = scene::scene_digest, without a second serialisation
  p.submit.scene = {};
  return p;
}

protocol::JobSettings job_settings(const PreparedJob& job) { return {job.settings, job.png_bit_depth, job.crop}; }

store::StoredJob job_row(const PreparedJob& job, std::int64_t created_unix) {
  store::StoredJob row;
  row.digest = job.digest;
  row.settings_json = protocol::encode_settings(job_settings(job));
  row.output = job.submit.output;  // "" stands for job-<id>.png
  row.priority = job.submit.priority;
  row.tile_size = job.tile_size;
  row.state = std::string(store::kJobQueued);
  row.created_unix = created_unix;
  row.tile_costs = costs_to_blob(job.submit.tile_costs);
  return row;
}

util::Result<std::int64_t> insert_scene_and_job(store::Store& s, const store::StoredJob& row,
                                                std::string_view scene_json) {
  std::int64_t id = 0;
  const util::Status status = s.transaction([&]() -> util::Status {
    if (util::Status put = s.put_scene(row.digest, scene_json); !put) return put;
    util::Result<std::int64_t> inserted = s.insert_job(row);
    if (!inserted) return inserted.error();
    id = inserted.value();
    return {};
  });
  if (!status) return status.error();
  return id;
}

util::Result<JobRecord> record_from_row(const store::StoredJob& row) {
  auto settings = protocol::decode_settings(row.settings_json);
  if (!settings) {
    return util::Error(
        fmt::format("job {}: stored settings are unreadable: {}", row.id, util::to_string(settings.error())));
  }
  const auto state = protocol::job_state_from_string(row.state);
  if (!state) return util::Error(fmt::format("job {}: unknown state '{}'", row.id, row.state));
  if (row.tile_size < scene::kMinTileSize || row.tile_size > scene::kMaxTileSize) {
    return util::Error(fmt::format("job {}: tile size {} is out of range", row.id, row.tile_size));
  }
  if (row.id <= 0 || static_cast<std::uint64_t>(row.id) > protocol::kMaxId) {
    return util::Error(fmt::format("job id {} is out of range", row.id));
  }
  JobRecord rec;
  rec.id = static_cast<JobId>(row.id);
  rec.digest = row.digest;
  rec.settings = settings.value().render;
  rec.png_bit_depth = settings.value().png_bit_depth;
  rec.crop = settings.value().crop;  // inside the image: decode_settings checked it
  rec.priority = row.priority;
  rec.tile_size = row.tile_size;
  if (!init_frames(rec)) {
    const std::uint64_t per_frame = scene::TileGrid(rec.settings, row.tile_size).count();
    return util::Error(fmt::format("job {}: {} tiles x {} frames, outside [1, {}] tiles", row.id, per_frame,
                                   protocol::frame_count(rec.settings), protocol::kMaxTilesPerJob));
  }
  if (!row.tile_costs.empty()) {
    // Checked at submission; a blob that no longer fits only loses the order (row order then).
    auto costs = blob_to_costs(row.tile_costs, rec.tile_indices / rec.frames_total);
    if (costs) {
      rec.tile_costs = std::move(*costs);
    } else {
      util::log_warn("job {}: stored tile costs ({} bytes) do not fit its {} tiles per frame; leasing in row order",
                     row.id, row.tile_costs.size(), rec.tile_indices / rec.frames_total);
    }
  }
  rec.output = row.output.empty() ? default_output_name(rec.id, rec.frames_total) : row.output;
  rec.state = *state;
  rec.created_unix = row.created_unix;
  rec.finished_unix = row.finished_unix;
  rec.tiles_done = rec.state == protocol::JobState::kDone ? rec.tiles_total : 0;
  if (rec.state == protocol::JobState::kDone) rec.frames_written = rec.frames_total;
  return rec;
}

}  // namespace dtraced::collector
