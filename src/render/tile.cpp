#include "render/tile.h"

#include <cassert>
#include <cmath>

#include "math/rng.h"

namespace dtraced::render {

Tile render_tile(const RenderScene& scene, const scene::RenderSettings& settings, const TileRect& rect) {
  assert(rect.x0 + rect.width <= settings.width && rect.y0 + rect.height <= settings.height);
  Tile tile;
  tile.rect = rect;
  tile.rgb.assign(std::size_t(rect.width) * rect.height * 3, 0.0f);
  const TraceLimits limits{Vec3f(settings.background), settings.max_depth};
  const std::uint32_t spp = settings.samples;
  for (std::uint32_t ty = 0; ty < rect.height; ++ty) {
    for (std::uint32_t tx = 0; tx < rect.width; ++tx) {
      const std::uint32_t x = rect.x0 + tx, y = rect.y0 + ty;
      double sum[3] = {0, 0, 0};
      for (std::uint32_t s = 0; s < spp; ++s) {
        // One sample per pixel goes through the pixel centre (the closed-form tests rely on
        // it); more are jittered uniformly over the pixel (box filter).
        double jx = 0.5, jy = 0.5;
        if (spp > 1) {
          const math::SampleKey key{settings.seed, settings.frame, x, y, s};
          jx = math::sample_uniform(key, 0);
          jy = math::sample_uniform(key, 1);
        }
        const math::Ray ray = scene.camera().generate(x + jx, y + jy, settings.width, settings.height);
        const Vec3f l = trace_radiance(scene, ray, limits, tile.stats);
        bool has_nan = false, has_inf = false;
        for (int c = 0; c < 3; ++c) {
          has_nan = has_nan || std::isnan(l[c]);
          has_inf = has_inf || std::isinf(l[c]);
        }
        if (has_nan || has_inf) {
          // Never let a bad sample reach a pixel; count it so tests and logs can see it.
          tile.stats.nan_samples += has_nan;
          tile.stats.inf_samples += has_inf && !has_nan;
          continue;
        }
        for (int c = 0; c < 3; ++c) sum[c] += double(l[c]);
      }
      float* out = &tile.rgb[(std::size_t(ty) * rect.width + tx) * 3];
      for (int c = 0; c < 3; ++c) out[c] = float(sum[c] / double(spp));
    }
  }
  return tile;
}

std::vector<TileRect> split_into_tiles(std::uint32_t width, std::uint32_t height, std::uint32_t tile_size) {
  assert(tile_size > 0);
  std::vector<TileRect> tiles;
  for (std::uint32_t y = 0; y < height; y += tile_size) {
    for (std::uint32_t x = 0; x < width; x += tile_size) {
      tiles.push_back({x, y, std::min(tile_size, width - x), std::min(tile_size, height - y)});
    }
  }
  return tiles;
}

}  // namespace dtraced::render
