#include "collector/jobs.h"

#include <algorithm>
#include <bit>
#include <cassert>
#include <cmath>
#include <cstring>

#include <fmt/format.h>

#include "image/sequence.h"
#include "util/sha256.h"

namespace dtraced::collector {

static_assert(std::endian::native == std::endian::little,
              "tile blobs and payloads carry little-endian floats; a big-endian collector would need byte swaps");

std::string default_output_name(JobId id, std::uint32_t frames) {
  return frames > 1 ? fmt::format("job-{}-%04d.png", id) : fmt::format("job-{}.png", id);
}

TilePlace tile_place(const JobRecord& job, TileIndex tile) {
  // From the grid itself (a few multiplications), so that it holds for any record.
  const scene::TileGrid grid(job.settings, job.tile_size);
  const auto per_frame = static_cast<TileIndex>(grid.count());
  return {tile / per_frame, grid.rect(tile % per_frame)};
}

scene::RenderSettings frame_settings(const scene::RenderSettings& job_settings, std::uint32_t frame_index) {
  scene::RenderSettings s = job_settings;
  s.frame = protocol::frame_number(job_settings, frame_index);
  s.frames.reset();
  return s;
}

std::optional<std::uint32_t> frame_index_of(const scene::RenderSettings& s, std::uint32_t frame) {
  if (!s.frames) return frame == s.frame ? std::optional<std::uint32_t>(0) : std::nullopt;
  if (frame < s.frames->first || frame > s.frames->last || (frame - s.frames->first) % s.frames->step != 0) {
    return std::nullopt;
  }
  return (frame - s.frames->first) / s.frames->step;
}

std::string frame_output_name(const JobRecord& job, std::uint32_t frame_index) {
  // A name without a frame number is taken as it is (so a single-frame job keeps any name it
  // could always have, "100%.png" included). A sequence's name was checked at submission.
  const auto pattern = image::parse_sequence_pattern(job.output);
  if (!pattern || !pattern->has_number) return job.output;
  return image::frame_path(*pattern, protocol::frame_number(job.settings, frame_index));
}

namespace {

// The tiles of one frame's grid without a pixel in `crop` (none without a crop), ascending: one
// rule for the count init_frames gives the job and the tiles skipped_tiles leaves out of the queue.
std::vector<TileIndex> skipped_in_frame(const scene::TileGrid& grid, const std::optional<scene::TileRect>& crop) {
  std::vector<TileIndex> out;
  if (!crop) return out;
  for (TileIndex t = 0; t < grid.count(); ++t) {
    if (!overlaps_crop(grid.rect(t), crop)) out.push_back(t);
  }
  return out;
}

}  // namespace

bool init_frames(JobRecord& job) {
  const scene::TileGrid grid(job.settings, job.tile_size);
  const std::uint64_t per_frame = grid.count();
  const std::uint64_t frames = protocol::frame_count(job.settings);
  const std::uint64_t indices = per_frame * frames;
  if (per_frame == 0 || indices > protocol::kMaxTilesPerJob) return false;
  if (job.crop) {
    const scene::TileRect& c = *job.crop;
    if (c.width == 0 || c.height == 0 || std::uint64_t{c.x0} + c.width > job.settings.width ||
        std::uint64_t{c.y0} + c.height > job.settings.height) {
      return false;
    }
  }
  const std::uint64_t wanted = per_frame - skipped_in_frame(grid, job.crop).size();
  job.frames_total = static_cast<std::uint32_t>(frames);
  job.tiles_per_frame = static_cast<TileIndex>(wanted);
  job.tile_indices = static_cast<TileIndex>(indices);
  job.tiles_total = static_cast<TileIndex>(wanted * frames);
  job.frame_tiles_done.assign(frames, 0);
  return true;
}

bool overlaps_crop(const scene::TileRect& r, const std::optional<scene::TileRect>& crop) {
  if (!crop) return true;
  const scene::TileRect& c = *crop;
  return r.x0 < c.x0 + c.width && c.x0 < r.x0 + r.width && r.y0 < c.y0 + c.height && c.y0 < r.y0 + r.height;
}

bool tile_of_job(const JobRecord& job, TileIndex tile) {
  return tile < job.tile_indices && (!job.crop || overlaps_crop(tile_place(job, tile).rect, job.crop));
}

std::vector<TileIndex> skipped_tiles(const JobRecord& job) {
  std::vector<TileIndex> skipped;
  if (!job.crop) return skipped;
  const scene::TileGrid grid(job.settings, job.tile_size);
  const auto per_frame = static_cast<TileIndex>(grid.count());
  const std::vector<TileIndex> in_frame = skipped_in_frame(grid, job.crop);
  skipped.reserve(in_frame.size() * job.frames_total);
  for (std::uint32_t f = 0; f < job.frames_total; ++f) {
    for (const TileIndex t : in_frame) skipped.push_back(f * per_frame + t);
  }
  return skipped;
}

std::vector<TileIndex> lease_order(std::span<const float> costs, std::uint32_t frames) {
  std::vector<TileIndex> in_frame(costs.size());
  for (TileIndex t = 0; t < in_frame.size(); ++t) in_frame[t] = t;
  std::stable_sort(in_frame.begin(), in_frame.end(), [costs](TileIndex a, TileIndex b) { return costs[a] > costs[b]; });
  std::vector<TileIndex> order;
  order.reserve(in_frame.size() * frames);
  const auto per_frame = static_cast<TileIndex>(costs.size());
  for (std::uint32_t f = 0; f < frames; ++f) {
    for (const TileIndex t : in_frame) order.push_back(f * per_frame + t);
  }
  return order;
}

store::Blob costs_to_blob(std::span<const float> costs) {
  const auto* bytes = reinterpret_cast<const std::uint8_t*>(costs.data());
  return store::Blob(bytes, bytes + costs.size_bytes());
}

std::optional<std::vector<float>> blob_to_costs(const store::Blob& blob, TileIndex per_frame) {
  if (blob.size() != std::size_t{per_frame} * sizeof(float)) return std::nullopt;
  std::vector<float> costs(per_frame);
  if (per_frame != 0) std::memcpy(costs.data(), blob.data(), blob.size());
  if (!std::all_of(costs.begin(), costs.end(), [](float c) { return std::isfinite(c) && c >= 0; })) {
    return std::nullopt;
  }
  return costs;
}

bool queue_job(WorkQueue& queue, const JobRecord& job, std::span<const TileIndex> stored) {
  std::vector<TileIndex> order;
  if (!job.tile_costs.empty() && std::uint64_t{job.tile_costs.size()} * job.frames_total == job.tile_indices) {
    order = lease_order(job.tile_costs, job.frames_total);
  }
  return queue.add_job(job.id, job.priority, job.tile_indices, stored, skipped_tiles(job), order);
}

store::Blob pixels_to_blob(std::span<const float> rgb, std::span<const std::uint32_t> spp) {
  assert(spp.empty() || spp.size() * 3 == rgb.size());
  // Appended, not sized first: sizing would zero every byte before the copy overwrites it (a
  // pass over each stored tile on the event loop).
  const auto* rgb_bytes = reinterpret_cast<const std::uint8_t*>(rgb.data());
  const auto* spp_bytes = reinterpret_cast<const std::uint8_t*>(spp.data());
  store::Blob blob;
  blob.reserve(rgb.size_bytes() + spp.size_bytes());
  blob.insert(blob.end(), rgb_bytes, rgb_bytes + rgb.size_bytes());
  blob.insert(blob.end(), spp_bytes, spp_bytes + spp.size_bytes());
  return blob;
}

std::optional<TileBlob> blob_to_tile(const store::Blob& blob, std::size_t pixels) {
  const std::size_t rgb_bytes = pixels * 3 * sizeof(float);
  const bool counts = blob.size() == rgb_bytes + pixels * sizeof(std::uint32_t);
  if (blob.size() != rgb_bytes && !counts) return std::nullopt;
  TileBlob t;
  t.rgb.resize(pixels * 3);
  if (pixels != 0) std::memcpy(t.rgb.data(), blob.data(), rgb_bytes);
  if (counts) {
    t.spp.resize(pixels);
    if (pixels != 0) std::memcpy(t.spp.data(), blob.data() + rgb_bytes, pixels * sizeof(std::uint32_t));
  }
  return t;
}

util::Status check_sample_counts(const scene::RenderSettings& settings, const scene::TileRect& rect,
                                 std::span<const std::uint32_t> spp) {
  constexpr std::string_view kField = "/spp";
  const bool adaptive = settings.error_target > 0;
  if (!adaptive) {
    if (spp.empty()) return {};
    return util::Error("the tile carries sample counts, but the job samples uniformly (no error target)",
                       std::string(kField));
  }
  if (spp.empty()) {
    return util::Error("the job samples adaptively, but the tile carries no sample counts", std::string(kField));
  }
  assert(spp.size() == std::size_t{rect.width} * rect.height);
  for (std::size_t i = 0; i < spp.size(); ++i) {
    const std::uint32_t n = spp[i];
    if (!scene::is_valid_sample_count(settings, n)) {
      return util::Error(
          fmt::format("pixel ({}, {}) took {} samples; a pixel takes {} or stops at a checkpoint {} * 2^k below it",
                      rect.x0 + i % rect.width, rect.y0 + i / rect.width, n, settings.samples, settings.min_samples),
          std::string(kField));
    }
  }
  return {};
}

void count_samples(JobRecord& job, std::span<const std::uint32_t> spp) {
  if (job.settings.error_target > 0) job.spp.add(spp);
}

void copy_tile(image::ImageRGBf& image, const scene::TileRect& rect, std::span<const float> rgb) {
  copy_tile(image, scene::TileRect{0, 0, image.width, image.height}, rect, rgb);
}

void copy_tile(image::ImageRGBf& image, const scene::TileRect& window, const scene::TileRect& rect,
               std::span<const float> rgb) {
  assert(window.width == image.width && window.height == image.height);
  assert(rgb.size() == std::size_t{rect.width} * rect.height * 3);
  const std::uint32_t x0 = std::max(rect.x0, window.x0);
  const std::uint32_t y0 = std::max(rect.y0, window.y0);
  const std::uint32_t x1 = std::min(rect.x0 + rect.width, window.x0 + window.width);
  const std::uint32_t y1 = std::min(rect.y0 + rect.height, window.y0 + window.height);
  if (x0 >= x1 || y0 >= y1) return;
  const std::size_t row_floats = std::size_t{rect.width} * 3;
  const std::size_t copy_bytes = std::size_t{x1 - x0} * 3 * sizeof(float);
  for (std::uint32_t y = y0; y < y1; ++y) {
    const float* from = rgb.data() + (y - rect.y0) * row_floats + std::size_t{x0 - rect.x0} * 3;
    std::memcpy(image.pixel(x0 - window.x0, y - window.y0), from, copy_bytes);
  }
}

bool frame_complete(const JobRecord& job, std::uint32_t frame_index) {
  return frame_index < job.frame_tiles_done.size() && job.frame_tiles_done[frame_index] == job.tiles_per_frame;
}

protocol::JobStatus job_status(const JobRecord& job, std::int64_t now_unix, TimePoint now) {
  protocol::JobStatus s;
  s.id = job.id;
  s.state = job.state;
  s.output = job.output;
  s.priority = job.priority;
  s.width = job.settings.width;
  s.height = job.settings.height;
  s.samples = job.settings.samples;
  s.tiles_done = job.tiles_done;
  s.tiles_total = job.tiles_total;
  s.digest = job.digest;
  if (job.frames_total > 1) {
    protocol::FrameProgress f;
    f.frames_total = job.frames_total;
    const bool done = job.state == protocol::JobState::kDone;
    f.frames_done = done ? job.frames_total : job.frames_written;
    const std::uint32_t current = std::min(f.frames_done, job.frames_total - 1);
    f.frame = protocol::frame_number(job.settings, current);
    f.frame_tiles_total = job.tiles_per_frame;
    f.frame_tiles_done =
        done || current >= job.frame_tiles_done.size() ? job.tiles_per_frame : job.frame_tiles_done[current];
    s.frames = f;
  }
  if (job.tiles_done > 0) {
    if (job.settings.error_target <= 0) {
      s.mean_spp = static_cast<double>(job.settings.samples);
    } else if (job.spp.known && !job.spp_pending && job.spp.pixels > 0) {
      s.mean_spp = static_cast<double>(job.spp.sum) / static_cast<double>(job.spp.pixels);
    }
  }
  const std::int64_t end = job.unfinished() ? now_unix : job.finished_unix;
  s.elapsed_s = static_cast<double>(std::max<std::int64_t>(0, end - job.created_unix));
  if (job.state == protocol::JobState::kDone) {
    s.eta_s = 0.0;
  } else if (job.unfinished() && job.state != protocol::JobState::kPaused && job.stored_this_run > 0 &&
             job.first_lease) {
    const double seconds = std::chrono::duration<double>(now - *job.first_lease).count();
    if (seconds > 0) {
      const double rate = job.stored_this_run / seconds;  // tiles per second
      s.eta_s = static_cast<double>(job.tiles_total - job.tiles_done) / rate;
    }
  }
  return s;
}

std::string one_shot_client_key(std::string_view digest, const protocol::JobSettings& settings, std::uint32_t tile_size,
                                std::string_view output) {
  // Newlines separate the parts: none of them can contain one (hex, JSON without whitespace, a
  // number, a checked file name).
  const std::string text = fmt::format("dtraced-one-shot-v1\n{}\n{}\n{}\n{}", digest,
                                       protocol::encode_settings(settings), tile_size, output);
  return util::sha256_hex(text);
}

util::Result<std::vector<TileIndex>> load_stored_tiles(store::Store& s, JobRecord& rec) {
  std::vector<TileIndex> stored;
  rec.restored.assign(rec.tile_indices, false);
  rec.frame_tiles_done.assign(rec.frames_total, 0);
  // One tile in memory at a time: a large job's pixels (1.5 GiB at 16384 x 8192) never are at once.
  // A tile the store cannot read back is left out (and logged there), so it is rendered again.
  const util::Status st = s.visit_tiles(static_cast<std::int64_t>(rec.id), [&](store::StoredTile&& t) -> util::Status {
    if (t.tile >= rec.tile_indices) {
      return util::Error(fmt::format("{}: job {}: stored tile {} is out of range ({} tiles)", s.path(), rec.id, t.tile,
                                     rec.tile_indices));
    }
    if (!tile_of_job(rec, t.tile)) {
      return util::Error(
          fmt::format("{}: job {}: stored tile {} lies outside the job's crop", s.path(), rec.id, t.tile));
    }
    const TilePlace place = tile_place(rec, t.tile);
    const scene::TileRect& rect = place.rect;
    const std::size_t pixels = std::size_t{rect.width} * rect.height;
    auto stored_tile = blob_to_tile(t.pixels, pixels);
    if (!stored_tile) {
      return util::Error(fmt::format(
          "{}: job {}: stored tile {} holds {} bytes; its {}x{} rectangle needs {} (or {} with sample counts)",
          s.path(), rec.id, t.tile, t.pixels.size(), rect.width, rect.height, pixels * 12, pixels * 16));
    }
    ++rec.frame_tiles_done[place.frame_index];
    count_samples(rec, stored_tile->spp);
    stored.push_back(t.tile);
    rec.restored[t.tile] = true;
    return util::Status();
  });
  if (!st) return st.error();
  return stored;
}

}  // namespace dtraced::collector
