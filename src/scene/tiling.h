// dtraced::scene tiling: how an image is cut into tiles, and where an adaptive pixel may stop.
//
// Owns the vocabulary that the renderer, the wire and the collector share: a tile rectangle, the
// tile grid of an image (how many tiles, the rectangle of tile i, all of them in order) and the
// adaptive-sampling checkpoint rule. It sits here, beside RenderSettings, so that protocol and
// collector name tiles without including the renderer.
//
// The grid is row-major: tile i is at column i % columns and row i / columns, each tile_size
// square except at the right and bottom edges. The checkpoints of a render are the sample counts
// n = min_samples * 2^k below settings.samples (README: "Adaptive sampling"); a pixel of an
// adaptive render takes either settings.samples or one of those.
//
// Pure functions over values: thread-safe.
#pragma once

#include <cstdint>
#include <vector>

#include "scene/description.h"

namespace dtraced::scene {

// Tile sides a user may ask for (a local render, a job, a one-shot collector). The tile count of
// a farm job is bounded separately (protocol::kMaxTilesPerJob).
inline constexpr std::uint32_t kMinTileSize = 1;
inline constexpr std::uint32_t kMaxTileSize = 1024;
inline constexpr std::uint32_t kDefaultTileSize = 32;
// A local adaptive render's default (cli/render_verb.cpp says why).
inline constexpr std::uint32_t kDefaultAdaptiveTileSize = 64;

struct TileRect {
  std::uint32_t x0 = 0, y0 = 0;
  std::uint32_t width = 0, height = 0;
  bool operator==(const TileRect&) const = default;
};

// The tiles of a width x height image. width, height and tile_size > 0.
class TileGrid {
 public:
  TileGrid(std::uint32_t width, std::uint32_t height, std::uint32_t tile_size);
  TileGrid(const RenderSettings& settings, std::uint32_t tile_size)
      : TileGrid(settings.width, settings.height, tile_size) {}

  std::uint32_t columns() const { return columns_; }
  std::uint32_t rows() const { return rows_; }
  // columns * rows; in 64 bits, since a 1-pixel tile size over a large image overflows 32.
  std::uint64_t count() const { return std::uint64_t{columns_} * rows_; }
  // Tile `index` (< count()).
  TileRect rect(std::uint64_t index) const;
  // Every tile, in index order.
  std::vector<TileRect> all() const;

 private:
  std::uint32_t width_, height_, tile_size_;
  std::uint32_t columns_, rows_;
};

// Whether n samples is a checkpoint of the settings: n = min_samples * 2^k (k >= 0), n < samples.
bool is_checkpoint(const RenderSettings& settings, std::uint32_t n);

// Whether a pixel may have taken n samples under the settings: all of them, or (adaptive
// sampling only, error_target > 0) a checkpoint.
bool is_valid_sample_count(const RenderSettings& settings, std::uint32_t n);

}  // namespace dtraced::scene
