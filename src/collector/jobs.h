// dtraced::collector jobs: what the collector knows about each job, and the pure operations on it.
//
// Owns: JobRecord (a job's effective settings, output name, tiles, state, and while it is
// unfinished its per-frame tile counts and scene text), and the small pure functions around it:
// where each tile of a frame range lies (tile index = frame index x tiles per frame + tile in
// the frame, so the queue's lowest indices are the lowest frames and frames complete in order),
// tile pixels to and from the store's blobs, copying a tile into an image, the status a client
// sees, a job's default output name and the one-shot job key.
//
// A job's pixels live in the store only, never in a framebuffer of the collector: an image (a
// finished frame's file, GET image, the web page's tiles) is read back from the store on the
// thread pool (StoreReader). So the collector's memory does not grow with the pixels it holds,
// and nothing on the event loop allocates, zeroes or copies a whole frame (1.5 GiB at
// 16384 x 8192).
//
// Thread safety: JobRecord is owned by the collector's event loop; the free functions are pure.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "collector/queue.h"
#include "image/image.h"
#include "protocol/messages.h"
#include "scene/description.h"
#include "scene/tiling.h"
#include "store/store.h"
#include "util/result.h"

namespace dtraced::collector {

// Sample counts summed over tiles. `known` turns false once a tile came without readable counts:
// the mean is then reported as unknown rather than wrong.
struct SampleTally {
  std::uint64_t sum = 0;
  std::uint64_t pixels = 0;
  bool known = true;
  void add(std::span<const std::uint32_t> spp) {
    if (spp.empty()) {
      known = false;
      return;
    }
    for (const std::uint32_t n : spp) sum += n;
    pixels += spp.size();
  }
  void add(const SampleTally& o) {
    sum += o.sum;
    pixels += o.pixels;
    known = known && o.known;
  }
};

struct JobRecord {
  JobId id = 0;
  std::string digest;
  scene::RenderSettings settings;
  std::string output;  // the effective file name (default_output_name when none was given)
  std::int32_t priority = 0;
  std::uint32_t tile_size = 0;
  std::uint32_t png_bit_depth = scene::kDefaultPngBitDepth;  // of a .png output
  protocol::JobState state = protocol::JobState::kQueued;
  std::int64_t created_unix = 0;
  std::int64_t finished_unix = 0;
  TileIndex tiles_total = 0;
  TileIndex tiles_done = 0;

  // Samples per pixel over the stored tiles this record has seen (adaptive jobs; a uniform job's
  // mean is settings.samples).
  SampleTally spp;
  bool spp_pending = false;  // a finished job's counts are still being read after start-up

  // Only these pixels of each frame are rendered and written (protocol::JobSettings::crop), or
  // whole frames when unset. A tile of the grid without a pixel in it is no part of the job: it
  // is never queued, leased, stored or counted, and the others keep their index in the full grid.
  std::optional<scene::TileRect> crop;

  // Estimated cost of each tile of one frame's full grid (protocol::JobSubmit::tile_costs), the
  // same for every frame; empty when none was sent: the tiles are then leased in row order.
  std::vector<float> tile_costs;

  // Frames of the job (1 for a single frame; settings.frames->count() for a sequence) and tiles
  // it renders per frame (tiles_total = frames x tiles_per_frame). Tile indices run over the
  // whole grid of every frame, [0, tile_indices): tile_indices = tiles_total without a crop.
  std::uint32_t frames_total = 1;
  TileIndex tiles_per_frame = 0;
  TileIndex tile_indices = 0;
  // Frames whose image this process has written, in order: frames [0, frames_written) are on
  // disk. The job is done when all are.
  std::uint32_t frames_written = 0;

  // Unfinished jobs only (released once done or cancelled).
  std::vector<TileIndex> frame_tiles_done;        // by frame index: tiles stored
  std::shared_ptr<const std::string> scene_json;  // canonical scene text, served to workers
  std::vector<bool> restored;                     // tiles already stored when this process started
  bool writing = false;                           // frame images are being written (finish_job runs)
  bool finishing = false;                         // every tile is stored; the last image is being written
  bool finish_failed = false;                     // writing an image failed; retried later
  bool rendering_persisted = false;               // the store has been told the job is rendering

  // The web page's view (handlers/web.cpp), of this process only; released with the scene text.
  // By tile index: the sequence number of each tile stored in memory (0: none), assigned as a
  // tile is stored and, for the tiles restored at start-up, when first needed (ascending index).
  // last_seq only grows, so a client's `since` stays meaningful.
  std::vector<std::uint32_t> tile_seq;
  std::uint32_t last_seq = 0;
  // By tile index: who stored it, 1 + an index into worker_names (0: unknown, e.g. restored).
  std::vector<std::uint16_t> tile_worker;
  std::vector<std::string> worker_names;  // at most kMaxJobWorkerNames
  // Who holds each outstanding lease (the latest holder), at most kMaxLeaseHolders tiles.
  std::map<TileIndex, std::string> leased_by;

  // The settings of the frame last leased, as a lease carries them (handlers/lease.cpp): encoded
  // once rather than rebuilt as a JSON object for every lease. Keyed by the settings themselves,
  // so a change of frame (or of settings) re-encodes them.
  struct LeaseSettingsText {
    scene::RenderSettings settings;
    std::string text;
  };
  std::optional<LeaseSettingsText> lease_settings_text;

  // Progress of this process, for the ETA.
  std::optional<TimePoint> first_lease;
  TileIndex stored_this_run = 0;

  bool unfinished() const {
    return state == protocol::JobState::kQueued || state == protocol::JobState::kRendering ||
           state == protocol::JobState::kPaused;
  }
};

// Bounds of the web page's view of a job (JobRecord::worker_names, leased_by).
inline constexpr std::size_t kMaxJobWorkerNames = 1024;
inline constexpr std::size_t kMaxLeaseHolders = 65536;

// "job-<id>.png"; "job-<id>-%04d.png" for a job of several frames.
std::string default_output_name(JobId id, std::uint32_t frames = 1);

// Where a tile of a job lies: its frame index and its rectangle in that frame.
struct TilePlace {
  std::uint32_t frame_index = 0;
  scene::TileRect rect;
};
TilePlace tile_place(const JobRecord& job, TileIndex tile);
// The settings a worker renders frame `frame_index` with: that frame's number, no range.
scene::RenderSettings frame_settings(const scene::RenderSettings& job_settings, std::uint32_t frame_index);
// The frame index of frame number `frame`, or nullopt when the job does not render it.
std::optional<std::uint32_t> frame_index_of(const scene::RenderSettings& job_settings, std::uint32_t frame);
// The file name of frame `frame_index`'s image: the output's sequence pattern (image/sequence.h)
// at that frame's number, or the output as it is when it holds no frame number.
std::string frame_output_name(const JobRecord& job, std::uint32_t frame_index);
// Sets frames_total, tiles_per_frame, tile_indices, tiles_total and frame_tiles_done from the
// settings, crop and tile size; false when the job has no tile, more than
// protocol::kMaxTilesPerJob tile indices, or a crop outside its image.
bool init_frames(JobRecord& job);

// Whether tile `tile` has a pixel inside `crop` (every tile does without a crop).
bool overlaps_crop(const scene::TileRect& tile, const std::optional<scene::TileRect>& crop);
// Whether `tile` is one of the job's: an index below tile_indices whose rectangle overlaps the crop.
bool tile_of_job(const JobRecord& job, TileIndex tile);
// The indices below tile_indices that are not the job's (none without a crop), ascending.
std::vector<TileIndex> skipped_tiles(const JobRecord& job);
// The order in which a job's tiles are first leased: frame by frame (frames still complete in
// order), and within a frame by descending cost, ties (and NaN, which validation keeps out) in
// row order, so the costliest tiles start first and the job's tail is made of cheap tiles. A
// permutation of [0, frames x costs.size()); empty when `costs` is.
std::vector<TileIndex> lease_order(std::span<const float> costs, std::uint32_t frames);
// Tile costs as the store keeps them (jobs' StoredJob::tile_costs): the float32 values' bytes in
// host (little-endian) order; empty for none.
store::Blob costs_to_blob(std::span<const float> costs);
// The costs of a stored blob, or nullopt when it is not `per_frame` finite floats >= 0.
std::optional<std::vector<float>> blob_to_costs(const store::Blob& blob, TileIndex per_frame);
// Adds the job to the queue (WorkQueue::add_job) with its skipped tiles and `stored` tiles, in
// lease_order of its tile costs when it has them (and they fit its grid), else in row order.
bool queue_job(WorkQueue& queue, const JobRecord& job, std::span<const TileIndex> stored = {});

// Tile pixels as the store keeps them (tiles.pixels): the float32 values' bytes in host order
// (the collector only runs on little-endian hosts, asserted at compile time, so this is the
// wire's order too), then, for an adaptive job, each pixel's u32 sample count. The blob's size
// tells which: 12 bytes per pixel without counts (every tile stored before adaptive sampling
// existed), 16 with them. No schema change was needed.
store::Blob pixels_to_blob(std::span<const float> rgb, std::span<const std::uint32_t> spp = {});

struct TileBlob {
  std::vector<float> rgb;          // pixels * 3
  std::vector<std::uint32_t> spp;  // pixels, or empty for a blob without counts
};
// nullopt when the blob holds neither pixels * 12 nor pixels * 16 bytes.
std::optional<TileBlob> blob_to_tile(const store::Blob& blob, std::size_t pixels);

// Whether a submitted tile's sample counts fit the job: present exactly when it is adaptive
// (settings.error_target > 0), one per pixel, each scene::is_valid_sample_count. The error names
// the first bad pixel; its path is the payload's "/spp".
util::Status check_sample_counts(const scene::RenderSettings& settings, const scene::TileRect& rect,
                                 std::span<const std::uint32_t> spp);

// Adds a stored tile's counts to the job's running mean (a uniform job needs none: a no-op).
void count_samples(JobRecord& job, std::span<const std::uint32_t> spp);

// Copies a tile's rgb (rect.width * rect.height * 3 floats) into `image` at `rect`.
void copy_tile(image::ImageRGBf& image, const scene::TileRect& rect, std::span<const float> rgb);
// Copies the part of a tile's rgb that lies inside `window` into `image`, which holds the
// window's pixels (its (0, 0) is the frame's (window.x0, window.y0)): a cropped job's output.
void copy_tile(image::ImageRGBf& image, const scene::TileRect& window, const scene::TileRect& rect,
               std::span<const float> rgb);

// Whether every tile of the frame is stored.
bool frame_complete(const JobRecord& job, std::uint32_t frame_index);

// Reads the job's stored tiles from `s` into `rec`: the per-frame counts, its sample tally and its
// `restored` flags (the pixels stay in the store); returns their indices, ascending. One tile is in
// memory at a time; a tile the store cannot read back (store::Store::get_all_tiles) is left out, to
// be rendered again. Fails, naming the database, on a tile out of range or a blob of the wrong size.
// Runs wherever `s` may be used (start-up; the store writer's thread for a requeue) on a record no
// other thread touches.
util::Result<std::vector<TileIndex>> load_stored_tiles(store::Store& s, JobRecord& rec);

// The status a client sees. `now_unix` for the elapsed time, `now` for the rate of this process.
protocol::JobStatus job_status(const JobRecord& job, std::int64_t now_unix, TimePoint now);

// The key a one-shot collector stores with its job, so that a restart with the same arguments
// finds it: SHA-256 over the scene digest, the effective settings (protocol::encode_settings, so
// an 8-bit job keeps the key it had before bit depths could be set), the tile size and the output.
std::string one_shot_client_key(std::string_view digest, const protocol::JobSettings& settings, std::uint32_t tile_size,
                                std::string_view output);

}  // namespace dtraced::collector
