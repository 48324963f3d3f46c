// dtraced::collector store reader: the collector's second SQLite connection, for reads too large
// for the event loop.
//
// Owns: a Store opened on first use (without the integrity check: the first connection ran it at
// start-up) and the reads that go through it: a job's image (or one frame of it), assembled from
// its stored tiles and encoded, whether the job is finished or not (the collector keeps no
// framebuffer); one stored tile's pixels; a scene by digest; a finished adaptive job's sample
// counts. The store writer (store/tile_writer.h) has the other connection; WAL lets the two work
// at once.
//
// Memory: the float images assembled at once (12 bytes a pixel: a 16384^2 frame is 3 GiB) are
// bounded by a byte budget, not only by the thread pool's size: a frame waits for its bytes
// before it is allocated and holds them until its HeldImage goes (util/byte_budget.h).
//
// Thread safety: every member function may be called from any thread (the thread pool's); the
// connection is used by one caller at a time under a lock. The sample counts are read one tile
// per lock, so image and scene reads go on in between.
#pragma once

#include <cstdint>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "collector/jobs.h"
#include "image/image_io.h"
#include "scene/description.h"
#include "store/store.h"
#include "util/byte_budget.h"
#include "util/result.h"

namespace dtraced::collector {

// A frame assembled from the store and the share of the reader's image budget it holds.
struct HeldImage {
  util::ByteBudget::Lease lease;
  image::ImageRGBf image;
};

class StoreReader {
 public:
  // image_memory_bytes: the budget of the frames assembled at once (one larger frame still goes,
  // alone).
  StoreReader(std::string state_dir, std::uint64_t image_memory_bytes);

  // The image of frame `frame_index` (0 for a single frame) of a job whose pixels live in the
  // store, black where no tile is stored, encoded in `format`: the whole frame, or only the
  // `crop` pixels of a cropped job.
  util::Result<std::string> encode_image(JobId id, const scene::RenderSettings& settings, std::uint32_t tile_size,
                                         const std::optional<scene::TileRect>& crop, std::uint32_t frame_index,
                                         const image::WriteOptions& options, image::ImageFormat format);

  // Frame `frame_index` of a job from its stored tiles, black where none is stored, cut to `crop`
  // when set (only the crop's pixels are allocated); read one tile at a time (a sequence's GIF
  // is assembled from these, one frame in memory at a time). Waits for the frame's bytes in the
  // image budget first.
  util::Result<HeldImage> frame_image(JobId id, const scene::RenderSettings& settings, std::uint32_t tile_size,
                                      const std::optional<scene::TileRect>& crop, std::uint32_t frame_index);

  // The rgb values of stored tile `tile` (`pixels` of them: width x height of its rectangle), or
  // nullopt when it is not stored; fails on a read error or a blob of the wrong size.
  util::Result<std::optional<std::vector<float>>> tile_rgb(JobId id, TileIndex tile, std::size_t pixels);

  // A scene's canonical text; nullopt when no scene has this digest.
  util::Result<std::optional<std::string>> scene(const std::string& digest);

  // The sample counts of a finished adaptive job's stored tiles (indices below `tile_indices`).
  // A tile whose blob holds no readable counts makes the tally unknown (its image is checked when
  // it is served).
  util::Result<SampleTally> sample_counts(JobId id, const scene::RenderSettings& settings, std::uint32_t tile_size,
                                          TileIndex tile_indices);

  // Closes the connection for good: reads after this fail ("the collector is stopping").
  void close();

 private:
  // One stored tile, read under the lock (one tile per lock, so that other reads go on between).
  util::Result<std::optional<store::StoredTile>> stored_tile(JobId id, std::uint32_t tile);
  // The connection, opened if need be; call with mu_ held.
  util::Result<store::Store*> store_locked();

  const std::string state_dir_;
  util::ByteBudget image_budget_;
  std::mutex mu_;
  std::optional<store::Store> store_;  // guarded by mu_
  bool closed_ = false;                // guarded by mu_: stopping, never reopen
};

}  // namespace dtraced::collector
