// dtraced::render cost map: a cheap estimate of what each tile of a frame costs to render.
//
// Owns: the submission-time pre-pass behind the farm's tile order (docs/tile_order.md). The frame
// is rendered once at low resolution (each side at most 1/min_downscale of the image's, at most
// max_pixels pixels in all), 1 sample per pixel, uniform sampling, the job's max_depth and branch
// cut-off, one pixel at a time so that each low-resolution pixel's ray count is known. A tile's
// cost is the sum, over its full-resolution pixels, of the ray count of the low-resolution pixel
// each falls in: an estimate of the rays one sample of the tile casts. Glass and mirrors cast more
// rays per pixel, so the tiles that show them cost more. Only the order of the costs matters to
// the collector (it leases the costliest tiles first), not their unit.
//
// Bounded: at most max_pixels (default 16,384) camera samples, so a few milliseconds for the demo
// scenes once the RenderScene is built; O(tiles + width + height) for the sums.
//
// Pure function of (scene, settings, tile size, options): the same costs on every host (ray counts,
// not times). Thread-safe.
#pragma once

#include <cstdint>
#include <vector>

#include "render/render_scene.h"
#include "scene/description.h"

namespace dtraced::render {

struct CostMapOptions {
  std::uint32_t min_downscale = 8;   // each side of the pre-pass at most 1/this of the image's, >= 1
  std::uint64_t max_pixels = 16384;  // pixels of the pre-pass at most, >= 1
};

struct CostMap {
  std::vector<float> costs;  // one per tile of scene::TileGrid(settings, tile_size), index order
  std::uint32_t width = 0;   // of the pre-pass
  std::uint32_t height = 0;
  std::uint64_t rays = 0;  // the pre-pass cast in all
};

// The pre-pass's image size for a frame of width x height: each side divided by the same factor
// f >= min_downscale, chosen so that the pixels are at most max_pixels, rounded up, at least 1.
struct CostGridSize {
  std::uint32_t width = 1;
  std::uint32_t height = 1;
};
CostGridSize cost_grid_size(std::uint32_t width, std::uint32_t height, const CostMapOptions& options = {});

// The costs of every tile of `settings`' frame (its `frame` number) in tiles of `tile_size`
// (scene::kMinTileSize..kMaxTileSize). `scene` is that frame's render-ready scene.
CostMap tile_cost_map(const RenderScene& scene, const scene::RenderSettings& settings, std::uint32_t tile_size,
                      const CostMapOptions& options = {});

}  // namespace dtraced::render
