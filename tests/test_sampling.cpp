// Fewer rays and fewer samples (issue 16): one mirror ray per hit, the settable branch cut-off,
// and the stratified per-pixel sample sequence.
#include <bit>
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "render/integrator.h"
#include "render/render_scene.h"
#include "render/sampler.h"
#include "render/shading.h"
#include "render/tile.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "scene_builders.h"

using namespace dtraced;
using math::Vec3d;
using math::Vec3f;

namespace {

// Whether the points form a (0,m,2)-net in base 2 (n = 2^m points): every box of
// 2^-a by 2^-(m-a) holds exactly one point, for each a in [0, m].
bool is_net(const std::vector<render::Sample2>& pts) {
  int m = 0;
  while ((std::size_t(1) << m) < pts.size()) ++m;
  if ((std::size_t(1) << m) != pts.size()) return false;
  for (int a = 0; a <= m; ++a) {
    std::set<std::uint64_t> boxes;
    for (const render::Sample2& p : pts) {
      const std::uint64_t bx = std::uint64_t(double(p.u) * double(1u << a));
      const std::uint64_t by = std::uint64_t(double(p.v) * double(1u << (m - a)));
      if (!boxes.insert(bx << 32 | by).second) return false;
    }
  }
  return true;
}

std::vector<render::Sample2> points(const math::SampleKey& key, std::uint32_t dim, std::uint32_t first,
                                    std::uint32_t count) {
  std::vector<render::Sample2> out;
  for (std::uint32_t i = first; i < first + count; ++i) out.push_back(render::stratified_2d(key, dim, i));
  return out;
}

// A sphere straight ahead of a 1x1 camera, whose one ray goes through the pixel centre.
scene::SceneDesc sphere_ahead(const scene::Material& m) {
  scene::SceneDesc d;
  d.camera.position = {0, 0, 5};
  d.camera.look_at = {0, 0, 0};
  d.camera.fov_deg = 30;
  d.objects.push_back(testing::sphere({0, 0, 0}, 1.0, m));
  d.render.width = 1;
  d.render.height = 1;
  d.render.samples = 1;
  d.render.max_depth = 1;
  d.render.background = {0.5, 0.75, 1.0};
  return d;
}

}  // namespace

TEST_CASE("Every aligned run of 2^k points of a pixel is a (0,k,2)-net", "[sampling]") {
  for (const math::SampleKey& key : {math::SampleKey{0, 0, 0, 0, 0}, math::SampleKey{7, 3, 101, 57, 0},
                                     math::SampleKey{1ull << 40, 9, 4000, 3000, 0}}) {
    for (const std::uint32_t dim : {0u, 2u, 10u}) {
      INFO("seed " << key.seed << " pixel " << key.x << "," << key.y << " dim " << dim);
      CHECK(is_net(points(key, dim, 0, 16)));
      CHECK(is_net(points(key, dim, 0, 64)));
      CHECK(is_net(points(key, dim, 0, 1024)));
      CHECK(is_net(points(key, dim, 64, 64)));  // a later run, as an area light's block of samples
      CHECK(is_net(points(key, dim, 96, 32)));
      // An unaligned run is not guaranteed to be a net; the aligned ones above are.
    }
  }
}

TEST_CASE("Stratified samples are a pure function of (seed, frame, pixel, dimension, index)", "[sampling]") {
  const math::SampleKey key{5, 2, 10, 20, 0};
  const render::Sample2 a = render::stratified_2d(key, 0, 3);
  math::SampleKey other_sample = key;
  other_sample.sample = 12345;  // the caller's index says which point; key.sample is not read
  const render::Sample2 b = render::stratified_2d(other_sample, 0, 3);
  CHECK(a.u == b.u);
  CHECK(a.v == b.v);
  // Another pixel, seed, frame or dimension pair scrambles differently.
  std::set<std::pair<float, float>> seen{{a.u, a.v}};
  for (const math::SampleKey& k : {math::SampleKey{5, 2, 11, 20, 0}, math::SampleKey{5, 2, 10, 21, 0},
                                   math::SampleKey{6, 2, 10, 20, 0}, math::SampleKey{5, 3, 10, 20, 0}}) {
    const render::Sample2 c = render::stratified_2d(k, 0, 3);
    CHECK(seen.insert({c.u, c.v}).second);
  }
  const render::Sample2 d = render::stratified_2d(key, 2, 3);
  CHECK(seen.insert({d.u, d.v}).second);
  // In [0, 1) and multiples of 2^-24.
  for (std::uint32_t i = 0; i < 4096; ++i) {
    const render::Sample2 s = render::stratified_2d(key, 4, i);
    REQUIRE(s.u >= 0.0f);
    REQUIRE(s.u < 1.0f);
    REQUIRE(s.v >= 0.0f);
    REQUIRE(s.v < 1.0f);
    REQUIRE(float(std::uint32_t(s.u * 0x1p24f)) == s.u * 0x1p24f);
  }
}

TEST_CASE("Stratified samples keep their bits: the sequence's values before the closed forms", "[sampling]") {
  // A hash of stratified_2d's values over several keys, dimensions and indices, recorded from the
  // implementation that walked Sobol's direction numbers bit by bit and hashed the pixel at every
  // sample: the image bits of every render with more than one sample depend on these values.
  std::uint64_t h = 0;
  for (std::uint32_t k = 0; k < 64; ++k) {
    const math::SampleKey key{0x1234567ull + k * 977, k % 3, k * 37, k * 11 + 5, 0};
    for (const std::uint32_t dim : {0u, 2u, 7u}) {
      const render::PixelSampler2 pixel(key, dim);
      for (std::uint32_t i = 0; i < 1024; ++i) {
        const std::uint32_t index = i * 16411u % (1u << 24);
        const render::Sample2 s = render::stratified_2d(key, dim, index);
        const render::Sample2 p = pixel.at(index);
        REQUIRE(std::bit_cast<std::uint32_t>(p.u) == std::bit_cast<std::uint32_t>(s.u));
        REQUIRE(std::bit_cast<std::uint32_t>(p.v) == std::bit_cast<std::uint32_t>(s.v));
        h = math::hash_combine(
            h, std::uint64_t(std::bit_cast<std::uint32_t>(s.u)) << 32 | std::bit_cast<std::uint32_t>(s.v));
      }
    }
  }
  CHECK(h == 0x29bcdb374a44226eull);
  // Sobol's dimension 1, against its definition: direction number k is the previous one xor
  // itself shifted right by one (primitive polynomial x + 1), starting from 2^31.
  for (std::uint32_t i = 0; i < (1u << 16); ++i) {
    const std::uint32_t index = i * 0x9e3779b9u ^ i;  // all 32 bits in play
    std::uint32_t want = 0, v = 1u << 31;
    for (int bit = 0; bit < 32; ++bit, v ^= v >> 1) {
      if (index >> bit & 1u) want ^= v;
    }
    std::uint32_t x, y;
    render::sobol2(index, x, y);
    REQUIRE(y == want);
  }
}

TEST_CASE("owen_scramble is a bijection that keeps aligned runs together", "[sampling]") {
  // The top 8 bits of the result depend on the top 8 bits of the value only, and permute them.
  std::set<std::uint32_t> seen;
  for (std::uint32_t i = 0; i < 256; ++i) {
    const std::uint32_t v = render::owen_scramble(i << 24, 42);
    CHECK(render::owen_scramble((i << 24) | (i * 0x10101u), 42) >> 24 == v >> 24);
    seen.insert(v >> 24);
  }
  CHECK(seen.size() == 256);
  // Not the identity, and another seed scrambles differently.
  std::uint32_t moved = 0, differs = 0;
  for (std::uint32_t i = 0; i < 256; ++i) {
    moved += render::owen_scramble(i << 24, 42) >> 24 != i;
    differs += render::owen_scramble(i << 24, 42) != render::owen_scramble(i << 24, 43);
  }
  CHECK(moved > 128);
  CHECK(differs > 128);
  // The values [0, 16) land in one aligned run of 16.
  std::set<std::uint32_t> runs;
  for (std::uint32_t i = 0; i < 16; ++i) runs.insert(render::owen_scramble(i, 99) >> 4);
  CHECK(runs.size() == 1);
  // Sobol's dimensions 0 and 1 of the first points.
  std::uint32_t x, y;
  render::sobol2(1, x, y);
  CHECK(x == 1u << 31);
  CHECK(y == 1u << 31);
  render::sobol2(2, x, y);
  CHECK(x == 1u << 30);
  CHECK(y == 3u << 30);
  render::sobol2(3, x, y);
  CHECK(x == 3u << 30);
  CHECK(y == 1u << 30);
}

TEST_CASE("Glass that also reflects casts one mirror ray, with the weight of both lobes", "[sampling][rays]") {
  scene::Material m = testing::glass(1.5, 0.9);
  m.reflectivity = 0.06;
  m.color = {1.0, 0.5, 0.25};
  scene::SceneDesc d = sphere_ahead(m);
  d.render.background = {1, 1, 1};
  const render::RenderScene rs = render::RenderScene::build(d);
  const math::Ray ray = rs.camera().generate(0.5, 0.5, 1, 1);
  accel::Hit hit;
  REQUIRE(rs.geometry().intersect(ray, hit));
  const Vec3f wo = -ray.d;
  const Vec3f nf = math::dot(wo, hit.n) >= 0.0f ? hit.n : -hit.n;
  const render::Interface it = render::dielectric_interface(wo, nf, 1.5f);
  REQUIRE(it.refracts);
  const render::MaterialF& mf = rs.material(hit.shape);

  // max_depth 1: the mirror ray sees the background behind the camera, the refracted one ends on
  // the sphere's far side with nothing to show. Before issue 16 the `reflectivity` mirror and the
  // Fresnel reflection were traced as two identical rays: 4 rays; now 3.
  const render::TraceLimits limits{Vec3f(d.render.background), 1};
  for (const bool packet : {false, true}) {
    render::TraceStats stats;
    Vec3f got;
    if (packet) {
      const math::Ray rays[accel::kPacketSize] = {ray};
      const math::SampleKey keys[accel::kPacketSize] = {};
      Vec3f out[accel::kPacketSize];
      render::trace_radiance8(rs, rays, keys, 1u, limits, stats, out);
      got = out[0];
    } else {
      got = render::trace_radiance(rs, ray, math::SampleKey{}, limits, stats);
    }
    INFO("packet " << packet);
    CHECK(stats.rays == 3);
    // The same sum as two rays gave: the tinted mirror plus the untinted Fresnel reflection.
    const Vec3f bg(d.render.background);
    const Vec3f want = math::mul(mf.color, bg) * mf.reflectivity + bg * (mf.transparency * it.fresnel);
    CHECK(got == want);
    CHECK(got[0] > got[2]);  // the tint reaches only the reflectivity part
  }
}

TEST_CASE("The branch cut-off setting decides which branches are traced", "[sampling][rays]") {
  scene::SceneDesc d = sphere_ahead(testing::glass(1.5));
  d.render.background = {1, 1, 1};
  const render::RenderScene rs = render::RenderScene::build(d);
  const scene::TileRect all{0, 0, 1, 1};

  // Head-on, F = 0.04: the Fresnel reflection weighs 0.04, the refracted branch 0.96.
  d.render.branch_cutoff = 1e-6;
  const render::Tile fine = render::render_tile(rs, d.render, all);
  CHECK(fine.stats.rays == 3);
  CHECK(fine.rgb[0] == Approx(0.04).epsilon(0.01));

  d.render.branch_cutoff = 0.05;  // above the reflection's weight: not traced, its light lost
  const render::Tile coarse = render::render_tile(rs, d.render, all);
  CHECK(coarse.stats.rays == 2);
  CHECK(coarse.rgb[0] == 0.0f);
  // What is lost is at most the cut-off times the radiance along the branch (here 1).
  CHECK(fine.rgb[0] - coarse.rgb[0] <= 0.05f);
}

TEST_CASE("branch_cutoff reads from the render block, is checked, and is canonical only when set", "[sampling]") {
  const auto scene_with = [](const std::string& extra) {
    return R"({"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "fov": 40},
               "render": {"width": 4, "height": 4, "samples": 1, "max_depth": 2, "background": [0, 0, 0],
                          "seed": 1)" +
           extra + R"(},
               "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1}], "scene_lights": []})";
  };
  const scene::LoadResult plain = scene::load_scene_string(scene_with(""), "s.json");
  INFO(scene::format_errors(plain.errors));
  REQUIRE(plain.ok());
  CHECK(plain.scene->render.branch_cutoff == 1e-6);
  CHECK(scene::canonical_json(*plain.scene).find("branch_cutoff") == std::string::npos);

  const scene::LoadResult set =
      scene::load_scene_string(scene_with(R"(, "branch_cutoff": 0.00392156862745098)"), "s.json");
  REQUIRE(set.ok());
  CHECK(set.scene->render.branch_cutoff == 0.00392156862745098);
  const std::string canonical = scene::canonical_json(*set.scene);
  CHECK(canonical.find("branch_cutoff") != std::string::npos);
  const scene::LoadResult again = scene::load_scene_string(canonical, "c.json");
  REQUIRE(again.ok());
  CHECK(again.scene->render == set.scene->render);
  CHECK(scene::scene_digest(*again.scene) != scene::scene_digest(*plain.scene));

  for (const char* bad : {R"(, "branch_cutoff": 0.9)", R"(, "branch_cutoff": 0)", R"(, "branch_cutoff": "x")"}) {
    const scene::LoadResult r = scene::load_scene_string(scene_with(bad), "s.json");
    INFO(bad << "\n" << scene::format_errors(r.errors));
    CHECK_FALSE(r.ok());
    CHECK(scene::format_errors(r.errors).find("/render/branch_cutoff") != std::string::npos);
  }
}
