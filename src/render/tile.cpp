#include "render/tile.h"

#include <algorithm>
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

// One pixel's running sums, in double and in sample order. The sums of squares are kept only
// when something reads them (adaptive sampling, variance output); they never change `sum`.
struct PixelSums {
  double sum[3] = {0, 0, 0};
  double squares[3] = {0, 0, 0};
};

// Adds one sample to a pixel's sums, or counts it and drops it when it has a NaN or an Inf: a bad
// sample never reaches a pixel, and tests and logs can still see it. A dropped sample still
// counts in the pixel's sample count, as a zero.
void accumulate(const Vec3f& l, PixelSums& p, bool squares, TraceStats& stats) {
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
  for (int c = 0; c < 3; ++c) p.sum[c] += double(l[c]);
  if (squares) {
    for (int c = 0; c < 3; ++c) p.squares[c] += double(l[c]) * double(l[c]);
  }
}

// The unbiased sample variance of channel c after n >= 2 samples (0 for fewer).
double sample_variance(const PixelSums& p, int c, std::uint32_t n) {
  if (n < 2) return 0.0;
  const double mean = p.sum[c] / double(n);
  return std::max(0.0, (p.squares[c] - p.sum[c] * mean) / double(n - 1));
}

// Where a pixel may stop: n = min_samples * 2^k below settings.samples.
bool is_checkpoint(const scene::RenderSettings& settings, std::uint32_t n) {
  if (n < settings.min_samples || n >= settings.samples || n % settings.min_samples != 0) return false;
  const std::uint32_t k = n / settings.min_samples;
  return (k & (k - 1)) == 0;
}

// Whether a pixel's estimated relative standard error after n samples is within the target:
// sqrt(max_c (s_c^2 / n) / (mean_c^2 + 0.01)) <= error_target. The 0.01 is relMSE's epsilon, so
// dark pixels are judged by absolute rather than relative error. Needs n >= 2 to estimate.
bool converged(const scene::RenderSettings& settings, const PixelSums& p, std::uint32_t n) {
  if (n < 2) return false;
  double worst = 0.0;
  for (int c = 0; c < 3; ++c) {
    const double mean = p.sum[c] / double(n);
    worst = std::max(worst, sample_variance(p, c, n) / double(n) / (mean * mean + 0.01));
  }
  return std::sqrt(worst) <= settings.error_target;
}

struct TileContext {
  const RenderScene& scene;
  const scene::RenderSettings& settings;
  TraceLimits limits;
  bool adaptive = false;
  bool want_variance = false;
  bool squares() const { return adaptive || want_variance; }
};

// Writes pixel i of the tile (row-major index) from its sums after n samples.
void store(const TileContext& ctx, const PixelSums& p, std::uint32_t n, std::size_t i, Tile& tile) {
  for (int c = 0; c < 3; ++c) tile.rgb[i * 3 + c] = float(p.sum[c] / double(n));
  if (ctx.adaptive) tile.spp[i] = n;
  if (ctx.want_variance) {
    for (int c = 0; c < 3; ++c) tile.variance[i * 3 + c] = float(sample_variance(p, c, n) / double(n));
  }
}

void render_pixels(const TileContext& ctx, Tile& tile) {
  const TileRect& rect = tile.rect;
  const scene::RenderSettings& settings = ctx.settings;
  for (std::uint32_t ty = 0; ty < rect.height; ++ty) {
    for (std::uint32_t tx = 0; tx < rect.width; ++tx) {
      const std::uint32_t x = rect.x0 + tx, y = rect.y0 + ty;
      PixelSums p;
      std::uint32_t n = 0;
      while (n < settings.samples) {
        accumulate(trace_radiance(ctx.scene, camera_ray(ctx.scene, settings, x, y, n), sample_key(settings, x, y, n),
                                  ctx.limits, tile.stats),
                   p, ctx.squares(), tile.stats);
        ++n;
        if (ctx.adaptive && is_checkpoint(settings, n) && converged(settings, p, n)) break;
      }
      store(ctx, p, n, std::size_t(ty) * rect.width + tx, tile);
    }
  }
}

// Pixel blocks of one packet: 4 wide and 2 tall, so the rays of a packet stay close together on
// the film (and so in the scene) in both directions. Lane i is pixel (i % 4, i / 4) of the block.
constexpr std::uint32_t kBlockW = 4, kBlockH = 2;
static_assert(kBlockW * kBlockH == accel::kPacketSize);

void render_packets(const TileContext& ctx, Tile& tile) {
  const TileRect& rect = tile.rect;
  const scene::RenderSettings& settings = ctx.settings;
  for (std::uint32_t by = 0; by < rect.height; by += kBlockH) {
    for (std::uint32_t bx = 0; bx < rect.width; bx += kBlockW) {
      // Lanes outside the tile (a partial block at its right or bottom edge) stay invalid.
      std::uint32_t valid = 0;
      for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
        if (bx + i % kBlockW < rect.width && by + i / kBlockW < rect.height) valid |= 1u << i;
      }
      // Each pixel still sums its own samples in sample order, in double, and decides when to
      // stop from its own samples only: the same bits as render_pixels, only interleaved with its
      // neighbours'. A converged lane leaves `active`; the packet goes on with the others.
      PixelSums sums[kBlockW * kBlockH];
      std::uint32_t taken[kBlockW * kBlockH] = {};
      math::Ray rays[kBlockW * kBlockH];
      math::SampleKey keys[kBlockW * kBlockH];
      Vec3f radiance[kBlockW * kBlockH];
      std::uint32_t active = valid;
      for (std::uint32_t s = 0; s < settings.samples && active != 0; ++s) {
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (active >> i & 1u) {
            const std::uint32_t x = rect.x0 + bx + i % kBlockW, y = rect.y0 + by + i / kBlockW;
            rays[i] = camera_ray(ctx.scene, settings, x, y, s);
            keys[i] = sample_key(settings, x, y, s);
          }
        }
        trace_radiance8(ctx.scene, rays, keys, active, ctx.limits, tile.stats, radiance);
        const bool checkpoint = ctx.adaptive && is_checkpoint(settings, s + 1);
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (!(active >> i & 1u)) continue;
          accumulate(radiance[i], sums[i], ctx.squares(), tile.stats);
          taken[i] = s + 1;
          if (checkpoint && converged(settings, sums[i], s + 1)) active &= ~(1u << i);
        }
      }
      for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
        if (!(valid >> i & 1u)) continue;
        const std::uint32_t tx = bx + i % kBlockW, ty = by + i / kBlockW;
        store(ctx, sums[i], taken[i], std::size_t(ty) * rect.width + tx, tile);
      }
    }
  }
}

}  // namespace

Tile render_tile(const RenderScene& scene, const scene::RenderSettings& settings, const TileRect& rect,
                 const TileOptions& options) {
  assert(rect.x0 + rect.width <= settings.width && rect.y0 + rect.height <= settings.height);
  assert(settings.samples >= 1 && settings.min_samples >= 1);
  Tile tile;
  tile.rect = rect;
  const std::size_t pixels = std::size_t(rect.width) * rect.height;
  tile.rgb.assign(pixels * 3, 0.0f);
  const TileContext ctx{scene, settings,
                        TraceLimits{Vec3f(settings.background), settings.max_depth, options.specialise},
                        settings.error_target > 0, options.want_variance};
  if (ctx.adaptive) tile.spp.assign(pixels, 0);
  if (ctx.want_variance) tile.variance.assign(pixels * 3, 0.0f);
  if (options.packets) {
    render_packets(ctx, tile);
  } else {
    render_pixels(ctx, tile);
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
