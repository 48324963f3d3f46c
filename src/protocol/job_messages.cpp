// The job messages: submission (POST /v1/jobs), its answer, and job statuses and lists.
#include <array>
#include <cassert>
#include <cfloat>
#include <limits>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "image/sequence.h"
#include "protocol/codec.h"
#include "protocol/messages.h"
#include "scene/digest.h"
#include "scene/scene_json.h"

namespace dtraced::protocol {
namespace {

namespace json = boost::json;
using namespace detail;

// Indexed by JobState.
constexpr std::array<std::string_view, 5> kJobStateNames = {"queued", "rendering", "done", "cancelled", "paused"};

constexpr std::array<std::string_view, 5> kSubmitOwnKeys = {"scene", "output", "priority", "tile_size", "tile_costs"};
constexpr auto kSubmitKeys = jsonio::join_keys(jsonio::join_keys(kSubmitOwnKeys, scene::kRenderKeys),
                                               std::array<std::string_view, 2>{"png_bit_depth", "crop"});
constexpr std::array<std::string_view, 2> kJobCreatedKeys = {"id", "digest"};
constexpr std::array<std::string_view, 19> kJobStatusKeys = {
    "id",          "state",   "output",           "priority",         "width",
    "height",      "samples", "tiles_done",       "tiles_total",      "elapsed_s",
    "eta_s",       "digest",  "mean_spp",         "no_worker_s",      "frames_total",
    "frames_done", "frame",   "frame_tiles_done", "frame_tiles_total"};
constexpr std::array<std::string_view, 1> kJobListKeys = {"jobs"};
constexpr std::array<std::string_view, 1> kJobPriorityKeys = {"priority"};
constexpr std::array<std::string_view, 4> kJobDeletedKeys = {"id", "tiles", "image", "image_error"};
constexpr std::array<std::string_view, 4> kImageFates = {"kept", "deleted", "none", "failed"};

// The scene of a submission: loaded from the embedded object, with paths under "/scene".
void read_submitted_scene(Fields& f, scene::SceneDesc& out) {
  const json::value* s = f.get("scene", Need::kRequired);
  if (s == nullptr) return;
  if (!s->is_object()) {
    f.reader().error(f.path("scene"), fmt::format("expected an object (a scene), got {}", jsonio::kind_name(*s)));
    return;
  }
  // The loader reads text, so the embedded object goes back to text: exact, because the reader
  // converted its numbers with correct rounding and Boost writes the shortest digits that read
  // back to the same double. The body's size limit already bounds it.
  scene::LoadOptions options;
  options.max_bytes = std::numeric_limits<std::uint64_t>::max();
  options.max_errors = kMaxDecodeErrors;
  // A submission carries its meshes inline: a "file" would make the collector read a file of its
  // own host into the scene, and from there serve it to any worker.
  options.allow_mesh_files = false;
  scene::LoadResult loaded = scene::load_scene_string(json::serialize(*s), "", options);
  for (util::Error& e : loaded.errors) f.reader().error("/scene" + e.path, std::move(e.message));
  if (loaded.ok()) out = std::move(*loaded.scene);
}

// The submission's overrides: each an optional top-level key, with the limits of scene files.
void read_overrides(Fields& f, scene::Overrides& o) {
  f.integer("tile_size", o.tile_size, scene::kMinTileSize, scene::kMaxTileSize);
  scene::read_render_settings(f, o, Need::kOptional);
  if (f.has("png_bit_depth")) {
    std::uint32_t bits = scene::kDefaultPngBitDepth;
    if (read_bit_depth(f, bits)) o.png_bit_depth = bits;
  }
  read_crop(f, o.crop);
}

// The optional "tile_costs": one finite number in [0, kMaxTileCost] per tile of a frame's grid.
void read_tile_costs(Fields& f, std::size_t per_frame, std::vector<float>& out) {
  const json::value* v = f.get("tile_costs", Need::kOptional);
  if (v == nullptr) return;
  Reader& r = f.reader();
  const Path at = f.path("tile_costs");
  const json::array* a = r.array(*v, at, kMaxTilesPerJob, "tile costs");
  if (a == nullptr) return;
  if (a->size() != per_frame) {
    r.error(at, fmt::format("has {} costs; the job has {} tiles per frame (one cost each)", a->size(), per_frame));
    return;
  }
  std::vector<float> costs;
  costs.reserve(per_frame);
  const std::size_t before = r.error_count();
  for (std::size_t i = 0; i < a->size(); ++i) {
    const std::optional<double> d = r.number((*a)[i], at.index(i), 0.0, double{kMaxTileCost});
    costs.push_back(d ? static_cast<float>(*d) : 0.0f);
  }
  if (r.error_count() == before) out = std::move(costs);
}

void read_job_submit(Fields& f, JobSubmit& m) {
  read_submitted_scene(f, m.scene);
  read_output(f, m.output, Need::kOptional);
  f.integer("priority", m.priority, kMinPriority, kMaxPriority, Need::kOptional);
  read_overrides(f, m.overrides);
  if (f.reader().failed()) return;

  const scene::RenderSettings s = effective_settings(m);
  // Against the image the overrides make: "--width 64 --crop ..." is checked at width 64.
  if (m.overrides.crop) check_crop_inside(f, *m.overrides.crop, s.width, s.height);
  const std::uint32_t tile_size = scene::tile_size_or_default(m.overrides);
  const std::uint64_t per_frame = scene::TileGrid(s, tile_size).count();
  const std::uint64_t frames = frame_count(s);
  if (per_frame * frames > kMaxTilesPerJob) {
    const std::string times = frames > 1 ? fmt::format(" x {} frames", frames) : std::string();
    f.reader().error(f.path(frames > 1 && !f.has("tile_size") ? "frames" : "tile_size"),
                     fmt::format("a {}x{} image in tiles of {} is {} tiles{}, more than the limit of {}", s.width,
                                 s.height, tile_size, per_frame, times, kMaxTilesPerJob));
  }
  if (per_frame <= kMaxTilesPerJob) read_tile_costs(f, static_cast<std::size_t>(per_frame), m.tile_costs);
  // A sequence's output is a pattern with the frame number (or a GIF, one file for all frames).
  if (frames > 1 && !m.output.empty()) {
    if (util::Status pattern = image::check_sequence_path(m.output, static_cast<std::uint32_t>(frames)); !pattern) {
      f.reader().error(f.path("output"), pattern.error().message);
    }
  }
}

// The frame progress of a sequence's status: every key or none.
void read_frame_progress(Fields& f, JobStatus& s) {
  if (!f.has("frames_total")) return;
  FrameProgress p;
  Reader& r = f.reader();
  const std::size_t before = r.error_count();
  const std::int64_t max_frame = std::numeric_limits<std::uint32_t>::max();
  f.integer("frames_total", p.frames_total, 1, scene::kMaxFrames);
  f.integer("frames_done", p.frames_done, 0, scene::kMaxFrames);
  f.integer("frame", p.frame, 0, max_frame);
  f.integer("frame_tiles_done", p.frame_tiles_done, 0, kMaxTilesPerJob);
  f.integer("frame_tiles_total", p.frame_tiles_total, 1, kMaxTilesPerJob);
  if (r.error_count() != before) return;
  if (p.frames_done > p.frames_total) {
    r.error(f.path("frames_done"), fmt::format("must be <= frames_total (got {} > {})", p.frames_done, p.frames_total));
  } else if (p.frame_tiles_done > p.frame_tiles_total) {
    r.error(f.path("frame_tiles_done"),
            fmt::format("must be <= frame_tiles_total (got {} > {})", p.frame_tiles_done, p.frame_tiles_total));
  } else {
    s.frames = p;
  }
}

// The number at `key` in [lo, hi], or null (`out` stays unset).
void read_nullable_number(Fields& f, std::string_view key, std::optional<double>& out, double lo, double hi,
                          Need need) {
  const json::value* v = f.get(key, need);
  if (v != nullptr && !v->is_null()) f.number(key, out, lo, hi);
}

void read_job_status(Fields& f, JobStatus& s) {
  Reader& r = f.reader();
  const std::size_t before = r.error_count();
  f.integer("id", s.id, 1, kMaxId);
  f.read("state", s.state, Need::kRequired, [&r](const json::value& v, const Path& at) {
    const auto i = r.choice(v, at, kJobStateNames, "state", "states");
    return i ? std::optional<JobState>(static_cast<JobState>(*i)) : std::nullopt;
  });
  read_output(f, s.output, Need::kRequired);
  f.integer("priority", s.priority, kMinPriority, kMaxPriority);
  f.integer("width", s.width, 1, scene::kMaxImageSide);
  f.integer("height", s.height, 1, scene::kMaxImageSide);
  f.integer("samples", s.samples, 1, scene::kMaxSamples);
  f.integer("tiles_done", s.tiles_done, 0, kMaxTilesPerJob);
  f.integer("tiles_total", s.tiles_total, 1, kMaxTilesPerJob);
  f.number("elapsed_s", s.elapsed_s, 0, DBL_MAX);
  read_nullable_number(f, "eta_s", s.eta_s, 0, DBL_MAX, Need::kRequired);
  read_digest(f, s.digest);
  // Optional, so that an older collector's answer still reads.
  read_nullable_number(f, "mean_spp", s.mean_spp, 1, scene::kMaxSamples, Need::kOptional);
  read_nullable_number(f, "no_worker_s", s.no_worker_s, 0, DBL_MAX, Need::kOptional);
  read_frame_progress(f, s);
  if (r.error_count() == before && s.tiles_done > s.tiles_total) {
    r.error(f.path("tiles_done"), fmt::format("must be <= tiles_total (got {} > {})", s.tiles_done, s.tiles_total));
  }
}

json::object job_status_object(const JobStatus& s) {
  json::object o;
  o["id"] = s.id;
  o["state"] = to_string(s.state);
  o["output"] = s.output;
  o["priority"] = s.priority;
  o["width"] = s.width;
  o["height"] = s.height;
  o["samples"] = s.samples;
  o["tiles_done"] = s.tiles_done;
  o["tiles_total"] = s.tiles_total;
  o["elapsed_s"] = jsonio::exact_number(s.elapsed_s);
  o["eta_s"] = s.eta_s ? jsonio::exact_number(*s.eta_s) : json::value(nullptr);
  o["digest"] = s.digest;
  o["mean_spp"] = s.mean_spp ? jsonio::exact_number(*s.mean_spp) : json::value(nullptr);
  o["no_worker_s"] = s.no_worker_s ? jsonio::exact_number(*s.no_worker_s) : json::value(nullptr);
  if (s.frames) {
    o["frames_total"] = s.frames->frames_total;
    o["frames_done"] = s.frames->frames_done;
    o["frame"] = s.frames->frame;
    o["frame_tiles_done"] = s.frames->frame_tiles_done;
    o["frame_tiles_total"] = s.frames->frame_tiles_total;
  }
  return o;
}

}  // namespace

// ---- JobSubmit -----------------------------------------------------------------------------

scene::RenderSettings effective_settings(const JobSubmit& submit) {
  return scene::apply(submit.overrides, submit.scene.render);
}

std::uint32_t frame_count(const scene::RenderSettings& s) { return scene::frame_range(s).count(); }

std::uint32_t frame_number(const scene::RenderSettings& s, std::uint32_t index) {
  return scene::frame_range(s).at(index);
}

std::string encode(const JobSubmit& m) {
  json::object o;
  // The scene travels in its canonical form, which reloads to the identical SceneDesc.
  jsonio::Document doc = jsonio::parse_strict(scene::canonical_json(m.scene), scene::kMaxJsonDepth, 1);
  assert(doc.parsed && doc.errors.empty());
  o["scene"] = std::move(doc.value);
  if (!m.output.empty()) o["output"] = m.output;
  o["priority"] = m.priority;
  const scene::Overrides& v = m.overrides;
  if (v.tile_size) o["tile_size"] = *v.tile_size;
  if (v.width) o["width"] = *v.width;
  if (v.height) o["height"] = *v.height;
  if (v.samples) o["samples"] = *v.samples;
  if (v.max_depth) o["max_depth"] = *v.max_depth;
  if (v.seed) o["seed"] = *v.seed;
  if (v.frame) o["frame"] = *v.frame;
  if (v.background) o["background"] = scene::vec3_value(*v.background);
  if (v.error_target) o["error_target"] = jsonio::exact_number(*v.error_target);
  if (v.min_samples) o["min_samples"] = *v.min_samples;
  if (v.branch_cutoff) o["branch_cutoff"] = jsonio::exact_number(*v.branch_cutoff);
  if (v.png_bit_depth) o["png_bit_depth"] = *v.png_bit_depth;
  if (v.frames) o["frames"] = scene::frame_range_value(*v.frames);
  if (v.fps) o["fps"] = jsonio::exact_number(*v.fps);
  if (v.exposure) o["exposure"] = jsonio::exact_number(*v.exposure);
  if (v.tone) o["tone"] = image::to_string(*v.tone);
  if (v.crop) o["crop"] = crop_object(*v.crop);
  if (!m.tile_costs.empty()) {
    json::array costs;
    costs.reserve(m.tile_costs.size());
    for (const float c : m.tile_costs) costs.emplace_back(static_cast<double>(c));
    o["tile_costs"] = std::move(costs);
  }
  return jsonio::to_text(o);
}

Decoded<JobSubmit> decode_job_submit(std::string_view text) {
  return decode_object<JobSubmit>(text, kMaxJobSubmitBytes, kMaxJobSubmitDepth, kSubmitKeys, read_job_submit);
}

// ---- JobCreated ----------------------------------------------------------------------------

std::string encode(const JobCreated& m) { return jsonio::to_text(json::object{{"id", m.id}, {"digest", m.digest}}); }

Decoded<JobCreated> decode_job_created(std::string_view text) {
  return decode_object<JobCreated>(text, kMaxMessageBytes, kMaxMessageDepth, kJobCreatedKeys,
                                   [](Fields& f, JobCreated& m) {
                                     f.integer("id", m.id, 1, kMaxId);
                                     read_digest(f, m.digest);
                                   });
}

// ---- JobStatus, JobList --------------------------------------------------------------------

std::string_view to_string(JobState state) { return kJobStateNames[static_cast<std::size_t>(state)]; }

std::optional<JobState> job_state_from_string(std::string_view text) {
  for (std::size_t i = 0; i < kJobStateNames.size(); ++i) {
    if (text == kJobStateNames[i]) return static_cast<JobState>(i);
  }
  return std::nullopt;
}

std::string encode(const JobStatus& m) { return jsonio::to_text(job_status_object(m)); }

Decoded<JobStatus> decode_job_status(std::string_view text) {
  return decode_object<JobStatus>(text, kMaxMessageBytes, kMaxMessageDepth, kJobStatusKeys, read_job_status);
}

std::string encode(const JobList& m) {
  json::array jobs;
  jobs.reserve(m.jobs.size());
  for (const JobStatus& s : m.jobs) jobs.push_back(job_status_object(s));
  json::object o;
  o["jobs"] = std::move(jobs);
  return jsonio::to_text(o);
}

Decoded<JobList> decode_job_list(std::string_view text) {
  return decode_object<JobList>(text, kMaxJobListBytes, kMaxMessageDepth, kJobListKeys, [](Fields& f, JobList& m) {
    read_object_array(f, "jobs", kMaxListedJobs, kJobStatusKeys, m.jobs, read_job_status);
  });
}

// ---- JobPriority ---------------------------------------------------------------------------

std::string encode(const JobPriority& m) { return jsonio::to_text(json::object{{"priority", m.priority}}); }

Decoded<JobPriority> decode_job_priority(std::string_view text) {
  return decode_object<JobPriority>(
      text, kMaxMessageBytes, kMaxMessageDepth, kJobPriorityKeys,
      [](Fields& f, JobPriority& m) { f.integer("priority", m.priority, kMinPriority, kMaxPriority); });
}

// ---- JobDeleted ----------------------------------------------------------------------------

std::string encode(const JobDeleted& m) {
  json::object o{{"id", m.id}, {"tiles", m.tiles}, {"image", m.image}};
  if (!m.image_error.empty()) o["image_error"] = m.image_error;
  return jsonio::to_text(o);
}

Decoded<JobDeleted> decode_job_deleted(std::string_view text) {
  return decode_object<JobDeleted>(
      text, kMaxMessageBytes, kMaxMessageDepth, kJobDeletedKeys, [](Fields& f, JobDeleted& m) {
        f.integer("id", m.id, 1, kMaxId);
        f.integer("tiles", m.tiles, 0, kMaxTilesPerJob);
        f.read("image", m.image, Need::kRequired, [&f](const json::value& v, const Path& at) {
          const auto i = f.reader().choice(v, at, kImageFates, "image", "fates");
          return i ? std::optional<std::string>(kImageFates[*i]) : std::nullopt;
        });
        f.string("image_error", m.image_error, kMaxErrorMessageBytes, Need::kOptional);
      });
}

}  // namespace dtraced::protocol
