#include "scene/tiling.h"

#include <algorithm>
#include <cassert>

namespace dtraced::scene {

TileGrid::TileGrid(std::uint32_t width, std::uint32_t height, std::uint32_t tile_size)
    : width_(width), height_(height), tile_size_(tile_size) {
  assert(width > 0 && height > 0 && tile_size > 0);
  columns_ = static_cast<std::uint32_t>((std::uint64_t{width} + tile_size - 1) / tile_size);
  rows_ = static_cast<std::uint32_t>((std::uint64_t{height} + tile_size - 1) / tile_size);
}

TileRect TileGrid::rect(std::uint64_t index) const {
  assert(index < count());
  const auto x0 = static_cast<std::uint32_t>(index % columns_) * tile_size_;
  const auto y0 = static_cast<std::uint32_t>(index / columns_) * tile_size_;
  return {x0, y0, std::min(tile_size_, width_ - x0), std::min(tile_size_, height_ - y0)};
}

std::vector<TileRect> TileGrid::all() const {
  std::vector<TileRect> tiles;
  tiles.reserve(count());
  for (std::uint64_t i = 0; i < count(); ++i) tiles.push_back(rect(i));
  return tiles;
}

bool is_checkpoint(const RenderSettings& settings, std::uint32_t n) {
  if (n < settings.min_samples || n >= settings.samples || n % settings.min_samples != 0) return false;
  const std::uint32_t k = n / settings.min_samples;
  return (k & (k - 1)) == 0;
}

bool is_valid_sample_count(const RenderSettings& settings, std::uint32_t n) {
  return n == settings.samples || (settings.error_target > 0 && is_checkpoint(settings, n));
}

}  // namespace dtraced::scene
