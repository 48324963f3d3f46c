// Numerical hard cases at silhouettes: families of rays stepping one ulp at a time across a
// sphere's tangent, and a real camera zoomed onto a silhouette. The references are in
// test_hard_cases.h.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "math/ray.h"
#include "math/vec.h"
#include "render/integrator.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/description.h"
#include "scene/load.h"
#include "scene_builders.h"
#include "test_hard_cases.h"

namespace dtraced {

using namespace testing;
using math::Vec3d;
using math::Vec3f;

namespace {

struct Family {
  const char* name;
  Vec3d center;
  double radius;
  double angle_deg;  // direction in the xz-plane
  double back;       // distance of the ray origin from the tangent point, along the ray
};

// The family's sphere three times: clear glass (ior 1.5), a perfect mirror, and a diffuse and
// specular surface under a point light; max depth 64.
struct FamilyScenes {
  render::RenderScene glass, mirror, diffuse;
};

FamilyScenes family_scenes(const Family& fam, const Vec3d& background) {
  scene::SceneDesc desc = make_desc({0, 0, 0}, {0, 0, -1}, 45.0, 16);
  desc.render.background = background;
  desc.render.max_depth = 64;
  desc.objects.push_back(sphere(fam.center, fam.radius, glass(1.5)));
  FamilyScenes out{render::RenderScene::build(desc), {}, {}};
  desc.objects[0].material = mirror(1.0);
  out.mirror = render::RenderScene::build(desc);
  desc.objects[0].material = diffuse();
  desc.objects[0].material.specular = 0.5;
  desc.lights.push_back(point_light(fam.center + Vec3d{0, 3, 1} * fam.radius, 10.0 * fam.radius * fam.radius));
  out.diffuse = render::RenderScene::build(desc);
  return out;
}

// 2 * steps + 1 floats one ulp apart, `middle` in the middle, increasing towards the sign of
// `side` (+1 or -1).
std::vector<float> ulp_steps(float middle, int side, int steps) {
  std::vector<float> out(2 * steps + 1);
  out[steps] = middle;
  const float outwards = side * std::numeric_limits<float>::infinity();
  for (int j = 1; j <= steps; ++j) {
    out[steps + j] = std::nextafter(out[steps + j - 1], outwards);
    out[steps - j] = std::nextafter(out[steps - j + 1], -outwards);
  }
  return out;
}

}  // namespace

// =============================================================================================
// 3. Grazing rays at a sphere's silhouette.
//
// Families of rays with one direction (no y component) whose origins step by single ulps in y
// across the tangent: the exact distance h from the centre to the line then grows strictly with
// the step, so the hit/miss answer of Geometry::intersect must switch exactly once, from hit to
// miss. Every ray is also traced through the whole integrator with glass, mirror and diffuse
// materials: no NaN or Inf may come out, and clear glass under a uniform background may not
// create energy.
TEST_CASE("grazing rays at a sphere's silhouette: monotone hit/miss and finite radiance", "[hard][grazing]") {
  const Family families[] = {
      {"unit sphere, axis-aligned ray", {0, 0, 0}, 1.0, 0.0, 5.0},
      {"unit sphere, oblique ray", {0, 0, 0}, 1.0, 37.0, 5.0},
      {"offset sphere", {0.3, -0.7, 2.1}, 1.7, 113.0, 4.0},
      {"far sphere, long ray", {1e5, 0, 3e4}, 1.0, 211.0, 1e5},
      {"tiny sphere at 1e3", {1e3, 0, 0}, 1e-3, 71.0, 1.0},
      {"huge sphere, near the horizon", {0, 0, 0}, 1e3, 300.0, 10.0},
  };
  constexpr int kSteps = 1024;  // ulps either side of the tangent
  // Outside this band around the tangent the decision must also be the exact one. It allows
  // 16 ulps of r for the discriminant, plus what forming f = o - c in float costs: each
  // component off by up to ulp(|f|)/2 <= |f| eps / 2 (eps = 2^-23) sideways to the line moves h
  // by (|f| eps / 2)^2 / (2 r); the band takes twice that. (An f formed in double costs nothing.)
  auto band = [](LD f_norm, LD r) {
    const LD eps = std::numeric_limits<float>::epsilon();
    return 16 * eps * r + (f_norm * eps) * (f_norm * eps) / (4 * r);
  };
  const Vec3d background{0.25, 0.5, 1.0};

  for (const Family& fam : families) {
    for (const int side : {+1, -1}) {
      CAPTURE(fam.name, side);
      const FamilyScenes scenes = family_scenes(fam, background);
      const render::RenderScene &glass_scene = scenes.glass, &mirror_scene = scenes.mirror,
                                &diffuse_scene = scenes.diffuse;
      const render::TraceLimits limits{Vec3f(background), 64};

      const accel::LayeredGeometry& geometry = glass_scene.geometry();
      const accel::SphereShape& s = geometry.shape(0).sphere;
      const V3L c = ld(s.center);
      const LD r = s.radius;
      const LD a = fam.angle_deg * kPi / 180;
      const Vec3f dir = math::normalize(Vec3f{float(std::cos(a)), 0.0f, float(std::sin(a))});
      const V3L d = ld(dir);
      // x and z of the origin are rounded first; then y is chosen so the exact line is tangent.
      const float ox = float(c.x - LD(fam.back) * d.x / math::length(d));
      const float oz = float(c.z - LD(fam.back) * d.z / math::length(d));
      const LD fx = ox - c.x, fz = oz - c.z;
      const LD offset_xz = std::abs(fx * d.z - fz * d.x) / math::length(d);
      REQUIRE(offset_xz < r);
      const float oy_tangent = float(c.y + side * std::sqrt(r * r - offset_xz * offset_xz));

      // Index j counts steps outwards (away from the centre): h grows with j.
      std::vector<LD> h(2 * kSteps + 1);
      std::vector<char> hit(2 * kSteps + 1);
      std::vector<char> textbook_hit(2 * kSteps + 1);  // control: b^2 - (|f|^2 - r^2) >= 0 in float
      std::uint64_t non_finite = 0, energy_gain = 0;
      LD max_glass_ratio = 0;
      const std::vector<float> ys = ulp_steps(oy_tangent, side, kSteps);  // origins' y, ordered outwards
      for (int j = -kSteps; j <= kSteps; ++j) {
        const float oy = ys[j + kSteps];
        math::Ray ray;
        ray.o = {ox, oy, oz};
        ray.d = dir;
        h[j + kSteps] = line_sphere(ld(ray.o), d, c, r).h;
        accel::Hit record;
        hit[j + kSteps] = geometry.intersect(ray, record);
        const Vec3f f = ray.o - s.center;
        const float b = math::dot(f, ray.d);
        textbook_hit[j + kSteps] = b * b - (math::dot(f, f) - s.radius * s.radius) >= 0.0f;

        for (const render::RenderScene* rs : {&glass_scene, &mirror_scene, &diffuse_scene}) {
          render::TraceStats stats;
          const Vec3f l = render::trace_radiance(*rs, ray, math::SampleKey{}, limits, stats);
          non_finite += !math::is_finite(l);
          if (rs == &glass_scene) {
            for (int ch = 0; ch < 3; ++ch) {
              const LD ratio = LD(l[ch]) / LD(background[ch]);
              max_glass_ratio = std::max(max_glass_ratio, ratio);
              energy_gain += ratio > 1 + kEnergyGainTolerance;
            }
          }
        }
      }
      for (int i = 1; i <= 2 * kSteps; ++i) REQUIRE(h[i] > h[i - 1]);  // precondition: h strictly increasing
      REQUIRE(h.front() < r);
      REQUIRE(h.back() > r);

      int first_miss = -1, hits_after_miss = 0, exact_switch = -1, wrong_outside_band = 0;
      int textbook_first_miss = -1, textbook_hits_after_miss = 0, textbook_wrong = 0;
      const LD f_norm = math::length(V3L{LD(ox), LD(oy_tangent), LD(oz)} - c);
      for (int i = 0; i <= 2 * kSteps; ++i) {
        if (!hit[i] && first_miss < 0) first_miss = i;
        if (hit[i] && first_miss >= 0) ++hits_after_miss;
        if (!textbook_hit[i] && textbook_first_miss < 0) textbook_first_miss = i;
        if (textbook_hit[i] && textbook_first_miss >= 0) ++textbook_hits_after_miss;
        if (h[i] > r && exact_switch < 0) exact_switch = i;
        if (std::abs(h[i] - r) > band(f_norm, r) && bool(hit[i]) != (h[i] < r)) ++wrong_outside_band;
        if (std::abs(h[i] - r) > band(f_norm, r) && bool(textbook_hit[i]) != (h[i] < r)) ++textbook_wrong;
      }
      report(
          "[grazing] %-30s side %+d: switch at step %+d, exact %+d (%+d ulps), hits after first miss %d, wrong "
          "outside band %d, non-finite %llu, max glass L/B %.8Lf; textbook float: hits after first miss %d, wrong "
          "outside band %d\n",
          fam.name, side, first_miss - kSteps, exact_switch - kSteps, first_miss - exact_switch, hits_after_miss,
          wrong_outside_band, static_cast<unsigned long long>(non_finite), max_glass_ratio, textbook_hits_after_miss,
          textbook_wrong);
      CHECK(first_miss > 0);  // the rays nearest the centre hit
      CHECK(hits_after_miss == 0);
      CHECK(wrong_outside_band == 0);
      CHECK(non_finite == 0);
      CHECK(energy_gain == 0);
    }
  }
}

// 3 (cont.). A real camera with a tiny field of view aimed at the silhouette of a unit sphere:
// pixel centres 1e-6 apart straddle it, 4 jittered samples per pixel, through render_tile.
TEST_CASE("grazing camera rays at a silhouette: no NaN or Inf through render_tile", "[hard][grazing]") {
  const Vec3d background{0.25, 0.5, 1.0};
  // Unit sphere, camera 5 away: the silhouette point in the xz-plane is (sqrt(24)/5, 0, 1/5).
  const Vec3d eye{0, 0, 5};
  const Vec3d tangent_point{std::sqrt(24.0) / 5.0, 0.0, 0.2};
  // 64 pixels over 6.4e-5 units at the sphere: a few float direction steps per pixel.
  const double fov = fov_for(3.2e-5, math::length(tangent_point - eye));
  for (int variant = 0; variant < 2; ++variant) {
    CAPTURE(variant);
    scene::SceneDesc desc = make_desc(eye, tangent_point, fov, 64);
    desc.render.samples = 4;
    desc.render.max_depth = 64;
    desc.render.background = background;
    if (variant == 0) {
      desc.objects.push_back(sphere({0, 0, 0}, 1.0, glass(1.5)));
    } else {
      desc.objects.push_back(sphere({0, 0, 0}, 1.0, mirror(0.9)));
      desc.objects.push_back(plane({0, -1, 0}, {0, 1, 0}, diffuse()));
      desc.lights.push_back(point_light({3, 4, 2}, 30.0));
    }
    const render::RenderScene rs = render::RenderScene::build(desc);
    const render::Tile tile = render_image(rs, desc.render);
    CHECK(tile.stats.nan_samples == 0);
    CHECK(tile.stats.inf_samples == 0);
    std::uint32_t on_sphere = 0, off_sphere = 0;
    for (std::uint32_t y = 0; y < 64; ++y) {
      for (std::uint32_t x = 0; x < 64; ++x) {
        accel::Hit record;
        (rs.geometry().intersect(pixel_ray(rs, desc.render, x, y), record) ? on_sphere : off_sphere) += 1;
      }
    }
    CHECK(on_sphere > 0);  // the view really straddles the silhouette
    CHECK(off_sphere > 0);
    if (variant == 0) {
      const EnergyStats e = energy_of(tile, background);
      report("[grazing] silhouette close-up, glass: %u on / %u off the sphere, L/B in [%.8f, %.8f]\n", on_sphere,
             off_sphere, e.min_ratio, e.max_ratio);
      CHECK(e.non_finite == 0);
      CHECK(e.max_ratio <= 1 + kEnergyGainTolerance);
    }
  }
}

}  // namespace dtraced
