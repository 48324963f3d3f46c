// dtraced::render tiles: the unit of work of both the local renderer and the farm.
//
// render_tile is a pure function of (scene, settings, rect): every sample's random numbers come
// from a counter-based hash of (seed, frame, x, y, sample index) and each pixel sums its samples
// in sample order, so a pixel has the same bits whichever tile, thread or host renders it, and
// whether its camera rays were traced one by one or in packets.
//
// Adaptive sampling (settings.error_target > 0): a pixel may stop at the checkpoints
// n = min_samples, 2 min_samples, 4 min_samples, ... below settings.samples, once its estimated
// relative standard error sqrt(max_c (v_c / (mean_c^2 + 0.01))) is at most error_target;
// otherwise it takes all settings.samples. v_c estimates the variance of its mean: from 4 samples
// up, from its own samples (the spread of its four quarters' means, or s^2/n). At the first
// checkpoint (n = min_samples, 1 and 2 included) v_c is at least the variance of its 3x3
// neighbourhood's means about their fitted plane: one pixel's samples can all miss an edge that
// clips it, its neighbours' do not, and with 1 sample it has no estimate of its own. The tile
// renders its one-pixel border for that (TraceStats::border_rays). A pixel that goes on keeps
// that neighbourhood estimate as a prior, scaled by (min_samples / n)^1.5, so that later
// checkpoints cannot stop it on a few own samples that agree by chance. Every decision reads
// samples that are a pure function of (seed, frame, pixel, sample index), so the image stays the
// same bits under any tiling, thread count, packet mode, ISA or farm layout. A sample dropped as
// NaN/Inf counts as a zero. Memory: an adaptive render keeps 169 bytes of running state per pixel
// of the tile between its phases; a uniform one keeps a block's only.
// Thread-safe: any number of tiles may render at once over one shared RenderScene.
#pragma once

#include <cstdint>
#include <vector>

#include "render/integrator.h"
#include "render/render_scene.h"
#include "scene/description.h"
#include "scene/tiling.h"

namespace dtraced::render {

using scene::TileRect;

struct Tile {
  TileRect rect;
  std::vector<float> rgb;  // width * height * 3 linear floats, row-major, top row first
  // Samples each pixel took, width * height, row-major: filled only with adaptive sampling
  // (settings.error_target > 0); empty otherwise, when every pixel took settings.samples.
  std::vector<std::uint32_t> spp;
  // TileOptions::want_variance only: each pixel's estimated variance of its mean, s^2 / n per
  // channel (width * height * 3, like rgb); 0 for a pixel of one sample.
  std::vector<float> variance;
  TraceStats stats;
};

struct TileOptions {
  // Trace camera rays in packets of kPacketSize (blocks of 4x2 pixels, one sample index at a
  // time; see trace_radiance8) rather than pixel by pixel. Both give the same bits and ray
  // counts; the per-pixel path stays as the reference the tests compare against.
  bool packets = true;
  // TraceLimits::specialise: false runs the generic integrator path (same bits).
  bool specialise = true;
  // Fill Tile::variance (for error reports); the image is the same bits either way.
  bool want_variance = false;
};

// Renders the pixels of `rect`, which must lie inside the settings' image.
Tile render_tile(const RenderScene& scene, const scene::RenderSettings& settings, const TileRect& rect,
                 const TileOptions& options = {});

}  // namespace dtraced::render
