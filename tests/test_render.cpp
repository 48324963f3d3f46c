// Closed-form checks of the Whitted integrator, Fresnel edge cases, determinism of the tiled
// renderer, and bitwise equality of the packet and the per-pixel paths on every isa.
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <iterator>
#include <limits>
#include <numbers>
#include <optional>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "math/float_util.h"
#include "render/integrator.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "render/shading.h"
#include "render/tile.h"
#include "render_checks.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "scene_builders.h"

using namespace dtraced;
using math::Vec3d;
using math::Vec3f;
using testing::box;
using testing::diffuse;
using testing::local_options;
using testing::pixel;
using testing::plane;
using testing::render_tiled;
using testing::Rendered;
using testing::require_identical;
using testing::sphere;

namespace {

render::Tile render_all(const scene::SceneDesc& d) {
  const render::RenderScene rs = render::RenderScene::build(d);
  return render::render_tile(rs, d.render, {0, 0, d.render.width, d.render.height});
}

// Exact (double) first hit of a ray with a sphere, for the reference.
std::optional<double> ref_sphere_t(Vec3d o, Vec3d d, Vec3d c, double r, double* disc_rel) {
  d = math::normalize(d);
  const Vec3d f = o - c;
  const double b = math::dot(f, d);
  const Vec3d perp = f - d * b;
  const double disc = r * r - math::dot(perp, perp);
  *disc_rel = disc / (r * r);
  if (disc < 0) return std::nullopt;
  const double t = -b - std::sqrt(disc);
  return t > 0 ? std::optional<double>(t) : std::nullopt;
}

}  // namespace

TEST_CASE("Lambertian sphere under a point light matches the closed form at pixel centres", "[render][closed-form]") {
  scene::SceneDesc d;
  const Vec3d albedo{0.7, 0.5, 0.3};
  d.objects.push_back(sphere({0, 0, 0}, 1.0, diffuse(albedo)));
  const Vec3d light_pos{3, 4, 5};
  const double intensity = 40.0;
  d.lights.push_back({light_pos, {1, 1, 1}, intensity});
  d.camera = {{0, 0, 6}, {0, 0, 0}, {0, 1, 0}, 30.0};
  d.render.width = 64;
  d.render.height = 64;
  d.render.samples = 1;
  const render::Tile tile = render_all(d);
  const render::RenderScene rs = render::RenderScene::build(d);

  int checked = 0;
  double worst = 0;
  for (std::uint32_t y = 0; y < 64; ++y) {
    for (std::uint32_t x = 0; x < 64; ++x) {
      const math::Ray ray = rs.camera().generate(x + 0.5, y + 0.5, 64, 64);
      double disc_rel = 0;
      const auto t = ref_sphere_t(Vec3d(ray.o), Vec3d(ray.d), {0, 0, 0}, 1.0, &disc_rel);
      if (!t || disc_rel < 1e-3) continue;  // silhouette pixels are the hard-case tests' business
      const Vec3d p = Vec3d(ray.o) + math::normalize(Vec3d(ray.d)) * *t;
      const Vec3d n = math::normalize(p);
      const Vec3d to_l = light_pos - p;
      const double r2 = math::dot(to_l, to_l);
      const double cos_l = math::dot(n, to_l) / std::sqrt(r2);
      if (cos_l <= 0.01) continue;
      const Vec3f got = pixel(tile, x, y);
      for (int c = 0; c < 3; ++c) {
        const double want = albedo[c] / std::numbers::pi * intensity * cos_l / r2;
        const double rel = std::abs(got[c] - want) / want;
        worst = std::max(worst, rel);
        REQUIRE(rel < 1e-4);
      }
      ++checked;
    }
  }
  INFO("worst relative error " << worst);
  REQUIRE(checked > 300);
}

TEST_CASE("Lambertian plane under a point light matches the closed form", "[render][closed-form]") {
  scene::SceneDesc d;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.5, 0.5, 0.5})));
  const double h = 2.0, intensity = 10.0;
  d.lights.push_back({{0.3, h, -0.2}, {1, 1, 1}, intensity});
  d.camera = {{0, 3, 4}, {0, 0, 0}, {0, 1, 0}, 50.0};
  d.render.width = 48;
  d.render.height = 48;
  const render::Tile tile = render_all(d);
  const render::RenderScene rs = render::RenderScene::build(d);
  int checked = 0;
  for (std::uint32_t y = 0; y < 48; ++y) {
    for (std::uint32_t x = 0; x < 48; ++x) {
      const math::Ray ray = rs.camera().generate(x + 0.5, y + 0.5, 48, 48);
      const Vec3d o(ray.o), dir = math::normalize(Vec3d(ray.d));
      if (dir.y >= -1e-3) continue;
      const Vec3d p = o + dir * (-o.y / dir.y);
      const Vec3d to_l = Vec3d{0.3, h, -0.2} - p;
      const double r2 = math::dot(to_l, to_l);
      const double want = 0.5 / std::numbers::pi * intensity * (to_l.y / std::sqrt(r2)) / r2;
      const Vec3f got = pixel(tile, x, y);
      REQUIRE(std::abs(got.x - want) / want < 1e-4);
      ++checked;
    }
  }
  REQUIRE(checked > 500);
}

// A point light 1e-20 above a Lambertian plane, straight above the point a camera ray hits: the
// squared distance, 1e-40, is below float's normal range and I cos / d^2 is 1e40 I. Computed in
// float that overflows to Inf, and the black green channel turns Inf * 0 into NaN. The radiance
// must be the closed form albedo / pi * I / h^2 where float can hold it (I = 1e-12: 1.6e27), the
// clamp kMaxLightTerm where it cannot (I = 1: 1.6e39), 0 in the black channel, and the same from
// the packet path and the generic path.
TEST_CASE("A point light almost touching a surface gives finite radiance, the closed form where float holds it",
          "[render][closed-form]") {
  const Vec3d albedo{0.5, 0.0, 0.25};
  for (const double intensity : {1e-12, 1.0}) {
    CAPTURE(intensity);
    scene::SceneDesc d;
    d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse(albedo)));
    d.lights.push_back(testing::point_light({0, 1e-20, 0}, intensity));
    d.camera = {{0, 1, 0}, {0, 0, 0}, {0, 0, 1}, 30.0};  // looking straight down
    d.render.width = 1;
    d.render.height = 1;
    const render::RenderScene rs = render::RenderScene::build(d);
    const math::Ray ray = rs.camera().generate(0.5, 0.5, 1, 1);
    REQUIRE(ray.d == Vec3f{0, -1, 0});  // so the hit is (0, 0, 0) exactly

    const render::TraceLimits limits{Vec3f{0, 0, 0}, 8};
    render::TraceStats stats;
    const Vec3f got = render::trace_radiance(rs, ray, math::SampleKey{}, limits, stats);
    const double h = double(rs.lights()[0].position.y);
    for (int c = 0; c < 3; ++c) {
      const double want = double(float(albedo[c])) / std::numbers::pi * double(rs.lights()[0].intensity[c]) / (h * h);
      INFO("channel " << c << ": got " << got[c] << ", closed form " << want);
      CHECK(std::isfinite(got[c]));
      if (want <= double(render::kMaxLightTerm)) {
        CHECK(std::abs(double(got[c]) - want) <= 1e-6 * want);
      } else {
        CHECK(got[c] == render::kMaxLightTerm);
      }
    }

    render::TraceLimits generic = limits;
    generic.specialise = false;
    CHECK(render::trace_radiance(rs, ray, math::SampleKey{}, generic, stats) == got);
    Vec3f packet[accel::kPacketSize];
    math::Ray rays[accel::kPacketSize] = {ray};
    const math::SampleKey keys[accel::kPacketSize] = {};
    render::trace_radiance8(rs, rays, keys, 1u, limits, stats, packet);
    CHECK(packet[0] == got);
    const render::Tile tile = render_all(d);
    CHECK(tile.stats.nan_samples == 0);
    CHECK(tile.stats.inf_samples == 0);
    CHECK(pixel(tile, 0, 0) == got);
  }
}

TEST_CASE("Fresnel reflectance at normal incidence is ((n-1)/(n+1))^2", "[render][fresnel]") {
  const Vec3f n{0, 0, 1};
  for (double eta : {1.33, 1.5, 2.42, 1.0 / 1.5}) {
    const render::Interface it = render::dielectric_interface(n, n, float(eta));
    const double want = std::pow((eta - 1) / (eta + 1), 2);
    INFO("eta " << eta);
    REQUIRE(std::abs(it.fresnel - want) < 1e-6);
    REQUIRE(it.refracts);
    REQUIRE(std::abs(it.wt.z + 1.0f) < 1e-6);
  }
  REQUIRE(std::abs(render::dielectric_interface(n, n, 1.5f).fresnel - 0.04) < 1e-6);
}

// The integrator takes the Fresnel term first (dielectric_fresnel) and the refracted direction
// only for rays it spawns (refracted_direction): together they must be the one-piece computation
// they were split from, bit for bit, at every angle, both ways through the surface, and under
// total internal reflection. The reference below is that computation, operation for operation.
TEST_CASE("dielectric_fresnel and refracted_direction give dielectric_interface's bits", "[render][fresnel]") {
  const auto reference = [](const Vec3f& wo, const Vec3f& n, float eta) {
    render::Interface out;
    const float cos_i = std::clamp(math::dot(wo, n), 0.0f, 1.0f);
    const float sin2_i = std::max(0.0f, 1.0f - cos_i * cos_i);
    const float sin2_t = sin2_i / (eta * eta);
    if (!(sin2_t < 1.0f)) return out;
    const float cos_t = std::sqrt(1.0f - sin2_t);
    const float r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
    const float r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
    out.fresnel = std::clamp(0.5f * (r_parl * r_parl + r_perp * r_perp), 0.0f, 1.0f);
    out.refracts = true;
    out.wt = math::normalize((-wo) / eta + n * (cos_i / eta - cos_t));
    return out;
  };
  const auto bits = [](float x) {
    std::uint32_t u;
    std::memcpy(&u, &x, sizeof u);
    return u;
  };
  int refracted = 0, reflected = 0;
  for (const float eta : {1.5f, 1.0f / 1.5f, 1.33f, 1.0f / 2.42f, 1.0f}) {
    for (int i = 0; i <= 2000; ++i) {
      const float a = float(i) / 2000.0f * 1.5707f;
      const Vec3f n = math::normalize(Vec3f{0.3f, 0.2f, 0.9f});
      const Vec3f wo = math::normalize(n * std::cos(a) + math::normalize(Vec3f{0.9f, -0.1f, -0.3f}) * std::sin(a));
      const render::Interface want = reference(wo, n, eta);
      const render::Interface got = render::dielectric_interface(wo, n, eta);
      const render::Fresnel f = render::dielectric_fresnel(wo, n, eta);
      INFO("eta " << eta << ", angle " << a);
      REQUIRE(got.refracts == want.refracts);
      REQUIRE(f.refracts == want.refracts);
      REQUIRE(bits(got.fresnel) == bits(want.fresnel));
      REQUIRE(bits(f.fresnel) == bits(want.fresnel));
      if (!want.refracts) {
        ++reflected;
        continue;
      }
      ++refracted;
      const Vec3f wt = render::refracted_direction(wo, n, eta, f);
      for (int k = 0; k < 3; ++k) {
        REQUIRE(bits(got.wt[k]) == bits(want.wt[k]));
        REQUIRE(bits(wt[k]) == bits(want.wt[k]));
      }
    }
  }
  CHECK(refracted > 1000);
  CHECK(reflected > 100);  // total internal reflection from the denser side
}

TEST_CASE("Fresnel and refraction agree about total internal reflection near the critical angle", "[render][fresnel]") {
  const Vec3f n{0, 0, 1};
  for (float eta : {1.0f / 1.33f, 1.0f / 1.5f, 1.0f / 2.42f}) {
    const double critical_cos = std::sqrt(1.0 - double(eta) * eta);
    float c = float(critical_cos);
    for (int i = 0; i < 10000; ++i) c = math::next_float_down(c);
    for (int i = 0; i < 20000; ++i, c = math::next_float_up(c)) {
      const float s = std::sqrt(std::max(0.0f, 1.0f - c * c));
      const Vec3f wo{s, 0, c};
      const render::Interface it = render::dielectric_interface(wo, n, eta);
      REQUIRE(std::isfinite(it.fresnel));
      REQUIRE(it.fresnel >= 0.0f);
      REQUIRE(it.fresnel <= 1.0f);
      REQUIRE((it.fresnel == 1.0f) == !it.refracts);
      if (it.refracts) {
        REQUIRE(std::abs(math::length(it.wt) - 1.0f) < 1e-6f);
        // Snell: eta * sin(theta_t) = sin(theta_i)
        const float sin_t = std::sqrt(it.wt.x * it.wt.x + it.wt.y * it.wt.y);
        REQUIRE(std::abs(eta * sin_t - s) < 1e-6f);
      }
    }
  }
}

TEST_CASE("A glass slab in front of a uniform background transmits (1-R)/(1+R) of it", "[render][closed-form]") {
  scene::SceneDesc d;
  scene::Material glass;
  glass.diffuse = 0;
  glass.transparency = 1;
  glass.ior = 1.5;
  d.objects.push_back(box({-5, -5, -0.5}, {5, 5, 0.5}, glass));
  // A black plane behind the camera swallows everything the slab reflects back.
  scene::Material black = diffuse({0, 0, 0});
  d.objects.push_back(plane({0, 0, 20}, {0, 0, -1}, black));
  d.camera = {{0, 0, 10}, {0, 0, 0}, {0, 1, 0}, 10.0};
  d.render.width = 3;
  d.render.height = 3;
  d.render.max_depth = 32;
  d.render.background = {0.2, 0.4, 0.6};
  const render::Tile tile = render_all(d);
  const Vec3f centre = pixel(tile, 1, 1);
  const double t_slab = (1.0 - 0.04) / (1.0 + 0.04);  // 0.923077
  REQUIRE(std::abs(t_slab - 0.92308) < 1e-5);
  for (int c = 0; c < 3; ++c) {
    const double want = t_slab * d.render.background[c];
    INFO("channel " << c << " got " << centre[c] << " want " << want);
    REQUIRE(std::abs(centre[c] - want) / want < 1e-5);
  }
}

TEST_CASE("A mirror reflects a known colour exactly", "[render][closed-form]") {
  scene::SceneDesc d;
  scene::Material mirror;
  mirror.diffuse = 0;
  mirror.reflectivity = 1;
  mirror.color = {0.9, 0.5, 0.25};
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, mirror));
  d.camera = {{0, 2, 4}, {0, 0, 0}, {0, 1, 0}, 20.0};
  d.render.width = 8;
  d.render.height = 8;
  d.render.background = {0.75, 0.5, 1.0};
  const render::Tile tile = render_all(d);
  const Vec3f want = math::mul(Vec3f(mirror.color), Vec3f(d.render.background));
  for (std::uint32_t y = 0; y < 8; ++y)
    for (std::uint32_t x = 0; x < 8; ++x) REQUIRE(pixel(tile, x, y) == want);
}

TEST_CASE("Images are bitwise identical for any tile size and thread count", "[render][determinism]") {
  for (const char* name : {"showcase.json", "snowman.json", "room.json"}) {
    INFO(name);
    scene::LoadResult r = scene::load_scene_file(std::string(DTRACED_SOURCE_DIR) + "/scenes/" + name);
    REQUIRE(r.ok());
    scene::SceneDesc d = *r.scene;
    d.render.width = 96;
    d.render.height = 64;
    d.render.samples = 3;
    const render::RenderScene rs = render::RenderScene::build(d);
    const render::LocalOptions one = local_options(/* threads = */ 1, /* tile_size = */ 16);
    const render::LocalOptions all = local_options(/* threads = */ 0, /* tile_size = */ 64);
    const auto a = render::render_local(rs, d.render, one);
    const auto b = render::render_local(rs, d.render, all);
    REQUIRE(a.image.rgb.size() == b.image.rgb.size());
    REQUIRE(std::memcmp(a.image.rgb.data(), b.image.rgb.data(), a.image.rgb.size() * sizeof(float)) == 0);
    REQUIRE(a.stats.nan_samples == 0);
    REQUIRE(a.stats.inf_samples == 0);
    REQUIRE(a.stats.rays == b.stats.rays);
    // A different seed changes the jittered samples (so the test above could fail).
    scene::RenderSettings other = d.render;
    other.seed += 1;
    const auto c = render::render_local(rs, other, one);
    REQUIRE(std::memcmp(a.image.rgb.data(), c.image.rgb.data(), a.image.rgb.size() * sizeof(float)) != 0);
  }
}

namespace {

// The 16 camera rays of the 4x4 pixel block whose top-left pixel is (bx, by), row by row, each
// through (x + fx, y + fy), and their sample keys: `key` with the pixel's x and y.
void block_rays(const render::CameraF& camera, std::uint32_t width, std::uint32_t height, std::uint32_t bx,
                std::uint32_t by, double fx, double fy, math::SampleKey key, math::Ray* rays, math::SampleKey* keys) {
  for (int i = 0; i < accel::kPacketSize16; ++i) {
    const std::uint32_t x = bx + i % 4, y = by + i / 4;
    rays[i] = camera.generate(x + fx, y + fy, width, height);
    keys[i] = key;
    keys[i].x = x;
    keys[i].y = y;
  }
}

// Renders `d` on every supported isa, per pixel and in packets, in tilings that leave partial 4x2
// and 4x4 blocks at tile edges, and requires every image and every ray count to equal the reference:
// per pixel on the scalar isa in one tile. Returns the reference.
Rendered check_packets_match_per_pixel(const scene::SceneDesc& d) {
  const render::RenderScene reference_scene = render::RenderScene::build(d, accel::Isa::kScalar);
  const std::uint32_t w = d.render.width, h = d.render.height;
  const Rendered reference = render_tiled(reference_scene, d.render, w, h, /* packets = */ false);
  REQUIRE(reference.stats.rays >= std::uint64_t(w) * h * d.render.samples);
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene rs = render::RenderScene::build(d, isa);
    struct Tiling {
      std::uint32_t tw, th;
      bool packets;
    };
    for (const Tiling t : {Tiling{w, h, false}, Tiling{w, h, true}, Tiling{13, 7, true}, Tiling{4, 2, true},
                           Tiling{6, 5, true}, Tiling{5, 3, true}, Tiling{13, 7, false}}) {
      INFO("tiles " << t.tw << "x" << t.th << (t.packets ? " packets" : " per pixel"));
      require_identical(reference, render_tiled(rs, d.render, t.tw, t.th, t.packets));
    }
  }
  return reference;
}

// The same scene with every transparent material made opaque, so that its first-hit shadow rays
// go through the packet path (occluded8) rather than the transmittance walk.
scene::SceneDesc without_transparency(scene::SceneDesc d) {
  for (scene::Object& o : d.objects) o.material.transparency = 0.0;
  return d;
}

}  // namespace

TEST_CASE("Packets render the bundled scenes bitwise like the per-pixel path on every isa", "[render][packets]") {
  for (const char* name : {"showcase.json", "snowman.json", "room.json", "mesh.json", "hard/far_sphere.json",
                           "hard/glass_cube_tir.json", "hard/grazing_light.json", "hard/invisible_ior1.json",
                           "hard/nested_glass.json", "hard/huge_ground.json", "hard/inside_glass.json"}) {
    INFO(name);
    scene::SceneDesc d = testing::load_bundled(name);
    // Small and odd-sized: partial 4x2 and 4x4 blocks at the image's own right and bottom edges too.
    d.render.width = 37;
    d.render.height = 23;
    d.render.samples = 2;
    const Rendered with_glass = check_packets_match_per_pixel(d);
    REQUIRE(with_glass.stats.nan_samples == 0);
    REQUIRE(with_glass.stats.inf_samples == 0);
    check_packets_match_per_pixel(without_transparency(d));
  }
}

// At one sample a pixel the packet path finds its camera rays' screen coordinates once per block
// column and row; the per-pixel path finds them ray by ray. The showcase's ground plane is tested
// beside the shapes (Geometry::outside_planes), huge_ground's huge shape beside the tree.
TEST_CASE("Packets render pixel centres bitwise like the per-pixel path on every isa", "[render][packets]") {
  for (const char* name : {"showcase.json", "hard/huge_ground.json"}) {
    INFO(name);
    scene::SceneDesc d = testing::load_bundled(name);
    d.render.width = 37;
    d.render.height = 23;
    d.render.samples = 1;
    check_packets_match_per_pixel(d);
  }
}

TEST_CASE("Packets render a generated sphere field bitwise like the per-pixel path", "[render][packets]") {
  scene::SceneDesc d = scene::generate_sphere_field(2000, 11);
  d.render.width = 53;
  d.render.height = 30;
  d.render.samples = 1;  // pixel centres
  check_packets_match_per_pixel(d);
  d.render.samples = 3;  // jittered
  d.render.width = 27;
  d.render.height = 15;
  check_packets_match_per_pixel(d);
  check_packets_match_per_pixel(without_transparency(d));
}

// 16-ray packets straight through trace_radiance16: every lane of a 4x4 camera block, under
// masks that leave lanes out (a partial block at a tile edge, converged pixels), must be
// trace_radiance's bits with the same ray count, on a static scene (one intersect16 /
// occluded16 query) and on a frame whose moving objects are a second layer (two 8-ray halves).
TEST_CASE("trace_radiance16 gives every lane trace_radiance's bits, one layer or two", "[render][packets]") {
  scene::SceneDesc d = scene::generate_sphere_field(2000, 11);
  d.render.width = 64;
  d.render.height = 48;
  std::vector<bool> moving(d.objects.size(), false);
  for (std::size_t i = 0; i < moving.size(); i += 3) moving[i] = true;
  for (const bool opaque : {false, true}) {
    const scene::SceneDesc desc = opaque ? without_transparency(d) : d;
    for (const accel::Isa isa : accel::supported_isas()) {
      INFO("isa " << accel::isa_name(isa) << (opaque ? ", opaque" : ", with glass"));
      const render::RenderScene whole = render::RenderScene::build(desc, isa);
      const auto part = render::StaticPart::build(desc, moving, isa);
      const render::RenderScene layered = render::RenderScene::build_frame(desc, *part);
      REQUIRE(whole.geometry().moving() == nullptr);
      REQUIRE(layered.geometry().moving() != nullptr);
      const render::TraceLimits limits{Vec3f{0.1f, 0.2f, 0.3f}, 8};
      int lanes_hit = 0;
      for (const std::uint32_t valid : {0xffffu, 0x0f0fu, 0x7777u, 0x8001u, 0x00ffu, 0xff00u, 0x0001u, 0u}) {
        for (std::uint32_t by = 0; by < d.render.height; by += 4) {
          for (std::uint32_t bx = 0; bx < d.render.width; bx += 4) {
            math::Ray rays[accel::kPacketSize16];
            math::SampleKey keys[accel::kPacketSize16];
            block_rays(whole.camera(), d.render.width, d.render.height, bx, by, 0.25, 0.75,
                       math::SampleKey{7, 0, 0, 0, 1}, rays, keys);
            for (const render::RenderScene* rs : {&whole, &layered}) {
              const Vec3f unset{-1, -1, -1};
              Vec3f out[accel::kPacketSize16];
              std::fill(std::begin(out), std::end(out), unset);
              render::TraceStats packet_stats, single_stats;
              render::trace_radiance16(*rs, rays, keys, valid, limits, packet_stats, out);
              for (int i = 0; i < accel::kPacketSize16; ++i) {
                INFO("block " << bx << "," << by << " lane " << i << " mask " << valid);
                if (valid >> i & 1u) {
                  REQUIRE(out[i] == render::trace_radiance(*rs, rays[i], keys[i], limits, single_stats));
                  if (out[i] != limits.background) ++lanes_hit;
                } else {
                  REQUIRE(out[i] == unset);  // left alone
                }
              }
              REQUIRE(packet_stats.rays == single_stats.rays);
            }
          }
        }
      }
      REQUIRE(lanes_hit > 1000);  // the blocks meet the spheres, not just the background
    }
  }
}

namespace {

// A seed-style Whitted scene (as tests/bench/povray_compare.sh renders it, smaller): a reflective
// floor, mirror spheres, glass that also reflects, diffuse spheres, two point lights. Under 64
// shapes, so packets test every shape directly.
scene::SceneDesc whitted_scene() {
  scene::SceneDesc d;
  scene::Material floor = diffuse({0.6, 0.6, 0.58});
  floor.specular = 0.1;
  floor.shininess = 16;
  floor.reflectivity = 0.1;
  scene::Material chrome = diffuse({0.95, 0.95, 0.95});
  chrome.diffuse = 0.1;
  chrome.specular = 0.9;
  chrome.shininess = 512;
  chrome.reflectivity = 0.85;
  scene::Material glass = diffuse({1, 1, 1});
  glass.diffuse = 0;
  glass.specular = 0.9;
  glass.shininess = 512;
  glass.reflectivity = 0.06;
  glass.transparency = 0.9;
  glass.ior = 1.5;
  scene::Material clear = glass;  // index-matched: the path goes straight through, same depth
  clear.ior = 1.0;
  clear.reflectivity = 0.2;
  clear.transparency = 0.5;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, floor));
  d.objects.push_back(sphere({-2.6, 1.0, -1.0}, 1.0, chrome));
  d.objects.push_back(sphere({0.0, 0.9, 0.4}, 0.9, glass));
  d.objects.push_back(sphere({2.5, 0.8, -1.4}, 0.8, chrome));
  d.objects.push_back(sphere({-0.9, 0.35, 2.1}, 0.35, diffuse({0.85, 0.15, 0.1})));
  d.objects.push_back(sphere({1.3, 0.45, 2.0}, 0.45, glass));
  d.objects.push_back(sphere({0.2, 0.3, 0.5}, 0.2, glass));  // inside the big glass sphere
  d.objects.push_back(sphere({-1.6, 0.4, 1.2}, 0.4, clear));
  d.objects.push_back(sphere({0.9, 0.6, -3.0}, 0.6, diffuse({0.9, 0.5, 0.1})));
  d.lights.push_back({{-4, 6, 5}, {1, 0.95, 0.88}, 320});
  d.lights.push_back({{5, 4, 2}, {0.8, 0.88, 1}, 120});
  d.camera = {{0, 2.4, 8.0}, {0, 0.7, 0}, {0, 1, 0}, 42.0};
  d.render.background = {0.08, 0.09, 0.12};
  d.render.max_depth = 5;
  return d;
}

// The secondary rays the 16- and 8-ray packets traced (TraceStats::secondary_packet_rays) and the
// rays in all.
struct LaneCounts {
  std::uint64_t secondary16 = 0, secondary8 = 0, rays = 0;
};

// Every 4x4 block of d's image through trace_radiance16 and as two halves through
// trace_radiance8: each lane must be trace_radiance's bits with the same ray count.
LaneCounts check_lanes_match(const render::RenderScene& rs, const scene::SceneDesc& d, std::uint32_t valid) {
  const render::TraceLimits limits{Vec3f(d.render.background), d.render.max_depth};
  LaneCounts counts;
  for (std::uint32_t by = 0; by < d.render.height; by += 4) {
    for (std::uint32_t bx = 0; bx < d.render.width; bx += 4) {
      math::Ray cam[accel::kPacketSize16];
      math::SampleKey keys[accel::kPacketSize16];
      block_rays(rs.camera(), d.render.width, d.render.height, bx, by, 0.5, 0.5,
                 math::SampleKey{d.render.seed, 0, 0, 0, 0}, cam, keys);
      Vec3f out16[accel::kPacketSize16], out8[accel::kPacketSize16];
      render::TraceStats stats16, stats8, single;
      render::trace_radiance16(rs, cam, keys, valid, limits, stats16, out16);
      render::trace_radiance8(rs, cam, keys, valid & 0xffu, limits, stats8, out8);
      render::trace_radiance8(rs, cam + 8, keys + 8, valid >> 8, limits, stats8, out8 + 8);
      for (int i = 0; i < accel::kPacketSize16; ++i) {
        if (!(valid >> i & 1u)) continue;
        INFO("block " << bx << "," << by << " lane " << i << " mask " << valid);
        const Vec3f want = render::trace_radiance(rs, cam[i], keys[i], limits, single);
        REQUIRE(std::memcmp(&out16[i], &want, sizeof want) == 0);
        REQUIRE(std::memcmp(&out8[i], &want, sizeof want) == 0);
      }
      REQUIRE(stats16.rays == single.rays);
      REQUIRE(stats8.rays == single.rays);
      REQUIRE(single.secondary_packet_rays == 0);
      counts.secondary16 += stats16.secondary_packet_rays;
      counts.secondary8 += stats8.secondary_packet_rays;
      counts.rays += stats16.rays;
    }
  }
  return counts;
}

}  // namespace

// The packet path traces mirror and refracted rays (and their shadow rays) ahead of each lane's
// tracer as packets where the scene has no tree, and on the 16-ray path where it has one: what it
// hands the lanes must be exactly what they would have found, on every isa, with an area light
// that mirrors show (its samples draw random numbers along the path) and without, and in a sphere
// field with a tree, with and without an area light, whose glass and mirror floor cast them at
// every depth (on a SIMD isa its 8-ray path leaves them to the lanes; on the scalar isa, whose
// packets test every shape, it does not).
TEST_CASE("Mirror and refracted rays as packets give every lane the per-ray bits on every isa", "[render][packets]") {
  scene::SceneDesc small = whitted_scene();
  small.render.width = 48;
  small.render.height = 28;
  scene::SceneDesc lit = small;
  lit.lights.push_back(testing::sphere_light({1.5, 3.0, 1.0}, 0.4, 20.0));
  lit.lights.back().samples = 2;
  scene::SceneDesc field = scene::generate_sphere_field(2000, 11);
  for (scene::Object& o : field.objects) {
    if (o.type == scene::ObjectType::kPlane) o.material.reflectivity = 0.3;  // mirror rays from every block
  }
  field.render.width = 48;
  field.render.height = 28;
  field.render.max_depth = 5;
  scene::SceneDesc field_lit = field;
  field_lit.lights.push_back(testing::sphere_light({0.0, 6.0, 2.0}, 0.5, 40.0));
  field_lit.lights.back().samples = 2;
  for (const accel::Isa isa : accel::supported_isas()) {
    for (const auto& [name, d] : {std::pair<const char*, const scene::SceneDesc&>{"whitted", small},
                                  {"whitted with an area light", lit},
                                  {"sphere field", field},
                                  {"sphere field with an area light", field_lit}}) {
      INFO("isa " << accel::isa_name(isa) << ", " << name);
      const render::RenderScene rs = render::RenderScene::build(d, isa);
      REQUIRE(rs.features().reflection);
      REQUIRE(rs.features().refraction);
      std::uint64_t secondary = 0, secondary8 = 0, rays = 0;
      for (const std::uint32_t valid : {0xffffu, 0x7777u, 0x8001u, 0x0f0fu}) {
        const LaneCounts c = check_lanes_match(rs, d, valid);
        secondary += c.secondary16;
        secondary8 += c.secondary8;
        rays += c.rays;
      }
      // The secondary rays did go as packets (a scalar isa's packets are per-ray loops, but the
      // path is the same): many of them without a tree, some with one; with a tree, not on the
      // 8-ray path.
      if (d.objects.size() < 64) REQUIRE(secondary * 10 > rays);
      REQUIRE(secondary * 100 > rays);
      if (d.objects.size() >= 64 && isa != accel::Isa::kScalar) REQUIRE(secondary8 == 0);
    }
  }
  // The tiled renderer, 4x2 and 4x4 blocks, partial blocks at the edges, several samples.
  small.render.width = 37;
  small.render.height = 23;
  small.render.samples = 2;
  check_packets_match_per_pixel(small);
  lit.render.width = 21;
  lit.render.height = 13;
  lit.render.samples = 2;
  check_packets_match_per_pixel(lit);
}

// The packet path walks a packet's shadow rays through transparent surfaces crossing by
// crossing, one packet query per crossing: shells around the light (alternately index-matched
// and bending) make every shadow ray from the floor cross each of them, up to and past the
// walk's bound of 64 crossings (a light behind more counts as blocked).
TEST_CASE("Shadow rays through many transparent shells give every lane the per-ray bits", "[render][packets]") {
  for (const int shells : {3, 40, 70}) {
    scene::SceneDesc d;
    d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.7, 0.7, 0.7})));
    for (int k = 0; k < shells; ++k) {
      scene::Material m = diffuse({1, 1, 1});
      m.diffuse = 0.2;
      m.transparency = 0.99;
      m.ior = k % 2 == 0 ? 1.0 : 1.2;
      d.objects.push_back(sphere({0, 2.5, 0}, 0.3 + 0.02 * k, m));
    }
    d.lights.push_back({{0, 2.5, 0}, {1, 1, 1}, 40});
    d.camera = {{0, 4.0, 7.0}, {0, 0.5, 0}, {0, 1, 0}, 50.0};
    d.render.width = 24;
    d.render.height = 16;
    d.render.max_depth = 3;
    for (const accel::Isa isa : accel::supported_isas()) {
      INFO(shells << " shells, isa " << accel::isa_name(isa));
      const render::RenderScene rs = render::RenderScene::build(d, isa);
      for (const std::uint32_t valid : {0xffffu, 0x5a5au}) check_lanes_match(rs, d, valid);
    }
    // The floor under the light: lit through 3 or 40 shells, dark behind 70.
    const render::RenderScene rs = render::RenderScene::build(d);
    const render::TraceLimits limits{Vec3f(d.render.background), d.render.max_depth};
    render::TraceStats stats;
    math::Ray down;
    down.o = {0.0f, 1.0f, 1.5f};
    down.d = math::normalize(Vec3f{0.0f, -1.0f, 0.0f});
    const Vec3f l = render::trace_radiance(rs, down, math::SampleKey{}, limits, stats);
    if (shells <= 40) {
      REQUIRE(l.x > 0.0f);
    } else {
      REQUIRE(l.x == 0.0f);
    }
  }
}

namespace {

// A static scene of 77 shapes with a compact glass part (a sphere with an index-matched one inside
// it, a box, and a glass that also shades, so shadow rays leave glass too) among opaque spheres on
// a floor, under two point lights and an area light: RenderScene::build splits it into an opaque
// and a transparent layer.
scene::SceneDesc split_scene() {
  scene::SceneDesc d;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.7, 0.7, 0.7})));
  for (int i = 0; i < 9; ++i) {
    for (int k = 0; k < 9; ++k) {
      const double x = -8.0 + 2.0 * i, z = -8.0 + 2.0 * k;
      if (std::abs(x) <= 2.0 && std::abs(z) <= 2.0) continue;
      d.objects.push_back(sphere({x, 0.3 + 0.05 * i, z}, 0.3, diffuse({0.2 + 0.08 * i, 0.5, 0.9 - 0.08 * k})));
    }
  }
  d.objects.push_back(sphere({0, 1.2, 0}, 0.9, testing::glass(1.5, 0.9)));
  d.objects.push_back(sphere({0, 1.2, 0}, 0.4, testing::glass(1.5, 0.95)));  // index-matched inside the first
  d.objects.push_back(box({1.2, 0.1, -0.6}, {2.0, 0.9, 0.2}, testing::glass(1.3, 0.8)));
  scene::Material tinted = testing::glass(1.2, 0.7);
  tinted.diffuse = 0.3;
  tinted.color = {0.9, 0.6, 0.4};
  d.objects.push_back(sphere({-1.3, 0.5, 0.9}, 0.35, tinted));
  d.lights.push_back(testing::point_light({-3, 6, 2}, 60));
  d.lights.push_back(testing::point_light({4, 5, -3}, 40));
  scene::Light area = testing::rect_light_down({0.5, 6.5, 0.5}, 1.0, 1.0, 6.0);
  area.samples = 2;
  d.lights.push_back(area);
  d.camera = {{0, 4.5, 9}, {0, 0.8, 0}, {0, 1, 0}, 45.0};
  d.render.width = 48;
  d.render.height = 32;
  d.render.samples = 2;
  d.render.max_depth = 5;
  d.render.background = {0.1, 0.12, 0.15};
  return d;
}

}  // namespace

// A static scene with glass among more than 64 shapes is split by transparency: its shadow rays ask
// the opaque layer for any hit, then walk the transparent layer. Packets and per pixel must give
// the same bits and ray counts on every isa, 16- and 8-ray packets each lane's, and the image must
// be the bits of the walk over every shape (the same scene as a frame with a fixed and a moving
// layer, which walks both), no tie of an opaque and a transparent surface being in it.
TEST_CASE("A static scene split by transparency renders the walk's bits, packets and per pixel", "[render][packets]") {
  const scene::SceneDesc d = split_scene();
  const Rendered reference = check_packets_match_per_pixel(d);
  REQUIRE(reference.stats.opaque_first_rays > 0);
  std::vector<bool> moving(d.objects.size(), false);
  moving[1] = true;  // an opaque sphere: the frame has a fixed and a moving layer
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene rs = render::RenderScene::build(d, isa);
    REQUIRE(rs.geometry().transparent() != nullptr);
    REQUIRE(rs.geometry().transparent()->geometry.shapes().size() == 4);
    REQUIRE(rs.geometry().shape_count() == d.objects.size());
    for (const std::uint32_t valid : {0xffffu, 0x5a5au}) check_lanes_match(rs, d, valid);
    const Rendered packets = render_tiled(rs, d.render, 16, 16, true);
    const Rendered single = render_tiled(rs, d.render, 16, 16, false);
    CHECK(packets.stats.opaque_first_rays == single.stats.opaque_first_rays);
    CHECK(packets.stats.opaque_first_rays == reference.stats.opaque_first_rays);

    const auto part = render::StaticPart::build(d, moving, isa);
    const render::RenderScene frame = render::RenderScene::build_frame(d, *part);
    REQUIRE(frame.geometry().transparent() == nullptr);
    const Rendered walk = render_tiled(frame, d.render, 16, 16, true);
    REQUIRE(walk.rgb.size() == packets.rgb.size());
    REQUIRE(std::memcmp(walk.rgb.data(), packets.rgb.data(), walk.rgb.size() * sizeof(float)) == 0);
    CHECK(walk.stats.opaque_first_rays == 0);
    // A blocked shadow ray is one ray however many glass surfaces lie before its blocker.
    CHECK(packets.stats.rays <= walk.stats.rays);
  }
  // The glass shows: without it the image is another.
  const render::RenderScene opaque = render::RenderScene::build(without_transparency(d));
  CHECK(opaque.geometry().transparent() == nullptr);
  CHECK(render_tiled(opaque, d.render, 16, 16, true).rgb != reference.rgb);
}

// Where a glass surface and an opaque one cross a shadow ray at exactly the same t, the glass with
// the smaller id, the split
// scene's shadow rays are blocked: the opaque layer's any-hit query sees the opaque surface. The
// walk over every shape (an animation frame's) crosses the glass first (the smaller id) and
// starts its next segment just past that t, so it passes the opaque surface and lets light
// through. Here a glass slab's top face lies in an opaque plane above a floor that the camera looks
// straight down at: every floor point is under the plane, so it gets no direct light, with the
// slab or without it. Pixel version 5 is this difference (protocol::kPixelVersion).
TEST_CASE("A split scene's shadow rays are blocked by an opaque surface level with a glass one", "[render][packets]") {
  scene::SceneDesc d;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.7, 0.7, 0.7})));
  d.objects.push_back(box({-1, 1, -1}, {1, 1.25, 1}, testing::glass(1.0, 0.9)));
  d.objects.push_back(plane({0, 1.25, 0}, {0, 1, 0}, diffuse({0.7, 0.7, 0.7})));
  for (int i = 0; i < 9; ++i) {
    for (int k = 0; k < 9; ++k)
      d.objects.push_back(sphere({-40.0 + 10 * i, 0.2, -40.0 + 10 * k}, 0.2, diffuse({0.5, 0.5, 0.5})));
  }
  d.lights.push_back(testing::point_light({0.3, 5, 0.2}, 20));
  d.camera = {{0, 0.9, 0}, {0, 0, 0}, {0, 0, 1}, 60.0};
  d.render.width = 32;
  d.render.height = 32;
  d.render.samples = 1;
  d.render.max_depth = 4;
  d.render.background = {0.1, 0.12, 0.15};
  scene::SceneDesc no_slab = d;
  no_slab.objects.erase(no_slab.objects.begin() + 1);
  const Rendered split = check_packets_match_per_pixel(d);
  CHECK(split.stats.opaque_first_rays > 0);
  const render::RenderScene dark_scene = render::RenderScene::build(no_slab);
  REQUIRE(dark_scene.geometry().transparent() == nullptr);
  const Rendered dark = render_tiled(dark_scene, d.render, 32, 32, true);
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene rs = render::RenderScene::build(d, isa);
    REQUIRE(rs.geometry().transparent() != nullptr);
    const Rendered got = render_tiled(rs, d.render, 32, 32, true);
    REQUIRE(got.rgb.size() == dark.rgb.size());
    CHECK(std::memcmp(got.rgb.data(), dark.rgb.data(), got.rgb.size() * sizeof(float)) == 0);
    // The walk over every shape passes the plane where the slab's top face meets it: light gets
    // through under the slab (so the tie is in this scene, and the test above could fail).
    std::vector<bool> moving(d.objects.size(), false);
    moving[3] = true;  // a far sphere: the frame has a fixed and a moving layer
    const auto part = render::StaticPart::build(d, moving, isa);
    const render::RenderScene frame = render::RenderScene::build_frame(d, *part);
    REQUIRE(frame.geometry().transparent() == nullptr);
    const Rendered walk = render_tiled(frame, d.render, 32, 32, true);
    REQUIRE(walk.rgb.size() == dark.rgb.size());
    CHECK(std::memcmp(walk.rgb.data(), dark.rgb.data(), walk.rgb.size() * sizeof(float)) != 0);
    // Without the opaque plane, light comes through the slab: the split scene renders the walk's
    // bits, and they are not the dark image's (so the split does not block shadow rays through glass
    // that no opaque surface meets).
    scene::SceneDesc open = d;
    open.objects.erase(open.objects.begin() + 2);
    const render::RenderScene open_split = render::RenderScene::build(open, isa);
    REQUIRE(open_split.geometry().transparent() != nullptr);
    std::vector<bool> open_moving(open.objects.size(), false);
    open_moving[2] = true;
    const auto open_part = render::StaticPart::build(open, open_moving, isa);
    const Rendered lit = render_tiled(open_split, d.render, 32, 32, true);
    const Rendered lit_walk = render_tiled(render::RenderScene::build_frame(open, *open_part), d.render, 32, 32, true);
    REQUIRE(lit.rgb.size() == lit_walk.rgb.size());
    CHECK(std::memcmp(lit.rgb.data(), lit_walk.rgb.data(), lit.rgb.size() * sizeof(float)) == 0);
    CHECK(std::memcmp(lit.rgb.data(), dark.rgb.data(), lit.rgb.size() * sizeof(float)) != 0);
  }
}

TEST_CASE("Packets match per pixel with misses, lights behind and on surfaces, and many lights", "[render][packets]") {
  scene::SceneDesc d;
  scene::Material shiny = diffuse({0.8, 0.6, 0.4});
  shiny.specular = 0.5;
  shiny.shininess = 20;
  scene::Material half_mirror = diffuse({0.3, 0.7, 0.9});
  half_mirror.reflectivity = 0.5;
  scene::Material dark = diffuse({0, 0, 0});  // direct light still computed, adds zero
  scene::Material specular_only;
  specular_only.diffuse = 0;
  specular_only.specular = 1;
  d.objects.push_back(sphere({-0.8, 0, 0}, 0.7, shiny));
  d.objects.push_back(sphere({0.8, 0.2, -0.5}, 0.6, half_mirror));
  d.objects.push_back(box({-0.3, -1, 0.6}, {0.3, -0.4, 1.0}, specular_only));
  d.objects.push_back(sphere({0.2, 0.9, 0.5}, 0.25, dark));
  d.objects.push_back(plane({0, -1, 0}, {0, 1, 0}, diffuse({0.5, 0.5, 0.5})));
  d.lights.push_back({{2, 3, 4}, {1, 1, 1}, 30});
  d.lights.push_back({{-3, 0.5, 1}, {1, 0.5, 0.2}, 10});
  d.lights.push_back({{0, -2, 0}, {1, 1, 1}, 5});        // below the floor: cos <= 0 for most points
  d.lights.push_back({{0, -1, -1}, {1, 1, 1}, 5});       // on the floor plane itself
  d.lights.push_back({{0.8, 0.2, -0.5}, {1, 1, 1}, 5});  // inside a sphere: always blocked
  d.camera = {{0, 0.5, 5}, {0, 0, 0}, {0, 1, 0}, 60.0};  // the top rows see only background
  d.render.background = {0.1, 0.2, 0.3};
  d.render.max_depth = 3;
  for (const std::uint32_t spp : {1u, 4u}) {
    INFO("spp " << spp);
    d.render.width = 29;
    d.render.height = 19;
    d.render.samples = spp;
    check_packets_match_per_pixel(d);
    // With a transparent object the first-hit shadows go through the transmittance walk instead.
    scene::SceneDesc glass = d;
    scene::Material g;
    g.diffuse = 0.2;
    g.transparency = 0.8;
    g.ior = 1.4;
    glass.objects.push_back(sphere({0, 0, 1.5}, 0.5, g));
    check_packets_match_per_pixel(glass);
    // The camera inside glass (a water sphere around everything): every path and first-hit
    // shadow ray starts in that medium.
    scene::SceneDesc inside = glass;
    scene::Material water = g;
    water.transparency = 0.9;
    water.ior = 1.33;
    inside.objects.push_back(sphere({0, 0, 0}, 8.0, water));
    REQUIRE(render::RenderScene::build(inside).camera_media() == std::vector<std::uint32_t>{6});
    check_packets_match_per_pixel(inside);
  }
}

TEST_CASE("Packets drop and count NaN and Inf samples exactly like the per-pixel path", "[render][packets]") {
  scene::SceneDesc d;
  // A light brighter than float's range: its float intensity is +Inf, so lit samples are Inf,
  // and NaN where a zero colour channel multiplies it.
  d.objects.push_back(sphere({-0.6, 0, 0}, 0.5, diffuse({1, 1, 1})));
  d.objects.push_back(sphere({0.6, 0, 0}, 0.5, diffuse({1, 0, 1})));
  d.objects.push_back(plane({0, -0.5, 0}, {0, 1, 0}, diffuse({0.5, 0.5, 0.5})));
  d.lights.push_back({{0, 0, 3}, {1, 1, 1}, 1e300});
  d.lights.push_back({{0, 3, 0}, {1, 1, 1}, 2});
  d.camera = {{0, 0.5, 4}, {0, 0, 0}, {0, 1, 0}, 40.0};
  d.render.width = 21;
  d.render.height = 11;
  d.render.samples = 3;
  const Rendered r = check_packets_match_per_pixel(d);
  REQUIRE(r.stats.nan_samples > 0);
  REQUIRE(r.stats.inf_samples > 0);
  for (const float v : r.rgb) REQUIRE(std::isfinite(v));
}

TEST_CASE("render_local gives the same image with and without packets", "[render][packets]") {
  scene::SceneDesc d = testing::load_bundled("room.json");
  d.render.width = 45;
  d.render.height = 31;
  d.render.samples = 2;
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::LocalOptions pixels = local_options(/* threads = */ 2, /* tile_size = */ 16, /* packets = */ false);
  const render::LocalOptions packets = local_options(/* threads = */ 2, /* tile_size = */ 7);
  const auto a = render::render_local(rs, d.render, pixels);
  const auto b = render::render_local(rs, d.render, packets);
  REQUIRE(a.image.rgb.size() == b.image.rgb.size());
  REQUIRE(std::memcmp(a.image.rgb.data(), b.image.rgb.data(), a.image.rgb.size() * sizeof(float)) == 0);
  REQUIRE(a.stats.rays == b.stats.rays);
}

// The packet path computes its shadow-ray origins a component to an array, four entries at a
// time without branches (render::offset_ray_origins): every entry must get
// accel::offset_ray_origin's bits, for either sign of the offset and for the special sums (zeros
// of either sign, infinities, the largest and smallest floats), whatever the count (n up to 13:
// the last group of four part padding).
TEST_CASE("offset_ray_origins gives offset_ray_origin's bits entry by entry", "[render][offset]") {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const float special[] = {0.0f, -0.0f, 1.0f, -1.0f, kInf, -kInf, 3e38f, -3e38f, 1e-45f, -1e-45f, 1e-38f, -2.5f};
  const float normals[] = {0.0f, -0.0f, 1.0f, -1.0f, 0.6f, -0.8f};
  std::uint64_t state = 17;
  const auto next = [&] {  // splitmix64
    std::uint64_t z = (state += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  };
  const auto uniform = [&](float a, float b) { return a + (b - a) * float(next() >> 40) * 0x1p-24f; };
  int checked = 0, stepped = 0;
  for (int trial = 0; trial < 3000; ++trial) {
    const int n = 1 + trial % 13;
    float a[15][16] = {};  // p, e, g, w and o, three components each, up to 16 entries
    std::vector<Vec3f> ps, es, gs, ws;
    for (int j = 0; j < n; ++j) {
      Vec3f p, g, w;
      for (int c = 0; c < 3; ++c) {
        const float pc = next() % 3 == 0 ? special[next() % std::size(special)] : uniform(-100.0f, 100.0f);
        const float gc = next() % 3 == 0 ? normals[next() % std::size(normals)] : uniform(-1.0f, 1.0f);
        const float wc = uniform(-1.0f, 1.0f);
        (c == 0 ? p.x : c == 1 ? p.y : p.z) = pc;
        (c == 0 ? g.x : c == 1 ? g.y : g.z) = gc;
        (c == 0 ? w.x : c == 1 ? w.y : w.z) = wc;
      }
      const float err = next() % 4 == 0 ? 0.0f : uniform(1e-7f, 1e-3f);
      const Vec3f e{err, err * 0.5f, err * 2.0f};
      const Vec3f* const vs[4] = {&p, &e, &g, &w};
      for (int k = 0; k < 4; ++k) {
        a[3 * k][j] = vs[k]->x, a[3 * k + 1][j] = vs[k]->y, a[3 * k + 2][j] = vs[k]->z;
      }
      ps.push_back(p), es.push_back(e), gs.push_back(g), ws.push_back(w);
    }
    const float* const p[3] = {a[0], a[1], a[2]};
    const float* const e[3] = {a[3], a[4], a[5]};
    const float* const g[3] = {a[6], a[7], a[8]};
    const float* const w[3] = {a[9], a[10], a[11]};
    float* const o[3] = {a[12], a[13], a[14]};
    render::offset_ray_origins(n, p, e, g, w, o);
    for (int j = 0; j < n; ++j) {
      const auto sj = static_cast<std::size_t>(j);
      const Vec3f want = accel::offset_ray_origin(ps[sj], es[sj], gs[sj], ws[sj]);
      const float wants[3] = {want.x, want.y, want.z};
      for (int c = 0; c < 3; ++c) {
        INFO("trial " << trial << " entry " << j << " component " << c);
        CHECK(std::bit_cast<std::uint32_t>(o[c][j]) == std::bit_cast<std::uint32_t>(wants[c]));
        ++checked;
        if (std::bit_cast<std::uint32_t>(wants[c]) != std::bit_cast<std::uint32_t>(p[c][j])) ++stepped;
      }
    }
  }
  CHECK(checked > 50000);
  CHECK(stepped > checked / 2);  // most components do step away from p
}
