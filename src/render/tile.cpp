#include "render/tile.h"

#include <cassert>
#include <cmath>

#include "accel/geometry.h"
#include "math/rng.h"

namespace dtraced::render {

namespace {

// Film position of sample s of pixel (x, y). One sample per pixel goes through the pixel centre
// (the closed-form tests rely on it); more are jittered uniformly over the pixel (box filter).
math::SampleKey sample_key(const scene::RenderSettings& settings, std::uint32_t x, std::uint32_t y, std::uint32_t s) {
  return math::SampleKey{settings.seed, settings.frame, x, y, s};
}

math::Ray camera_ray(const RenderScene& scene, const scene::RenderSettings& settings, std::uint32_t x, std::uint32_t y,
                     std::uint32_t s) {
  double jx = 0.5, jy = 0.5;
  if (settings.samples > 1) {
    const math::SampleKey key = sample_key(settings, x, y, s);
    jx = math::sample_uniform(key, 0);
    jy = math::sample_uniform(key, 1);
  }
  return scene.camera().generate(x + jx, y + jy, settings.width, settings.height);
}

// Adds one sample to a pixel's sum, or counts it and drops it when it has a NaN or an Inf: a bad
// sample never reaches a pixel, and tests and logs can still see it.
void accumulate(const Vec3f& l, double sum[3], TraceStats& stats) {
  bool has_nan = false, has_inf = false;
  for (int c = 0; c < 3; ++c) {
    has_nan = has_nan || std::isnan(l[c]);
    has_inf = has_inf || std::isinf(l[c]);
  }
  if (has_nan || has_inf) {
    stats.nan_samples += has_nan;
    stats.inf_samples += has_inf && !has_nan;
    return;
  }
  for (int c = 0; c < 3; ++c) sum[c] += double(l[c]);
}

void store(const double sum[3], std::uint32_t spp, float* out) {
  for (int c = 0; c < 3; ++c) out[c] = float(sum[c] / double(spp));
}

void render_pixels(const RenderScene& scene, const scene::RenderSettings& settings, const TraceLimits& limits,
                   Tile& tile) {
  const TileRect& rect = tile.rect;
  for (std::uint32_t ty = 0; ty < rect.height; ++ty) {
    for (std::uint32_t tx = 0; tx < rect.width; ++tx) {
      const std::uint32_t x = rect.x0 + tx, y = rect.y0 + ty;
      double sum[3] = {0, 0, 0};
      for (std::uint32_t s = 0; s < settings.samples; ++s) {
        accumulate(trace_radiance(scene, camera_ray(scene, settings, x, y, s), sample_key(settings, x, y, s), limits,
                                  tile.stats),
                   sum, tile.stats);
      }
      store(sum, settings.samples, &tile.rgb[(std::size_t(ty) * rect.width + tx) * 3]);
    }
  }
}

// Pixel blocks of one packet: 4 wide and 2 tall, so the rays of a packet stay close together on
// the film (and so in the scene) in both directions. Lane i is pixel (i % 4, i / 4) of the block.
constexpr std::uint32_t kBlockW = 4, kBlockH = 2;
static_assert(kBlockW * kBlockH == accel::kPacketSize);

void render_packets(const RenderScene& scene, const scene::RenderSettings& settings, const TraceLimits& limits,
                    Tile& tile) {
  const TileRect& rect = tile.rect;
  for (std::uint32_t by = 0; by < rect.height; by += kBlockH) {
    for (std::uint32_t bx = 0; bx < rect.width; bx += kBlockW) {
      // Lanes outside the tile (a partial block at its right or bottom edge) stay invalid.
      std::uint32_t valid = 0;
      for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
        if (bx + i % kBlockW < rect.width && by + i / kBlockW < rect.height) valid |= 1u << i;
      }
      // Each pixel still sums its own samples in sample order, in double: the same bits as
      // render_pixels, only interleaved with its neighbours'.
      double sum[kBlockW * kBlockH][3] = {};
      math::Ray rays[kBlockW * kBlockH];
      math::SampleKey keys[kBlockW * kBlockH];
      Vec3f radiance[kBlockW * kBlockH];
      for (std::uint32_t s = 0; s < settings.samples; ++s) {
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (valid >> i & 1u) {
            const std::uint32_t x = rect.x0 + bx + i % kBlockW, y = rect.y0 + by + i / kBlockW;
            rays[i] = camera_ray(scene, settings, x, y, s);
            keys[i] = sample_key(settings, x, y, s);
          }
        }
        trace_radiance8(scene, rays, keys, valid, limits, tile.stats, radiance);
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (valid >> i & 1u) accumulate(radiance[i], sum[i], tile.stats);
        }
      }
      for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
        if (!(valid >> i & 1u)) continue;
        const std::uint32_t tx = bx + i % kBlockW, ty = by + i / kBlockW;
        store(sum[i], settings.samples, &tile.rgb[(std::size_t(ty) * rect.width + tx) * 3]);
      }
    }
  }
}

}  // namespace

Tile render_tile(const RenderScene& scene, const scene::RenderSettings& settings, const TileRect& rect,
                 const TileOptions& options) {
  assert(rect.x0 + rect.width <= settings.width && rect.y0 + rect.height <= settings.height);
  Tile tile;
  tile.rect = rect;
  tile.rgb.assign(std::size_t(rect.width) * rect.height * 3, 0.0f);
  const TraceLimits limits{Vec3f(settings.background), settings.max_depth, options.specialise};
  if (options.packets) {
    render_packets(scene, settings, limits, tile);
  } else {
    render_pixels(scene, settings, limits, tile);
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
