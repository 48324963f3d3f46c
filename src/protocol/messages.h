// dtraced::protocol messages: the JSON bodies of the collector's HTTP API, as plain structs with
// strict codecs.
//
// Owns: every JSON body that crosses the wire (README.md, "HTTP API", lists the endpoints) and the
// limits on them. Encoders always produce a body that the matching decoder accepts and that
// decodes to an equal struct (doubles included, bit for bit). Decoders read with jsonio's strict
// reader (jsonio/reader.h), as the scene loader and config files do, so a mistake is worded the
// same in all three: unknown keys (with a did-you-mean), duplicate keys, wrong types, integers out
// of range, numbers that overflow a double, oversized or too deeply nested bodies are all errors,
// each located by the JSON Pointer of the offending value ("/tile_size",
// "/scene/scene_objects/3/radius"); "" names the body as a whole. A decoder returns either the
// struct or its errors, never a partial struct.
//
// Numbers: integers may be written as integral doubles (640.0, 1e3), as in scene files; ids,
// seeds and counters stay within 2^53 - 1 so that a JavaScript client reads them exactly.
//
// Stateless functions over values: thread-safe.
#pragma once

#include <cassert>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

#include "scene/description.h"
#include "scene/load.h"
#include "scene/overrides.h"
#include "scene/tiling.h"
#include "util/result.h"

namespace dtraced::protocol {

// ---- limits --------------------------------------------------------------------------------

// Every body but a job submission and a job list: they are a few hundred bytes.
inline constexpr std::size_t kMaxMessageBytes = 64 << 10;
// POST /v1/jobs carries a whole scene. Scenes for the farm are bounded tighter than scene files
// (scene::kMaxSceneBytes): the collector holds, parses and stores every one of them.
inline constexpr std::size_t kMaxJobSubmitBytes = 64 << 20;
// Upper bound of one JobSubmit::tile_costs entry (finite in a float with room to sum).
inline constexpr float kMaxTileCost = 1e30f;
// GET /v1/jobs: at most kMaxListedJobs statuses of a few hundred bytes each.
inline constexpr std::size_t kMaxJobListBytes = 16 << 20;
inline constexpr std::size_t kMaxListedJobs = 10'000;
// Nesting depth of control messages; a submission adds one level above a scene's own limit.
inline constexpr std::size_t kMaxMessageDepth = 8;
inline constexpr std::size_t kMaxJobSubmitDepth = scene::kMaxJsonDepth + 1;
// Errors reported per body; past this the rest are counted in one final error.
inline constexpr std::size_t kMaxDecodeErrors = 100;

inline constexpr std::uint64_t kMaxId = (1ull << 53) - 1;  // job ids, as JSON numbers
inline constexpr std::int32_t kMinPriority = -1000;
inline constexpr std::int32_t kMaxPriority = 1000;
// A job's tile count is capped so that the collector's per-job queue state stays small: a
// 16384 x 16384 image at the default tile size is exactly this many tiles.
inline constexpr std::uint32_t kMaxTilesPerJob = 1u << 18;
inline constexpr std::size_t kMaxOutputNameBytes = 255;  // NAME_MAX on Linux file systems
inline constexpr std::size_t kMaxWorkerNameBytes = 128;
inline constexpr std::uint32_t kMaxWorkerThreads = 4096;
inline constexpr std::uint32_t kMaxRetryAfterMs = 60'000;
inline constexpr std::size_t kMaxErrorMessageBytes = 16 << 10;
inline constexpr std::size_t kDigestHexChars = 64;  // a scene digest: lower-case hex SHA-256
// A worker names itself in this header on tile uploads; the collector records it with the tile.
inline constexpr std::string_view kWorkerHeader = "X-Dtraced-Worker";

// ---- results -------------------------------------------------------------------------------

// Either a decoded message or every error found (util::Error{message, path}, the path a JSON
// Pointer into the body, "" for the body as a whole), the first being the most useful one.
template <typename T>
using Decoded = util::Result<T, util::Errors>;

// ---- validation shared with the command line ----------------------------------------------

// Whether `name` is acceptable as a job's output: a plain file name (no '/', '\\', "..", control
// characters, no leading '.'), at most kMaxOutputNameBytes, ending in the extension of one of
// image::image_formats() (lower case). The error's message starts "output name ".
util::Status check_output_name(std::string_view name);

// True for kDigestHexChars lower-case hex digits.
bool is_digest(std::string_view text);

// ---- POST /v1/jobs -------------------------------------------------------------------------

struct JobSubmit {
  scene::SceneDesc scene;
  // check_output_name, or empty when the submitter leaves the name to the collector (the key is
  // then absent on the wire; an explicit "" is an error).
  std::string output;
  std::int32_t priority = 0;
  // Overrides of the scene's render block, the tile size (scene::kDefaultTileSize when unset),
  // the PNG bit depth of the output and the crop ("crop": {"x", "y", "width", "height"}, checked
  // against the effective image size); each a top-level key of its own, absent when unset,
  // checked against the limits of scene files.
  scene::Overrides overrides;
  // Estimated render cost of each tile of one frame's full grid (scene::TileGrid of the effective
  // settings and tile size, crop-skipped tiles included), in any unit (render/cost_map.h counts
  // rays): the collector leases the costliest tiles of each frame first. Empty when not sent
  // ("tile_costs" absent): tiles are leased in row order. When sent: exactly tiles-per-frame
  // finite numbers in [0, kMaxTileCost].
  std::vector<float> tile_costs;
  bool operator==(const JobSubmit&) const = default;
};

// The scene's render settings with the submission's overrides applied. The frame range is the
// override's, else the scene's render.frames, else the single frame render.frame; an explicit
// "frame" without "frames" is that single frame, and a range of one frame is stored as that
// single frame (frames unset), so that a single-frame job keeps the settings text it always had.
scene::RenderSettings effective_settings(const JobSubmit& submit);

// A job's frames: frames->count(), or 1 without a range; and the number of its index-th frame.
std::uint32_t frame_count(const scene::RenderSettings& s);
std::uint32_t frame_number(const scene::RenderSettings& s, std::uint32_t index);

std::string encode(const JobSubmit& m);
// Also rejects a submission whose effective image has more than kMaxTilesPerJob tiles over all
// its frames (at "/tile_size", or "/frames" for a sequence without a tile size). "frames" is
// {"first", "last", "step"} ("step" optional, 1 by default), as in a scene's render block. Scene problems come back
// with paths under "/scene".
Decoded<JobSubmit> decode_job_submit(std::string_view body);

// 201 answer to POST /v1/jobs.
struct JobCreated {
  std::uint64_t id = 0;  // [1, kMaxId]
  std::string digest;    // is_digest
  bool operator==(const JobCreated&) const = default;
};
std::string encode(const JobCreated& m);
Decoded<JobCreated> decode_job_created(std::string_view body);

// ---- GET /v1/jobs, GET /v1/jobs/{id}, POST /v1/jobs/{id}/cancel ----------------------------

enum class JobState { kQueued, kRendering, kDone, kCancelled, kPaused };

// "queued", "rendering", "done", "cancelled", "paused". A paused job is unfinished: no tile of it
// is leased until it is resumed, and tiles already out are still accepted.
std::string_view to_string(JobState state);
std::optional<JobState> job_state_from_string(std::string_view text);

// A job unserved this long is reported by its status (JobStatus::no_worker_s).
inline constexpr double kNoWorkerAfterS = 60;

// A sequence's progress: frames written, and the frame being rendered (the lowest one not written
// yet; the last frame once all are written) with its tiles stored.
struct FrameProgress {
  std::uint32_t frames_total = 1;  // [1, scene::kMaxFrames]
  std::uint32_t frames_done = 0;   // <= frames_total
  std::uint32_t frame = 0;         // a frame number
  std::uint32_t frame_tiles_done = 0;
  std::uint32_t frame_tiles_total = 1;  // >= frame_tiles_done
  bool operator==(const FrameProgress&) const = default;
};

struct JobStatus {
  std::uint64_t id = 0;  // [1, kMaxId]
  JobState state = JobState::kQueued;
  std::string output;  // check_output_name
  std::int32_t priority = 0;
  std::uint32_t width = 0, height = 0, samples = 0;  // scene limits
  std::uint32_t tiles_done = 0;                      // <= tiles_total
  std::uint32_t tiles_total = 0;                     // [1, kMaxTilesPerJob]
  double elapsed_s = 0;                              // finite, >= 0
  std::optional<double> eta_s;                       // finite, >= 0; null on the wire when unknown
  std::string digest;                                // is_digest
  // Mean samples per pixel over the tiles stored so far, in [1, samples]; null on the wire when
  // no tile is stored yet or the collector cannot tell (an adaptive job finished before its last
  // restart). Optional when decoding, so that an older collector's answer still reads.
  std::optional<double> mean_spp;
  // Seconds since a worker last leased or returned a tile of this unfinished job, once that is at
  // least a minute (kNoWorkerAfterS); null otherwise. Optional when decoding, like mean_spp.
  std::optional<double> no_worker_s;
  // A job of several frames only: "frames_total", "frames_done", "frame", "frame_tiles_done" and
  // "frame_tiles_total" on the wire, all or none. Optional when decoding, like mean_spp.
  std::optional<FrameProgress> frames;
  bool operator==(const JobStatus&) const = default;
};
std::string encode(const JobStatus& m);
Decoded<JobStatus> decode_job_status(std::string_view body);

struct JobList {
  std::vector<JobStatus> jobs;  // at most kMaxListedJobs
  bool operator==(const JobList&) const = default;
};
std::string encode(const JobList& m);
Decoded<JobList> decode_job_list(std::string_view body);

// ---- POST /v1/jobs/{id}/priority ---------------------------------------------------------------

// {"priority": N}: the job's new priority, in [kMinPriority, kMaxPriority].
struct JobPriority {
  std::int32_t priority = 0;
  bool operator==(const JobPriority&) const = default;
};
std::string encode(const JobPriority& m);
Decoded<JobPriority> decode_job_priority(std::string_view body);

// ---- DELETE /v1/jobs/{id} ----------------------------------------------------------------------

// What a deletion removed: the job and its `tiles` stored tiles, and what became of its image
// file: "kept" (the default), "deleted", "none" (no file: a cancelled job, or already gone), or
// "failed" with `image_error` saying why (the job is deleted all the same).
struct JobDeleted {
  std::uint64_t id = 0;
  std::uint64_t tiles = 0;
  std::string image = "kept";
  std::string image_error;  // empty unless image == "failed"
  bool operator==(const JobDeleted&) const = default;
};
std::string encode(const JobDeleted& m);
Decoded<JobDeleted> decode_job_deleted(std::string_view body);

// ---- POST /v1/lease ------------------------------------------------------------------------

struct LeaseRequest {
  std::string worker;         // 1..kMaxWorkerNameBytes printable ASCII characters (0x20..0x7e)
  std::uint32_t threads = 1;  // [1, kMaxWorkerThreads]
  bool operator==(const LeaseRequest&) const = default;
};
std::string encode(const LeaseRequest& m);
Decoded<LeaseRequest> decode_lease_request(std::string_view body);

// One tile to render: the pixels of `rect` of scene(digest) under `settings`.
struct Lease {
  std::uint64_t job = 0;   // [1, kMaxId]
  std::string digest;      // is_digest
  std::uint32_t tile = 0;  // < kMaxTilesPerJob
  scene::TileRect rect;    // 1..scene::kMaxTileSize on each side, inside the settings' image
  scene::RenderSettings settings;
  bool operator==(const Lease&) const = default;
};

// "Nothing now": ask again after this long.
struct RetryAfter {
  std::uint32_t ms = 0;  // [0, kMaxRetryAfterMs]
  bool operator==(const RetryAfter&) const = default;
};

// {"lease": {...}} or {"retry_after_ms": N}; exactly one of the two keys.
using LeaseReply = std::variant<Lease, RetryAfter>;
std::string encode(const LeaseReply& m);
Decoded<LeaseReply> decode_lease_reply(std::string_view body);

// ---- PUT /v1/jobs/{id}/tiles/{tile} answer -------------------------------------------------

enum class SubmitResult { kStored, kAlreadyDone, kJobGone };

// "stored", "already_done", "job_gone".
std::string_view to_string(SubmitResult result);
std::string encode(SubmitResult m);
Decoded<SubmitResult> decode_submit_result(std::string_view body);

// ---- every 4xx/5xx -------------------------------------------------------------------------

struct ErrorBody {
  std::string error;  // at most kMaxErrorMessageBytes
  std::string field;  // JSON Pointer of the offending value; "" when no single field is at fault
  bool operator==(const ErrorBody&) const = default;
};

// The first error, with a count of the others appended to its message.
ErrorBody error_body(const util::Errors& errors);

// "field" may be absent when decoding (it is then ""); it is always written.
std::string encode(const ErrorBody& m);
Decoded<ErrorBody> decode_error_body(std::string_view body);

// ---- a job's effective settings, as the store keeps them (jobs.settings_json) --------------

struct JobSettings {
  scene::RenderSettings render;
  std::uint32_t png_bit_depth = scene::kDefaultPngBitDepth;  // of a .png output
  // Only these pixels of each frame are rendered and written (scene::Overrides::crop): inside
  // render.width x render.height, not empty.
  std::optional<scene::TileRect> crop{};
  bool operator==(const JobSettings&) const = default;
};

// {"width", "height", "samples", "max_depth", "background": [r, g, b], "seed", "frame"}, every key
// required, plus "error_target" and "min_samples", written when either differs from its default
// and optional when read (absent: uniform sampling): the same object a Lease carries as
// "settings". Then "png_bit_depth", written when it is not 8 and optional when read; and "frames",
// "fps", "exposure" and "tone", written when they differ from a static single frame's and
// optional when read (a lease's settings carry them too; a lease is one frame, without "frames").
// Last "crop", {"x", "y", "width", "height"}, written only when set and optional when read; on
// reading it must lie inside the image (the error names "/crop/width" or "/crop/height"). A job
// stored before a field existed reads as it always did, and an 8-bit uniform job keeps its text
// (and so its one-shot key).
std::string encode_settings(const JobSettings& settings);
Decoded<JobSettings> decode_settings(std::string_view body);

}  // namespace dtraced::protocol
