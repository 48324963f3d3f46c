// dtraced::render local rendering: a whole image on this machine's cores.
//
// Tiles are handed to a fixed set of threads through one atomic counter; each tile writes a
// disjoint region of the image, so the result is bitwise identical for any tile size and thread
// count. The progress callback runs on the calling thread only. A render can be stopped between
// tiles (LocalOptions::stop_requested) and resumed by skipping the tiles it finished: each tile is
// a pure function of its rectangle, so the pieces put together are the same bits.
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
  // Called now and then, and once at the end, with (tiles done, tiles total); skipped tiles
  // count as done.
  std::function<void(std::size_t, std::size_t)> progress;
  // Cancellation, asked on the render threads before each tile starts: once it answers true, no
  // tile starts, the tiles being rendered finish (and reach tile_done), and the result is
  // incomplete. Must be thread-safe (an atomic flag's load).
  std::function<bool()> stop_requested;
  // Called with every tile rendered and its index in scene::TileGrid order, on the thread that
  // called render_local, one call at a time, in the order the tiles were finished; every tile
  // rendered has been through it when render_local returns: e.g. to append it to a file that a
  // later render resumes from. The render threads go on meanwhile. The calling thread takes the
  // finished tiles in batches, once 8 have finished, a render thread returns, or 20 ms have passed
  // (local_render.cpp), so a tile reaches it promptly but not at once.
  std::function<void(std::size_t, const Tile&)> tile_done;
  // Tiles not to render (by index in scene::TileGrid order; size = the tile count, or empty for
  // none): a resumed render has their pixels already. Their pixels (and spp) are left zero.
  std::vector<bool> skip;
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
  std::size_t tiles_rendered = 0;  // by this call (skipped tiles excluded)
  bool complete = true;            // false when stop_requested ended the render early
};

// Copies a tile's pixels (and its spp counts and variance, where both the tile and the result
// have them) into their place in `result`, an image `image_width` pixels wide. Tiles are
// disjoint, so threads may paste different tiles at once.
void paste_tile(const Tile& tile, std::uint32_t image_width, LocalResult& result);

LocalResult render_local(const RenderScene& scene, const scene::RenderSettings& settings, const LocalOptions& options);

}  // namespace dtraced::render
