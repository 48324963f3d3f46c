#include "render/tile.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <limits>
#include <vector>

#include "accel/geometry.h"
#include "math/rng.h"
#include "render/sampler.h"

namespace dtraced::render {

namespace {

// Film position of sample s of pixel (x, y). One sample per pixel goes through the pixel centre
// (the closed-form tests rely on it); more are spread over the pixel (box filter) by the
// stratified sequence of render/sampler.h, dimensions 0 and 1, point s: the first 2^k samples of
// a pixel cover it as a (0,k,2)-net.
math::SampleKey sample_key(const scene::RenderSettings& settings, std::uint32_t x, std::uint32_t y, std::uint32_t s) {
  return math::SampleKey{settings.seed, settings.frame, x, y, s};
}

// The film sampler of pixel (x, y), for camera_ray: the pixel's hashing done once for all of its
// samples. Only read when settings.samples > 1; left blank (no hashing) otherwise.
PixelSampler2 film_sampler(const scene::RenderSettings& settings, std::uint32_t x, std::uint32_t y) {
  return settings.samples > 1 ? PixelSampler2(sample_key(settings, x, y, 0), 0) : PixelSampler2{};
}

// Camera ray of sample s of pixel (x, y), whose film_sampler is `film`.
math::Ray camera_ray(const RenderScene& scene, const scene::RenderSettings& settings, const PixelSampler2& film,
                     std::uint32_t x, std::uint32_t y, std::uint32_t s) {
  double jx = 0.5, jy = 0.5;
  if (settings.samples > 1) {
    const Sample2 u = film.at(s);
    jx = u.u;
    jy = u.v;
  }
  return scene.camera().generate(x + jx, y + jy, settings.width, settings.height);
}

math::Ray camera_ray(const RenderScene& scene, const scene::RenderSettings& settings, std::uint32_t x, std::uint32_t y,
                     std::uint32_t s) {
  return camera_ray(scene, settings, film_sampler(settings, x, y), x, y, s);
}

// Groups of a pixel's samples for the adaptive error estimate: at checkpoint n they are the four
// aligned runs of n/4 samples, each a net of its own (render/sampler.h).
constexpr std::uint32_t kGroups = 4;

// One pixel's running sums, in double and in sample order. The sums of squares and the group
// sums are kept only when something reads them (adaptive sampling, variance output); they never
// change `sum`. Group k holds samples [k span, (k + 1) span); when sample kGroups * span arrives,
// neighbouring groups merge pairwise and span doubles, so at a checkpoint n = kGroups * span the
// groups are the four quarters of the pixel's samples.
struct PixelSums {
  double sum[3] = {0, 0, 0};
  double squares[3] = {0, 0, 0};
  double group[kGroups][3] = {};
  std::uint32_t span = 0;  // samples per group; 0 until the first sample
};

// The first group span: a quarter of the first checkpoint (at least 1), so that the groups are
// quarters at every checkpoint min_samples * 2^j when min_samples is a multiple of 4.
std::uint32_t first_span(const scene::RenderSettings& settings) { return std::max(1u, settings.min_samples / kGroups); }

// Adds sample s (0-based) of a pixel to its group sums.
void add_to_group(const Vec3f& l, std::uint32_t s, std::uint32_t span0, PixelSums& p) {
  if (p.span == 0) p.span = span0;
  while (s >= kGroups * p.span) {
    for (std::uint32_t k = 0; k < kGroups / 2; ++k) {
      for (int c = 0; c < 3; ++c) p.group[k][c] = p.group[2 * k][c] + p.group[2 * k + 1][c];
    }
    for (std::uint32_t k = kGroups / 2; k < kGroups; ++k) {
      for (int c = 0; c < 3; ++c) p.group[k][c] = 0.0;
    }
    p.span *= 2;
  }
  for (int c = 0; c < 3; ++c) p.group[s / p.span][c] += double(l[c]);
}

// Adds sample s to a pixel's sums, or counts it and drops it when it has a NaN or an Inf: a bad
// sample never reaches a pixel, and tests and logs can still see it. A dropped sample still
// counts in the pixel's sample count, as a zero.
void accumulate(const Vec3f& l, std::uint32_t s, std::uint32_t span0, PixelSums& p, bool squares, TraceStats& stats) {
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
    add_to_group(l, s, span0, p);
  }
}

// The unbiased sample variance of channel c after n >= 2 samples (0 for fewer).
double sample_variance(const PixelSums& p, int c, std::uint32_t n) {
  if (n < 2) return 0.0;
  const double mean = p.sum[c] / double(n);
  return std::max(0.0, (p.squares[c] - p.sum[c] * mean) / double(n - 1));
}

// The estimated variance of channel c's mean after n samples, from the pixel's own samples. When
// the samples fall in four equal groups of at least 2 (n = 4 span), each an aligned run of the
// stratified sequence and so a net of its own, it is the variance of the four group means over 4:
// the independent-sample formula applied to the groups. Where a pixel's variance falls as n^-a
// (a > 1 for stratified samples), s^2/n overstates it by about n^(a-1) (a pixel stops late); this
// by about 4^(a-1). Otherwise (groups of one, or a count that is not a checkpoint) the
// independent-sample s^2/n. With 3 degrees of freedom it can still come out low by chance; a pixel
// whose neighbourhood showed an edge or noise at the first checkpoint is also held by that
// (converged's prior). Taking the larger of this and s^2/n instead was measured and dropped: no
// better on the 10-sphere scene, 2-4 times the samples on lit_plane at the same target.
double mean_variance(const PixelSums& p, int c, std::uint32_t n) {
  if (p.span >= 2 && n == kGroups * p.span) {
    const double mean = p.sum[c] / double(n);
    double d2 = 0.0;
    for (std::uint32_t k = 0; k < kGroups; ++k) {
      const double d = p.group[k][c] / double(p.span) - mean;
      d2 += d * d;
    }
    return d2 / double(kGroups * (kGroups - 1));
  }
  return sample_variance(p, c, n) / double(n);
}

// The squared relative error of a mean `mean` whose variance is `var`: var / (mean^2 + 0.01).
// The 0.01 is relMSE's epsilon, so dark pixels are judged by absolute rather than relative error.
double relative_error2(double mean, double var) { return var / (mean * mean + 0.01); }

// Own checkpoints below this many samples decide nothing: 2 or 3 samples give a variance estimate
// of 1 or 2 degrees of freedom, too often near zero by chance.
constexpr std::uint32_t kMinOwnSamples = 4;

// Whether a pixel's estimated relative standard error after n samples is within the target:
// sqrt(max_c relative_error2(mean_c, var_c)) <= error_target. var_c is the larger of
// mean_variance and, when the pixel has one, its prior: the first checkpoint's neighbourhood
// estimate of the variance of a `first`-sample mean (first_checkpoint), carried to n samples as
// prior (first / n)^1.5, the rate at which a stratified pixel's variance falls across an edge.
// So a pixel whose neighbourhood showed an edge, a highlight or noise cannot stop on a few own
// samples that happened to agree (an outline that clips a pixel by a fifth misses all of 4
// samples two times in five), and keeps sampling in proportion to how much its neighbours differ.
bool converged(const scene::RenderSettings& settings, const PixelSums& p, std::uint32_t n, const float* prior,
               std::uint32_t first) {
  if (n < kMinOwnSamples) return false;
  const double ratio = double(first) / double(n);
  double worst = 0.0;
  for (int c = 0; c < 3; ++c) {
    double var = mean_variance(p, c, n);
    if (prior) var = std::max(var, double(prior[c]) * ratio * std::sqrt(ratio));
    worst = std::max(worst, relative_error2(p.sum[c] / double(n), var));
  }
  return std::sqrt(worst) <= settings.error_target;
}

struct TileContext {
  const RenderScene& scene;
  const scene::RenderSettings& settings;
  TraceLimits limits;
  bool adaptive = false;
  bool want_variance = false;
  std::uint32_t span0 = 1;  // first_span(settings)
  bool squares() const { return adaptive || want_variance; }
  // Samples of the first phase: every pixel takes them before any may stop. With adaptive
  // sampling, min_samples when that is a checkpoint (decided by the neighbourhood rule, see
  // first_checkpoint); otherwise settings.samples, and there is one phase only.
  std::uint32_t first = 0;
  // Whether a pixel may stop at checkpoint n from its own samples (the checkpoints after the first).
  bool own_checkpoint(std::uint32_t n) const {
    return adaptive && n > first && n >= kMinOwnSamples && scene::is_checkpoint(settings, n);
  }
};

// The state of every pixel of a tile between the two phases, row-major. Kept only when there are
// two phases (152 bytes of sums, 4 of count, 1 of done, 12 of prior a pixel); with one, each pixel
// is stored as soon as it is done.
struct TileSums {
  std::vector<PixelSums> sums;
  std::vector<std::uint32_t> taken;  // samples taken so far
  std::vector<std::uint8_t> done;    // stopped: takes no more samples
  // The first checkpoint's neighbourhood variance of each pixel's mean, 3 a pixel (first_checkpoint).
  std::vector<float> prior;
  bool kept() const { return !sums.empty(); }
  const float* prior_of(std::size_t i) const { return prior.empty() ? nullptr : &prior[i * 3]; }
};

// Writes pixel i of the tile (row-major index) from its sums after n samples.
void store(const TileContext& ctx, const PixelSums& p, std::uint32_t n, std::size_t i, Tile& tile) {
  for (int c = 0; c < 3; ++c) tile.rgb[i * 3 + c] = float(p.sum[c] / double(n));
  if (ctx.adaptive) tile.spp[i] = n;
  if (ctx.want_variance) {
    for (int c = 0; c < 3; ++c) tile.variance[i * 3 + c] = float(sample_variance(p, c, n) / double(n));
  }
}

// Takes each pixel that is not done from its current count up to `until` samples, one pixel at a
// time; a pixel stops early at a checkpoint after ctx.first once its own estimate converges.
void render_pixels(const TileContext& ctx, TileSums& st, std::uint32_t until, Tile& tile) {
  const TileRect& rect = tile.rect;
  for (std::uint32_t ty = 0; ty < rect.height; ++ty) {
    for (std::uint32_t tx = 0; tx < rect.width; ++tx) {
      const std::size_t i = std::size_t(ty) * rect.width + tx;
      if (st.kept() && st.done[i]) continue;
      const std::uint32_t x = rect.x0 + tx, y = rect.y0 + ty;
      PixelSums local;
      std::uint32_t local_n = 0;
      PixelSums& p = st.kept() ? st.sums[i] : local;
      std::uint32_t& n = st.kept() ? st.taken[i] : local_n;
      const PixelSampler2 film = film_sampler(ctx.settings, x, y);
      while (n < until) {
        accumulate(trace_radiance(ctx.scene, camera_ray(ctx.scene, ctx.settings, film, x, y, n),
                                  sample_key(ctx.settings, x, y, n), ctx.limits, tile.stats),
                   n, ctx.span0, p, ctx.squares(), tile.stats);
        ++n;
        if (ctx.own_checkpoint(n) && converged(ctx.settings, p, n, st.prior_of(i), ctx.first)) {
          if (st.kept()) st.done[i] = 1;
          break;
        }
      }
      if (!st.kept()) store(ctx, p, n, i, tile);
    }
  }
}

// Pixel blocks of one packet: 4 wide and 2 tall (8 rays) or 4 tall (16 rays), so the rays of a
// packet stay close together on the film (and so in the scene) in both directions. Lane i is
// pixel (i % 4, i / 4) of the block.
constexpr std::uint32_t kBlockW = 4;

// The packet height for the scene's kernels: 4x4 blocks on AVX-512 (a 16-ray packet is one
// vector) and AVX2 (two), where whole one-thread renders of the showcase, 100k spheres and a 1M
// triangle mesh measured 0-8 % faster than with 4x2 blocks and never slower (issue 16); 4x2 on
// SSE4 (a 16-ray packet would be four vectors; not measured) and the scalar isa.
std::uint32_t block_height(const RenderScene& scene) {
  const accel::Isa isa = scene.geometry().isa();
  return isa == accel::Isa::kAvx512 || isa == accel::Isa::kAvx2 ? 4 : 2;
}

// render_pixels in packets: the same bits, the camera rays of a 4 x kBlockH block traced together.
template <std::uint32_t kBlockH>
void render_packets(const TileContext& ctx, TileSums& st, std::uint32_t until, Tile& tile) {
  static_assert(kBlockW * kBlockH == accel::kPacketSize || kBlockW * kBlockH == accel::kPacketSize16);
  const TileRect& rect = tile.rect;
  const scene::RenderSettings& settings = ctx.settings;
  for (std::uint32_t by = 0; by < rect.height; by += kBlockH) {
    for (std::uint32_t bx = 0; bx < rect.width; bx += kBlockW) {
      // Lanes outside the tile (a partial block at its right or bottom edge) and pixels already
      // done stay inactive. Every active pixel of a block has taken the same number of samples
      // (both phases start all of them together), so one sample index serves the packet.
      std::uint32_t active = 0, valid = 0;
      std::size_t index[kBlockW * kBlockH] = {};
      PixelSums local_sums[kBlockW * kBlockH];
      std::uint32_t local_taken[kBlockW * kBlockH] = {};
      PixelSums* sums[kBlockW * kBlockH];
      std::uint32_t* taken[kBlockW * kBlockH];
      std::uint32_t start = until;
      PixelSampler2 film[kBlockW * kBlockH];
      for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
        const std::uint32_t tx = bx + i % kBlockW, ty = by + i / kBlockW;
        if (tx >= rect.width || ty >= rect.height) continue;
        valid |= 1u << i;
        index[i] = std::size_t(ty) * rect.width + tx;
        sums[i] = st.kept() ? &st.sums[index[i]] : &local_sums[i];
        taken[i] = st.kept() ? &st.taken[index[i]] : &local_taken[i];
        if ((st.kept() && st.done[index[i]]) || *taken[i] >= until) continue;
        active |= 1u << i;
        film[i] = film_sampler(settings, rect.x0 + tx, rect.y0 + ty);
        assert(start == until || start == *taken[i]);
        start = *taken[i];
      }
      // Each pixel still sums its own samples in sample order, in double, and decides when to
      // stop from its own samples only: the same bits as render_pixels, only interleaved with its
      // neighbours'. A converged lane leaves `active`; the packet goes on with the others.
      math::Ray rays[kBlockW * kBlockH];
      math::SampleKey keys[kBlockW * kBlockH];
      Vec3f radiance[kBlockW * kBlockH];
      // At one sample a pixel every ray goes through its pixel's centre (camera_ray): the block's
      // columns and rows share their screen coordinates, found once each.
      const bool centres = settings.samples <= 1 && active != 0;
      double screen_x[kBlockW], screen_y[kBlockH];
      if (centres) {
        const CameraF& camera = ctx.scene.camera();
        for (std::uint32_t c = 0; c < kBlockW; ++c) {
          screen_x[c] = camera.screen_x(rect.x0 + bx + c + 0.5, settings.width, settings.height);
        }
        for (std::uint32_t r = 0; r < kBlockH; ++r)
          screen_y[r] = camera.screen_y(rect.y0 + by + r + 0.5, settings.height);
      }
      for (std::uint32_t s = start; s < until && active != 0; ++s) {
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (active >> i & 1u) {
            const std::uint32_t x = rect.x0 + bx + i % kBlockW, y = rect.y0 + by + i / kBlockW;
            rays[i] = centres ? ctx.scene.camera().through(screen_x[i % kBlockW], screen_y[i / kBlockW])
                              : camera_ray(ctx.scene, settings, film[i], x, y, s);
            keys[i] = sample_key(settings, x, y, s);
          }
        }
        if constexpr (kBlockW * kBlockH == accel::kPacketSize16) {
          trace_radiance16(ctx.scene, rays, keys, active, ctx.limits, tile.stats, radiance);
        } else {
          trace_radiance8(ctx.scene, rays, keys, active, ctx.limits, tile.stats, radiance);
        }
        const bool checkpoint = ctx.own_checkpoint(s + 1);
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (!(active >> i & 1u)) continue;
          accumulate(radiance[i], s, ctx.span0, *sums[i], ctx.squares(), tile.stats);
          *taken[i] = s + 1;
          if (checkpoint && converged(settings, *sums[i], s + 1, st.prior_of(index[i]), ctx.first)) {
            if (st.kept()) st.done[index[i]] = 1;
            active &= ~(1u << i);
          }
        }
      }
      if (!st.kept()) {
        for (std::uint32_t i = 0; i < kBlockW * kBlockH; ++i) {
          if (valid >> i & 1u) store(ctx, *sums[i], *taken[i], index[i], tile);
        }
      }
    }
  }
}

void render_phase(const TileContext& ctx, bool packets, TileSums& st, std::uint32_t until, Tile& tile) {
  if (packets && block_height(ctx.scene) == 4) {
    render_packets<4>(ctx, st, until, tile);
  } else if (packets) {
    render_packets<2>(ctx, st, until, tile);
  } else {
    render_pixels(ctx, st, until, tile);
  }
}

// One camera sample to trace: pixel (x, y) of the image, sample index s.
struct SampleJob {
  std::uint32_t x = 0, y = 0, s = 0;
};

// Traces camera samples in packets of kN lanes whatever pixels they belong to: `next(job)` fills
// the next sample and returns false when there is none; `take(job, radiance)` gets each result in
// the order `next` gave them. Every lane of a packet gets the bits the scalar path gives its ray
// (the integrator's promise), so this is trace_radiance sample by sample, only fewer calls.
template <std::uint32_t kN, typename Next, typename Take>
void trace_jobs(const TileContext& ctx, TraceStats& stats, Next&& next, Take&& take) {
  static_assert(kN == accel::kPacketSize || kN == accel::kPacketSize16);
  SampleJob jobs[kN];
  math::Ray rays[kN];
  math::SampleKey keys[kN];
  Vec3f radiance[kN];
  // Jobs come pixel after pixel (several samples of one in a row): its film sampler is kept.
  // (No image is 2^32 - 1 pixels wide or tall: the first job's pixel differs from the start.)
  PixelSampler2 film;
  std::uint32_t film_x = std::numeric_limits<std::uint32_t>::max(), film_y = film_x;
  for (;;) {
    std::uint32_t n = 0;
    while (n < kN && next(jobs[n])) {
      if (jobs[n].x != film_x || jobs[n].y != film_y) {
        film = film_sampler(ctx.settings, jobs[n].x, jobs[n].y);
        film_x = jobs[n].x;
        film_y = jobs[n].y;
      }
      rays[n] = camera_ray(ctx.scene, ctx.settings, film, jobs[n].x, jobs[n].y, jobs[n].s);
      keys[n] = sample_key(ctx.settings, jobs[n].x, jobs[n].y, jobs[n].s);
      ++n;
    }
    if (n == 0) return;
    const std::uint32_t valid = (1u << n) - 1;
    if constexpr (kN == accel::kPacketSize16) {
      trace_radiance16(ctx.scene, rays, keys, valid, ctx.limits, stats, radiance);
    } else {
      trace_radiance8(ctx.scene, rays, keys, valid, ctx.limits, stats, radiance);
    }
    for (std::uint32_t j = 0; j < n; ++j) take(jobs[j], radiance[j]);
    if (n < kN) return;
  }
}

// The sample count at which a pixel that has taken n samples is next judged: its next own
// checkpoint, or `until`.
std::uint32_t next_stop(const TileContext& ctx, std::uint32_t n, std::uint32_t until) {
  // Checkpoints are min_samples * 2^k (scene::is_checkpoint): at most 32 candidates, not one per
  // sample count.
  for (std::uint64_t m = ctx.settings.min_samples; m < until; m *= 2) {
    if (m > n && ctx.own_checkpoint(std::uint32_t(m))) return std::uint32_t(m);
  }
  return until;
}

// The second phase of an adaptive tile in packets. After the first checkpoint most pixels have
// stopped, and those that go on are scattered (edges, highlights, glass), so packets of one
// sample index over a pixel block would run with a lane or two live. But between two of its
// checkpoints a pixel takes every sample whatever they show, so those samples can be traced
// together: the packets' lanes are (pixel, sample) pairs, a pixel's samples up to its next
// checkpoint and then the next pixel's, pixels in block order (neighbours share packets). Each
// pixel still sums its own samples in sample order and is judged at the same checkpoints from
// the same sums: the same bits as render_pixels.
template <std::uint32_t kBlockH>
void refine_packets(const TileContext& ctx, TileSums& st, std::uint32_t until, Tile& tile) {
  constexpr std::uint32_t kN = kBlockW * kBlockH;
  const TileRect& rect = tile.rect;
  std::vector<std::uint32_t> pending;  // tile pixel indices, block by block
  for (std::uint32_t by = 0; by < rect.height; by += kBlockH) {
    for (std::uint32_t bx = 0; bx < rect.width; bx += kBlockW) {
      for (std::uint32_t i = 0; i < kN; ++i) {
        const std::uint32_t tx = bx + i % kBlockW, ty = by + i / kBlockW;
        if (tx >= rect.width || ty >= rect.height) continue;
        const std::uint32_t index = ty * rect.width + tx;
        if (!st.done[index] && st.taken[index] < until) pending.push_back(index);
      }
    }
  }
  std::vector<std::uint32_t> stops;
  while (!pending.empty()) {
    // Every pending pixel goes to its next checkpoint (or to until) in this round.
    stops.resize(pending.size());
    for (std::size_t k = 0; k < pending.size(); ++k) stops[k] = next_stop(ctx, st.taken[pending[k]], until);
    std::size_t k = 0;                       // the pending pixel whose samples are queued next
    std::uint32_t s = st.taken[pending[0]];  // and its next sample
    trace_jobs<kN>(
        ctx, tile.stats,
        [&](SampleJob& job) {
          if (k == pending.size()) return false;
          job = {rect.x0 + pending[k] % rect.width, rect.y0 + pending[k] / rect.width, s};
          if (++s == stops[k] && ++k < pending.size()) s = st.taken[pending[k]];
          return true;
        },
        [&](const SampleJob& job, const Vec3f& radiance) {
          const std::uint32_t index = (job.y - rect.y0) * rect.width + (job.x - rect.x0);
          accumulate(radiance, job.s, ctx.span0, st.sums[index], ctx.squares(), tile.stats);
          const std::uint32_t n = job.s + 1;
          st.taken[index] = n;
          if (ctx.own_checkpoint(n) && converged(ctx.settings, st.sums[index], n, st.prior_of(index), ctx.first)) {
            st.done[index] = 1;
          }
        });
    std::erase_if(pending, [&](std::uint32_t index) { return st.done[index] || st.taken[index] >= until; });
  }
}

// The means of a pixel's 3x3 neighbourhood (fewer at the image's edges), with their offsets
// from the pixel.
struct Neighbourhood {
  double value[9] = {};
  int dx[9] = {}, dy[9] = {};
  std::uint32_t count = 0;
};

// The unbiased variance of the values about their mean (0 for fewer than 2).
double flat_variance(const Neighbourhood& nb) {
  if (nb.count < 2) return 0.0;
  double sum = 0.0, squares = 0.0;
  for (std::uint32_t j = 0; j < nb.count; ++j) sum += nb.value[j], squares += nb.value[j] * nb.value[j];
  return std::max(0.0, (squares - sum * sum / double(nb.count)) / double(nb.count - 1));
}

// The unbiased variance of the values about the plane a + b dx + c dy fitted to them by least
// squares: a shading gradient across the neighbourhood is image, not error, and leaves nothing;
// noise, an edge, a corner or a highlight do. The neighbourhood is a product of runs of offsets,
// so centred dx and dy are orthogonal and the fit is two projections. Fewer than 4 values (an
// image one pixel wide) leave no degree of freedom: their flat variance instead.
double residual_variance(const Neighbourhood& nb) {
  if (nb.count < 4) return flat_variance(nb);
  const double k = double(nb.count);
  double mx = 0.0, my = 0.0, mv = 0.0;
  for (std::uint32_t j = 0; j < nb.count; ++j) mx += nb.dx[j], my += nb.dy[j], mv += nb.value[j];
  mx /= k, my /= k, mv /= k;
  double sxx = 0.0, syy = 0.0, sxv = 0.0, syv = 0.0, svv = 0.0;
  for (std::uint32_t j = 0; j < nb.count; ++j) {
    const double x = nb.dx[j] - mx, y = nb.dy[j] - my, v = nb.value[j] - mv;
    sxx += x * x, syy += y * y, sxv += x * v, syv += y * v, svv += v * v;
  }
  const double residual = svv - (sxx > 0 ? sxv * sxv / sxx : 0.0) - (syy > 0 ? syv * syv / syy : 0.0);
  const double dof = k - 1.0 - (sxx > 0) - (syy > 0);
  return dof > 0 ? std::max(0.0, residual / dof) : 0.0;
}

// residual_variance9 (below) of `count` pixels of one image row at once: pixel k's neighbourhood
// is columns k, k + 1, k + 2 of the rows above (r0), at (r1) and below (r2) it. Written over the
// row so that the compiler runs neighbouring pixels in one vector: called per pixel and channel,
// the first checkpoint took about 6.5 % of an adaptive whitted10 render (-s 16 -N 1, target 0.1).
void residual_variance9_row(const double* r0, const double* r1, const double* r2, std::uint32_t count, double* out) {
  for (std::uint32_t k = 0; k < count; ++k) {
    const double v0 = r0[k], v1 = r0[k + 1], v2 = r0[k + 2];
    const double v3 = r1[k], v4 = r1[k + 1], v5 = r1[k + 2];
    const double v6 = r2[k], v7 = r2[k + 1], v8 = r2[k + 2];
    double mv = 0.0;
    mv += v0, mv += v1, mv += v2, mv += v3, mv += v4, mv += v5, mv += v6, mv += v7, mv += v8;
    mv /= 9.0;
    const double d0 = v0 - mv, d1 = v1 - mv, d2 = v2 - mv, d3 = v3 - mv, d4 = v4 - mv;
    const double d5 = v5 - mv, d6 = v6 - mv, d7 = v7 - mv, d8 = v8 - mv;
    double svv = 0.0;
    svv += d0 * d0, svv += d1 * d1, svv += d2 * d2, svv += d3 * d3, svv += d4 * d4;
    svv += d5 * d5, svv += d6 * d6, svv += d7 * d7, svv += d8 * d8;
    double sxv = 0.0, syv = 0.0;
    sxv -= d0, sxv += d2, sxv -= d3, sxv += d5, sxv -= d6, sxv += d8;
    syv -= d0, syv -= d1, syv -= d2, syv += d6, syv += d7, syv += d8;
    const double residual = svv - sxv * sxv / 6.0 - syv * syv / 6.0;
    const double r = residual / 6.0;
    out[k] = 0.0 < r ? r : 0.0;  // std::max(0.0, r)
  }
}

// residual_variance of a full 3x3 neighbourhood (offsets -1, 0, 1 in rows, then columns) whose
// values are v, with its constants folded: the offsets' means are exactly 0, sxx = syy = 6 and 6
// degrees of freedom are left. A product with an offset of 0 adds a zero to a sum, and one of
// +-1 is exact, so every sum is the same float operations in the same order as the general
// function's: the same bits.
double residual_variance9(const double* v) {
  double r;
  residual_variance9_row(v, v + 3, v + 6, 1, &r);
  return r;
}

// The first checkpoint's neighbourhood rule. A pixel's own samples cannot see an edge that none
// of them crossed: a pixel that an outline clips by a sliver has a fair chance that its first
// min_samples samples all land on one side, agree exactly, and estimate a variance of zero; with
// min_samples = 1 there is no own estimate at all. Its neighbours across the outline do see it.
// So at the first checkpoint n = min_samples a pixel's variance of its mean is estimated as the
// larger of its own (mean_variance, from kMinOwnSamples up) and the neighbourhood's: the residual
// variance of the means of the pixels of its 3x3 neighbourhood inside the image, each over its
// first n samples, about the plane fitted to them (residual_variance). Where the image is flat or
// a smooth gradient, that is the variance of an n-sample mean with 6 degrees of freedom; an edge,
// a corner or a highlight raise it, as neighbours that differ trigger POV-Ray's antialiasing. The
// pixel stops when its relative error (relative_error2, of its own mean) is within the target;
// otherwise the neighbourhood's estimate stays with it as its prior for the later checkpoints
// (converged). The samples of a pixel are a pure function of (seed, frame, pixel, sample index),
// so a neighbour outside the tile (the one-pixel border) is rendered here for its first n samples
// alone, with the same bits as its own tile gives it, and the decision does not depend on the
// tiling.
void first_checkpoint(const TileContext& ctx, bool packets, TileSums& st, Tile& tile) {
  const TileRect& rect = tile.rect;
  const scene::RenderSettings& settings = ctx.settings;
  const std::uint32_t n = ctx.first;
  // The first n samples' sums over the tile grown by one pixel on each side, clipped to the image.
  const std::uint32_t gx0 = rect.x0 > 0 ? rect.x0 - 1 : 0, gy0 = rect.y0 > 0 ? rect.y0 - 1 : 0;
  const std::uint32_t gx1 = std::min(rect.x0 + rect.width + 1, settings.width);
  const std::uint32_t gy1 = std::min(rect.y0 + rect.height + 1, settings.height);
  const std::uint32_t gw = gx1 - gx0;
  std::vector<const PixelSums*> grown(std::size_t(gw) * (gy1 - gy0), nullptr);
  std::vector<PixelSums> outside;
  outside.reserve(2 * std::size_t(gw) + 2 * std::size_t(gy1 - gy0));  // never reallocates: pointers stay valid
  std::vector<SampleJob> at;  // where each border pixel is (sample 0), in the order of `outside`
  at.reserve(outside.capacity());
  for (std::uint32_t y = gy0; y < gy1; ++y) {
    for (std::uint32_t x = gx0; x < gx1; ++x) {
      const bool inside = x >= rect.x0 && x < rect.x0 + rect.width && y >= rect.y0 && y < rect.y0 + rect.height;
      if (!inside) at.push_back({x, y, 0});
      grown[std::size_t(y - gy0) * gw + (x - gx0)] =
          inside ? &st.sums[std::size_t(y - rect.y0) * rect.width + (x - rect.x0)] : &outside.emplace_back();
    }
  }
  // The border pixels' first n samples, pixel after pixel, each in sample order; the results
  // come back in the same order.
  TraceStats border;
  std::size_t queued = 0, summed = 0;  // samples handed out and summed, n per border pixel
  const auto next = [&](SampleJob& job) {
    if (queued == at.size() * n) return false;
    job = at[queued / n];
    job.s = std::uint32_t(queued++ % n);
    return true;
  };
  const auto take = [&](const SampleJob& job, const Vec3f& radiance) {
    accumulate(radiance, job.s, ctx.span0, outside[summed++ / n], true, border);
  };
  if (packets && block_height(ctx.scene) == 4) {
    trace_jobs<accel::kPacketSize16>(ctx, border, next, take);
  } else if (packets) {
    trace_jobs<accel::kPacketSize>(ctx, border, next, take);
  } else {
    for (SampleJob job; next(job);) {
      take(job, trace_radiance(ctx.scene, camera_ray(ctx.scene, settings, job.x, job.y, job.s),
                               sample_key(settings, job.x, job.y, job.s), ctx.limits, border));
    }
  }
  assert(summed == outside.size() * n);
  // Border rays are extra work, not part of the image: their NaN/Inf samples belong to the
  // pixel's own tile, which counts them.
  tile.stats.border_rays += border.rays;
  // Each grown pixel's mean per channel, once (each is in up to 9 neighbourhoods): one plane a
  // channel, so that a row of neighbourhoods is three runs of each plane.
  const std::size_t plane = grown.size();
  std::vector<double> means(plane * 3);
  for (std::size_t j = 0; j < plane; ++j) {
    for (int c = 0; c < 3; ++c) means[std::size_t(c) * plane + j] = grown[j]->sum[c] / double(n);
  }
  const double limit2 = settings.error_target * settings.error_target;
  // The pixels of a tile row whose neighbourhood is a full 3x3 inside the image: [fx0, fx1).
  const std::uint32_t fx0 = std::max(rect.x0, 1u), fx1 = std::min(rect.x0 + rect.width, settings.width - 1);
  std::vector<double> full(fx1 > fx0 ? std::size_t(fx1 - fx0) * 3 : 0);  // a row's, channel after channel
  for (std::uint32_t ty = 0; ty < rect.height; ++ty) {
    const std::uint32_t y = rect.y0 + ty;
    const bool full_row = y > 0 && y + 1 < settings.height && fx1 > fx0;
    if (full_row) {
      for (int c = 0; c < 3; ++c) {
        const double* row = &means[std::size_t(c) * plane + std::size_t(y - 1 - gy0) * gw + (fx0 - 1 - gx0)];
        residual_variance9_row(row, row + gw, row + 2 * std::size_t(gw), fx1 - fx0,
                               &full[std::size_t(c) * (fx1 - fx0)]);
      }
    }
    for (std::uint32_t tx = 0; tx < rect.width; ++tx) {
      const std::uint32_t x = rect.x0 + tx;
      const std::size_t i = std::size_t(ty) * rect.width + tx;
      const PixelSums& own = st.sums[i];
      const bool in_full = full_row && x >= fx0 && x < fx1;
      // Otherwise the neighbourhood, in a fixed order (rows, then columns): offsets, and where its
      // means are.
      Neighbourhood nb;
      std::size_t at[9];
      if (!in_full) {
        for (std::uint32_t ny = (y > gy0 ? y - 1 : y); ny <= std::min(y + 1, gy1 - 1); ++ny) {
          for (std::uint32_t nx = (x > gx0 ? x - 1 : x); nx <= std::min(x + 1, gx1 - 1); ++nx) {
            at[nb.count] = std::size_t(ny - gy0) * gw + (nx - gx0);
            nb.dx[nb.count] = int(nx) - int(x);
            nb.dy[nb.count] = int(ny) - int(y);
            ++nb.count;
          }
        }
      }
      bool pass = true;
      for (int c = 0; c < 3; ++c) {
        double var;
        if (in_full) {
          var = full[std::size_t(c) * (fx1 - fx0) + (x - fx0)];
        } else {
          for (std::uint32_t j = 0; j < nb.count; ++j) nb.value[j] = means[std::size_t(c) * plane + at[j]];
          var = nb.count == 9 ? residual_variance9(nb.value) : residual_variance(nb);
        }
        st.prior[i * 3 + c] = float(var);
        if (n >= kMinOwnSamples) var = std::max(var, mean_variance(own, c, n));
        pass = pass && relative_error2(own.sum[c] / double(n), var) <= limit2;
      }
      st.done[i] = pass;
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
  const bool adaptive = settings.error_target > 0;
  const TraceLimits limits{Vec3f(settings.background), settings.max_depth, float(settings.branch_cutoff),
                           options.specialise};
  TileContext ctx{scene, settings, limits, adaptive, options.want_variance, first_span(settings)};
  ctx.first =
      adaptive && scene::is_checkpoint(settings, settings.min_samples) ? settings.min_samples : settings.samples;
  if (ctx.adaptive) tile.spp.assign(pixels, 0);
  if (ctx.want_variance) tile.variance.assign(pixels * 3, 0.0f);
  TileSums st;
  if (ctx.first == settings.samples) {
    render_phase(ctx, options.packets, st, settings.samples, tile);  // one phase: stored as it goes
    return tile;
  }
  st.sums.resize(pixels);
  st.taken.assign(pixels, 0);
  st.done.assign(pixels, 0);
  st.prior.assign(pixels * 3, 0.0f);
  render_phase(ctx, options.packets, st, ctx.first, tile);
  first_checkpoint(ctx, options.packets, st, tile);
  if (options.packets && block_height(scene) == 4) {
    refine_packets<4>(ctx, st, settings.samples, tile);
  } else if (options.packets) {
    refine_packets<2>(ctx, st, settings.samples, tile);
  } else {
    render_phase(ctx, options.packets, st, settings.samples, tile);
  }
  for (std::size_t i = 0; i < pixels; ++i) store(ctx, st.sums[i], st.taken[i], i, tile);
  return tile;
}

}  // namespace dtraced::render
