// Rendering helpers the render tests share: a whole image rendered as tiles of any size through
// render_tile (per pixel or in packets, specialised or generic), bitwise comparison of two such
// images, and pixel access. Header-only functions of their arguments: no state.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include <catch2/catch.hpp>

#include "math/vec.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "render/tile.h"

namespace dtraced::testing {

struct Rendered {
  std::vector<float> rgb;  // the whole image, row-major
  render::TraceStats stats;
};

// The whole image of `settings`, rendered as tiles of tw x th pixels (smaller at the right and
// bottom edges) and assembled.
inline Rendered render_tiled(const render::RenderScene& rs, const scene::RenderSettings& settings, std::uint32_t tw,
                             std::uint32_t th, bool packets, bool specialise = true) {
  Rendered out;
  out.rgb.assign(std::size_t(settings.width) * settings.height * 3, -1.0f);
  for (std::uint32_t y0 = 0; y0 < settings.height; y0 += th) {
    for (std::uint32_t x0 = 0; x0 < settings.width; x0 += tw) {
      const render::TileRect rect{x0, y0, std::min(tw, settings.width - x0), std::min(th, settings.height - y0)};
      const render::Tile t = render::render_tile(rs, settings, rect, {.packets = packets, .specialise = specialise});
      for (std::uint32_t row = 0; row < rect.height; ++row) {
        std::memcpy(&out.rgb[(std::size_t(y0 + row) * settings.width + x0) * 3],
                    &t.rgb[std::size_t(row) * rect.width * 3], std::size_t(rect.width) * 3 * sizeof(float));
      }
      out.stats.add(t.stats);
    }
  }
  return out;
}

// The same bits, the same ray count, the same dropped samples.
inline void require_identical(const Rendered& want, const Rendered& got) {
  REQUIRE(want.rgb.size() == got.rgb.size());
  REQUIRE(std::memcmp(want.rgb.data(), got.rgb.data(), want.rgb.size() * sizeof(float)) == 0);
  REQUIRE(want.stats.rays == got.stats.rays);
  REQUIRE(want.stats.nan_samples == got.stats.nan_samples);
  REQUIRE(want.stats.inf_samples == got.stats.inf_samples);
}

inline math::Vec3f pixel(const render::Tile& t, std::uint32_t x, std::uint32_t y) {
  const float* p = &t.rgb[(std::size_t(y) * t.rect.width + x) * 3];
  return {p[0], p[1], p[2]};
}

// render_local's options: `threads` threads (0: all), tiles of `tile_size`, packets or not.
inline render::LocalOptions local_options(std::uint32_t threads, std::uint32_t tile_size, bool packets = true) {
  render::LocalOptions o;
  o.threads = threads;
  o.tile_size = tile_size;
  o.packets = packets;
  return o;
}

}  // namespace dtraced::testing
