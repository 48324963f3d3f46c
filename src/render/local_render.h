// dtraced::render local rendering: a whole image on this machine's cores.
//
// Tiles are handed to a fixed set of threads through one atomic counter; each tile writes a
// disjoint region of the image, so the result is bitwise identical for any tile size and thread
// count. The progress callback runs on the calling thread only.
#pragma once

#include <cstdint>
#include <functional>
#include <vector>

#include "image/image.h"
#include "render/render_scene.h"
#include "render/tile.h"

namespace dtraced::render {

struct LocalOptions {
  std::uint32_t threads = 0;     // 0: every hardware thread
  std::uint32_t tile_size = 32;  // pixels per tile side, >= 1
  bool packets = true;           // TileOptions::packets: same image either way
  bool specialise = true;        // TileOptions::specialise: same image either way
  bool want_variance = false;    // fill LocalResult::variance (TileOptions::want_variance)
  // Called now and then, and once at the end, with (tiles done, tiles total).
  std::function<void(std::size_t, std::size_t)> progress;
};

struct LocalResult {
  image::ImageRGBf image;
  // Samples each pixel took (width * height, row-major) with adaptive sampling; empty otherwise.
  std::vector<std::uint32_t> spp;
  // With LocalOptions::want_variance: each pixel's estimated variance of its mean (s^2 / n per
  // channel); an empty image otherwise.
  image::ImageRGBf variance;
  TraceStats stats;
  double seconds = 0.0;  // wall time of rendering (scene build excluded)
  std::uint32_t threads = 0;
};

LocalResult render_local(const RenderScene& scene, const scene::RenderSettings& settings, const LocalOptions& options);

}  // namespace dtraced::render
