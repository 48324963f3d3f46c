#include "collector/store_reader.h"

#include <utility>
#include <vector>

#include <fmt/format.h>

#include "scene/tiling.h"

namespace dtraced::collector {

StoreReader::StoreReader(std::string state_dir, std::uint64_t image_memory_bytes)
    : state_dir_(std::move(state_dir)), image_budget_(image_memory_bytes) {}

util::Result<store::Store*> StoreReader::store_locked() {
  if (closed_) return util::Error("the collector is stopping");
  if (!store_) {
    store::OpenOptions options;
    options.verify_integrity = false;  // verified at start-up by the first connection
    auto opened = store::Store::open(state_dir_, options);
    if (!opened) return std::move(opened).error();
    store_.emplace(std::move(opened).value());
  }
  return &*store_;
}

util::Result<std::string> StoreReader::encode_image(JobId id, const scene::RenderSettings& settings,
                                                    std::uint32_t tile_size, const std::optional<scene::TileRect>& crop,
                                                    std::uint32_t frame_index, const image::WriteOptions& options,
                                                    image::ImageFormat format) {
  // The frame's tiles only, one at a time (a sequence's other frames are never read).
  util::Result<HeldImage> held = frame_image(id, settings, tile_size, crop, frame_index);
  if (!held) return std::move(held).error();
  return image::encode_image(format, held.value().image, options);
}

util::Result<HeldImage> StoreReader::frame_image(JobId id, const scene::RenderSettings& settings,
                                                 std::uint32_t tile_size, const std::optional<scene::TileRect>& crop,
                                                 std::uint32_t frame_index) {
  // Only the pixels the output shows are held: the crop's, or the whole frame without one.
  const scene::TileRect window = crop.value_or(scene::TileRect{0, 0, settings.width, settings.height});
  HeldImage held{image_budget_.acquire(std::uint64_t{window.width} * window.height * 3 * sizeof(float)), {}};
  held.image = image::ImageRGBf(window.width, window.height);
  image::ImageRGBf& image = held.image;
  const scene::TileGrid grid(settings, tile_size);
  const TileIndex first = frame_index * static_cast<TileIndex>(grid.count());
  for (TileIndex t = 0; t < grid.count(); ++t) {
    if (!overlaps_crop(grid.rect(t), crop)) continue;  // no part of the job
    const scene::TileRect rect = grid.rect(t);
    // One tile per lock (inside tile_rgb), so that other reads go on in between.
    auto rgb = tile_rgb(id, first + t, std::size_t{rect.width} * rect.height);
    if (!rgb) return std::move(rgb).error();
    if (rgb.value()) copy_tile(image, window, rect, *rgb.value());
  }
  return held;
}

util::Result<std::optional<store::StoredTile>> StoreReader::stored_tile(JobId id, std::uint32_t tile) {
  std::lock_guard lock(mu_);
  auto s = store_locked();
  if (!s) return std::move(s).error();
  return s.value()->get_tile(static_cast<std::int64_t>(id), tile);
}

util::Result<std::optional<std::vector<float>>> StoreReader::tile_rgb(JobId id, TileIndex tile, std::size_t pixels) {
  auto read = stored_tile(id, tile);
  if (!read) return std::move(read).error();
  std::optional<store::StoredTile>& stored = read.value();
  if (!stored) return std::optional<std::vector<float>>();
  auto parsed = blob_to_tile(stored->pixels, pixels);
  if (!parsed) return util::Error(fmt::format("stored tile {} of job {} has the wrong size", tile, id));
  return std::optional(std::move(parsed->rgb));
}

util::Result<std::optional<std::string>> StoreReader::scene(const std::string& digest) {
  std::lock_guard lock(mu_);
  auto s = store_locked();
  if (!s) return std::move(s).error();
  return s.value()->get_scene(digest);
}

util::Result<SampleTally> StoreReader::sample_counts(JobId id, const scene::RenderSettings& settings,
                                                     std::uint32_t tile_size, TileIndex tile_indices) {
  std::vector<std::uint32_t> indices;
  {
    std::lock_guard lock(mu_);
    auto s = store_locked();
    if (!s) return std::move(s).error();
    auto tiles = s.value()->stored_tiles(static_cast<std::int64_t>(id));
    if (!tiles) return std::move(tiles).error();
    indices = std::move(tiles).value();
  }
  SampleTally tally;
  const scene::TileGrid grid(settings, tile_size);
  for (const std::uint32_t index : indices) {
    if (index >= tile_indices) continue;
    auto read = stored_tile(id, index);
    if (!read) return std::move(read).error();
    const std::optional<store::StoredTile>& stored = read.value();
    if (!stored) continue;
    const scene::TileRect rect = grid.rect(index % grid.count());
    auto parsed = blob_to_tile(stored->pixels, std::size_t{rect.width} * rect.height);
    if (!parsed) {
      tally.known = false;  // the image itself is checked when it is served
      continue;
    }
    tally.add(parsed->spp);
  }
  return tally;
}

void StoreReader::close() {
  std::lock_guard lock(mu_);
  store_.reset();
  closed_ = true;
}

}  // namespace dtraced::collector
