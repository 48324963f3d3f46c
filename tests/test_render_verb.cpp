// The render verb in-process: --crop renders the same bits as the full image's pixels there, and
// the display transform changes 8-bit outputs only (PFM stays linear).
#include <filesystem>
#include <string>

#include <catch2/catch.hpp>

#include "cli/verbs.h"
#include "image/image_io.h"
#include "temp_dir.h"
#include "util/file.h"

namespace {

namespace cli = dtraced::cli;
namespace image = dtraced::image;

cli::RenderArgs small_render(const std::string& output) {
  cli::RenderArgs a;
  a.scene = std::string(DTRACED_SOURCE_DIR) + "/scenes/soft_shadows.json";
  a.output = output;
  a.overrides.width = 40;
  a.overrides.height = 30;
  a.overrides.samples = 2;
  a.overrides.tile_size = 8;
  a.quiet = true;
  return a;
}

std::string bytes_of(const std::string& path) {
  auto r = dtraced::util::read_file_limited(path, 1 << 24);
  REQUIRE(r.ok());
  return *r;
}

}  // namespace

TEST_CASE("A cropped render has the full render's bits in the crop") {
  const dtraced::testing::TempDir dir;
  const std::string full = dir.str() + "/full.pfm", crop = dir.str() + "/crop.pfm";
  REQUIRE(cli::run_render(small_render(full)) == 0);
  cli::RenderArgs c = small_render(crop);
  c.overrides.crop = dtraced::scene::TileRect{5, 3, 12, 17};  // crosses tile borders on every side
  REQUIRE(cli::run_render(c) == 0);
  const auto a = image::read_image(full);
  const auto b = image::read_image(crop);
  REQUIRE(a.ok());
  REQUIRE(b.ok());
  REQUIRE(b->width == 12);
  REQUIRE(b->height == 17);
  bool any_lit = false;
  for (std::uint32_t y = 0; y < b->height; ++y) {
    for (std::uint32_t x = 0; x < b->width; ++x) {
      for (int ch = 0; ch < 3; ++ch) {
        const float want = a->rgb[((std::size_t{y} + 3) * a->width + x + 5) * 3 + ch];
        const float got = b->rgb[(std::size_t{y} * b->width + x) * 3 + ch];
        REQUIRE(got == want);
        any_lit = any_lit || got > 0;
      }
    }
  }
  CHECK(any_lit);
}

TEST_CASE("A crop outside the image is a usage error and writes nothing") {
  const dtraced::testing::TempDir dir;
  cli::RenderArgs c = small_render(dir.str() + "/crop.pfm");
  c.overrides.crop = dtraced::scene::TileRect{30, 0, 11, 5};  // x1 = 41 > 40
  CHECK(cli::run_render(c) == 2);
  CHECK_FALSE(std::filesystem::exists(c.output));
}

TEST_CASE("Exposure and tone change an 8-bit output and leave a PFM's linear pixels alone") {
  const dtraced::testing::TempDir dir;
  const std::string png0 = dir.str() + "/e0.png", png1 = dir.str() + "/e1.png";
  const std::string pfm0 = dir.str() + "/e0.pfm", pfm1 = dir.str() + "/e1.pfm";
  REQUIRE(cli::run_render(small_render(png0)) == 0);
  REQUIRE(cli::run_render(small_render(pfm0)) == 0);
  for (const std::string* out : {&png1, &pfm1}) {
    cli::RenderArgs a = small_render(*out);
    a.overrides.exposure = -1.5;
    a.overrides.tone = image::ToneCurve::kFilmic;
    REQUIRE(cli::run_render(a) == 0);
  }
  CHECK(bytes_of(png0) != bytes_of(png1));
  CHECK(bytes_of(pfm0) == bytes_of(pfm1));
}

TEST_CASE("A float EXR holds the same linear pixels as the PFM of the same render") {
  const dtraced::testing::TempDir dir;
  const std::string pfm = dir.str() + "/r.pfm", exr = dir.str() + "/r.exr";
  REQUIRE(cli::run_render(small_render(pfm)) == 0);
  cli::RenderArgs a = small_render(exr);
  a.exr_float = true;
  REQUIRE(cli::run_render(a) == 0);
  const auto p = image::read_image(pfm);
  const auto e = image::read_image(exr);
  REQUIRE(p.ok());
  REQUIRE(e.ok());
  CHECK(p->width == e->width);
  CHECK(p->rgb == e->rgb);
}

TEST_CASE("An adaptive render in its default tiles has the bits and counts of 8-px tiles") {
  // An adaptive render that names no tile size gets larger tiles than a uniform one (fewer
  // first-checkpoint border rays); that may change only the time. 150x70 spans several of them.
  const dtraced::testing::TempDir dir;
  cli::RenderArgs a = small_render(dir.str() + "/default.pfm");
  a.overrides.width = 150;
  a.overrides.height = 70;
  a.overrides.samples = 16;
  a.overrides.min_samples = 1;
  a.overrides.error_target = 0.05;
  a.overrides.tile_size.reset();
  a.spp_map = dir.str() + "/default-spp.pfm";
  cli::RenderArgs b = a;
  b.output = dir.str() + "/small.pfm";
  b.spp_map = dir.str() + "/small-spp.pfm";
  b.overrides.tile_size = 8;
  REQUIRE(cli::run_render(a) == 0);
  REQUIRE(cli::run_render(b) == 0);
  const auto spp = image::read_image(a.spp_map);
  REQUIRE(spp.ok());
  bool refined = false, stopped = false;
  for (const float n : spp->rgb) refined = refined || n > 1, stopped = stopped || n == 1;
  CHECK(refined);  // both outcomes of the first checkpoint occur, so the test sees its border
  CHECK(stopped);
  CHECK(bytes_of(a.output) == bytes_of(b.output));
  CHECK(bytes_of(a.spp_map) == bytes_of(b.spp_map));
}
