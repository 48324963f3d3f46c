// dtraced::scene tiling: the tile grid that the renderer, the wire and the collector share, and
// the adaptive-sampling checkpoint rule.
#include <cstdint>
#include <tuple>
#include <vector>

#include <catch2/catch.hpp>

#include "scene/tiling.h"

using dtraced::scene::RenderSettings;
using dtraced::scene::TileGrid;
using dtraced::scene::TileRect;

TEST_CASE("Tiles cover every pixel exactly once", "[tiling]") {
  for (std::uint32_t ts : {1u, 7u, 16u, 64u, 1000u}) {
    const auto tiles = TileGrid(37, 23, ts).all();
    std::vector<int> hits(37 * 23, 0);
    for (const auto& t : tiles)
      for (std::uint32_t y = t.y0; y < t.y0 + t.height; ++y)
        for (std::uint32_t x = t.x0; x < t.x0 + t.width; ++x) ++hits[y * 37 + x];
    for (int h : hits) REQUIRE(h == 1);
  }
}

TEST_CASE("The grid is row-major, full tiles but at the right and bottom edges", "[tiling]") {
  for (const auto& [w, h, ts] : {std::tuple{32u, 24u, 8u},
                                 {33u, 25u, 8u},
                                 {1u, 1u, 8u},
                                 {640u, 480u, 32u},
                                 {100u, 7u, 64u},
                                 {1000u, 999u, 1024u}}) {
    INFO(w << "x" << h << " in tiles of " << ts);
    const TileGrid grid(w, h, ts);
    CHECK(grid.columns() == (w + ts - 1) / ts);
    CHECK(grid.rows() == (h + ts - 1) / ts);
    REQUIRE(grid.count() == std::uint64_t{grid.columns()} * grid.rows());
    const std::vector<TileRect> all = grid.all();
    REQUIRE(all.size() == grid.count());
    for (std::uint64_t i = 0; i < grid.count(); ++i) {
      const TileRect r = grid.rect(i);
      CHECK(r == all[i]);
      CHECK(r.x0 == (i % grid.columns()) * ts);
      CHECK(r.y0 == (i / grid.columns()) * ts);
      CHECK(r.width == (r.x0 + ts <= w ? ts : w - r.x0));
      CHECK(r.height == (r.y0 + ts <= h ? ts : h - r.y0));
    }
  }
}

TEST_CASE("A grid of the largest image in 1-pixel tiles counts in 64 bits", "[tiling]") {
  const TileGrid grid(16384, 16384, 1);
  CHECK(grid.count() == std::uint64_t{16384} * 16384);
  CHECK(grid.rect(grid.count() - 1) == TileRect{16383, 16383, 1, 1});
}

TEST_CASE("Checkpoints are min_samples * 2^k below samples", "[tiling][adaptive]") {
  RenderSettings s;
  s.samples = 100;
  s.min_samples = 4;
  std::vector<std::uint32_t> checkpoints;
  for (std::uint32_t n = 0; n <= 200; ++n) {
    if (dtraced::scene::is_checkpoint(s, n)) checkpoints.push_back(n);
  }
  CHECK(checkpoints == std::vector<std::uint32_t>{4, 8, 16, 32, 64});

  // Uniform sampling: only settings.samples is a valid count.
  s.error_target = 0;
  CHECK(dtraced::scene::is_valid_sample_count(s, 100));
  CHECK_FALSE(dtraced::scene::is_valid_sample_count(s, 64));
  // Adaptive: the checkpoints too, and nothing else.
  s.error_target = 0.05;
  CHECK(dtraced::scene::is_valid_sample_count(s, 100));
  CHECK(dtraced::scene::is_valid_sample_count(s, 64));
  CHECK(dtraced::scene::is_valid_sample_count(s, 4));
  CHECK_FALSE(dtraced::scene::is_valid_sample_count(s, 12));
  CHECK_FALSE(dtraced::scene::is_valid_sample_count(s, 128));
  CHECK_FALSE(dtraced::scene::is_valid_sample_count(s, 2));
  CHECK_FALSE(dtraced::scene::is_valid_sample_count(s, 0));

  // min_samples == samples: no checkpoint below samples.
  s.min_samples = 100;
  for (std::uint32_t n = 0; n < 100; ++n) CHECK_FALSE(dtraced::scene::is_checkpoint(s, n));
}
