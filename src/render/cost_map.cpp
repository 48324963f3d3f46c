#include "render/cost_map.h"

#include <algorithm>
#include <cassert>
#include <cmath>

#include "render/tile.h"
#include "scene/tiling.h"

namespace dtraced::render {
namespace {

// The low-resolution column (or row) that full-resolution column x of `full` falls in, of `low`.
std::uint32_t low_index(std::uint32_t x, std::uint32_t full, std::uint32_t low) {
  return static_cast<std::uint32_t>(std::uint64_t{x} * low / full);
}

// How many of the full-resolution columns [begin, end) fall in each low-resolution column, as
// (low column, count) pairs in ascending order.
std::vector<std::pair<std::uint32_t, std::uint32_t>> footprint(std::uint32_t begin, std::uint32_t end,
                                                               std::uint32_t full, std::uint32_t low) {
  std::vector<std::pair<std::uint32_t, std::uint32_t>> out;
  for (std::uint32_t x = begin; x < end;) {
    const std::uint32_t l = low_index(x, full, low);
    // The first full column of low column l + 1: ceil((l + 1) * full / low).
    const auto next = static_cast<std::uint32_t>((std::uint64_t{l + 1} * full + low - 1) / low);
    const std::uint32_t stop = std::min(end, std::max(next, x + 1));
    out.emplace_back(l, stop - x);
    x = stop;
  }
  return out;
}

}  // namespace

CostGridSize cost_grid_size(std::uint32_t width, std::uint32_t height, const CostMapOptions& options) {
  assert(width > 0 && height > 0 && options.min_downscale >= 1 && options.max_pixels >= 1);
  const double pixels = static_cast<double>(width) * height;
  double factor = std::max(double(options.min_downscale), std::sqrt(pixels / double(options.max_pixels)));
  CostGridSize size;
  // Rounding up may leave a pixel or two over the cap: grow the factor until it fits.
  for (int i = 0; i < 64; ++i) {
    size.width = std::max<std::uint32_t>(1, static_cast<std::uint32_t>(std::ceil(width / factor)));
    size.height = std::max<std::uint32_t>(1, static_cast<std::uint32_t>(std::ceil(height / factor)));
    if (std::uint64_t{size.width} * size.height <= options.max_pixels) break;
    factor *= 1.05;
  }
  return size;
}

CostMap tile_cost_map(const RenderScene& scene, const scene::RenderSettings& settings, std::uint32_t tile_size,
                      const CostMapOptions& options) {
  CostMap map;
  const CostGridSize size = cost_grid_size(settings.width, settings.height, options);
  map.width = size.width;
  map.height = size.height;

  scene::RenderSettings low = settings;
  low.width = size.width;
  low.height = size.height;
  low.samples = 1;
  low.error_target = 0;  // uniform: one sample, no border
  low.frames.reset();

  // Rays of each low-resolution pixel, rendered one by one to count them apart.
  std::vector<std::uint64_t> rays(std::size_t{size.width} * size.height);
  TileOptions tile_options;
  tile_options.packets = false;  // one pixel: nothing to pack
  for (std::uint32_t y = 0; y < size.height; ++y) {
    for (std::uint32_t x = 0; x < size.width; ++x) {
      const Tile t = render_tile(scene, low, scene::TileRect{x, y, 1, 1}, tile_options);
      rays[std::size_t{y} * size.width + x] = t.stats.rays;
      map.rays += t.stats.rays;
    }
  }

  const scene::TileGrid grid(settings, tile_size);
  map.costs.reserve(grid.count());
  for (std::uint64_t i = 0; i < grid.count(); ++i) {
    const scene::TileRect r = grid.rect(i);
    const auto xs = footprint(r.x0, r.x0 + r.width, settings.width, size.width);
    const auto ys = footprint(r.y0, r.y0 + r.height, settings.height, size.height);
    double cost = 0;
    for (const auto& [ly, ny] : ys) {
      for (const auto& [lx, nx] : xs) {
        cost += static_cast<double>(rays[std::size_t{ly} * size.width + lx]) * nx * ny;
      }
    }
    map.costs.push_back(static_cast<float>(cost));
  }
  return map;
}

}  // namespace dtraced::render
