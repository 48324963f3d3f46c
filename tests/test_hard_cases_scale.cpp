// Numerical hard cases of scale: a unit sphere seen from 1e5 and 1e6 away, a sphere on a plane
// under grazing light at three scales (shadow acne), and self-intersection on a tiny far sphere
// and a huge one. The references are in test_hard_cases.h.
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

// One diffuse sphere (object 0) under one point light (light 0), rendered, with the float values
// the renderer used, in long double for the references.
struct LitSphere {
  render::RenderScene rs;
  render::Tile tile;
  accel::SphereShape shape;
  V3L center;
  LD radius = 0;
  V3L light;
  LD intensity = 0;
  LD albedo = 0;
};

LitSphere render_lit_sphere(const scene::SceneDesc& desc) {
  LitSphere out{render::RenderScene::build(desc), {}, {}, {}, 0, {}, 0, 0};
  out.tile = render_image(out.rs, desc.render);
  CHECK(out.tile.stats.nan_samples == 0);
  CHECK(out.tile.stats.inf_samples == 0);
  out.shape = out.rs.geometry().shape(0).sphere;
  out.center = ld(out.shape.center);
  out.radius = out.shape.radius;
  out.light = ld(out.rs.lights()[0].position);
  out.intensity = out.rs.lights()[0].intensity.x;
  out.albedo = out.rs.material(0).color.x;
  return out;
}

}  // namespace

// =============================================================================================
// 1. A unit sphere seen from 1e5 and 1e6 units away.
//
// The textbook b^2 - c discriminant cancels completely here (c = |o - c|^2 - r^2 ~ 1e12 in
// float has an ulp of 65536), and o + t d carries an error of ~ulp(1e6) = 0.06, so a float
// renderer only gets this right with a cancellation-free discriminant and a hit point formed in
// the sphere's frame. A pixel agrees when hit/miss matches the exact line of the float camera
// ray, the normal is within kMaxNormalAngle of the exact one and the shaded value within
// kMaxShadeError of the closed form (relative to the value at cos = 1).
TEST_CASE("far unit sphere: silhouette, normals and shading match a long-double reference", "[hard][far]") {
  constexpr std::uint32_t kSide = 128;
  // 1e-4 rad: 8x the normal error of a hit point formed in the sphere's frame at 1e6 (about
  // 1.2e-5 rad; DTRACED_HARD_VERBOSE prints it), 100x below what o + t d gives at 1e5 (0.8 degrees).
  constexpr LD kMaxNormalAngle = 1e-4;
  // A normal error delta changes cos by at most delta, so the shaded value by delta * peak.
  constexpr LD kMaxShadeError = 2e-4;
  constexpr double kMinAgreement = 0.9995;

  for (const double distance : {1e5, 1e6}) {
    CAPTURE(distance);
    scene::SceneDesc desc = make_desc({0, 0, distance}, {0, 0, 0}, fov_for(1.6, distance), kSide);
    desc.objects.push_back(sphere({0, 0, 0}, 1.0, diffuse()));
    // About as far as the camera, up and to the side: most of the visible disc is lit and the
    // terminator crosses it. Intensity ~ distance^2 keeps the radiance near albedo / pi * cos.
    const Vec3d light_pos{0.5 * distance, 0.7 * distance, distance};
    desc.lights.push_back(point_light(light_pos, math::length_squared(light_pos)));

    const LitSphere fixture = render_lit_sphere(desc);
    const auto& [rs, tile, s, center, radius, light, intensity, albedo] = fixture;

    std::uint32_t hits = 0, silhouette_mismatch = 0, normal_bad = 0, shade_bad = 0, miss_bad = 0, textbook_wrong = 0;
    LD max_angle = 0, max_shade = 0, max_mismatch_distance = 0;
    for (std::uint32_t y = 0; y < kSide; ++y) {
      for (std::uint32_t x = 0; x < kSide; ++x) {
        const math::Ray ray = pixel_ray(rs, desc.render, x, y);
        const V3L o = ld(ray.o), d = ld(ray.d);
        const LineSphere ref = line_sphere(o, d, center, radius);
        accel::Hit hit;
        const bool got = rs.geometry().intersect(ray, hit);
        const float value = tile_pixel(tile, x, y)[0];
        {
          // Control: the textbook float discriminant b^2 - (|f|^2 - r^2) on the same ray.
          const Vec3f f = ray.o - s.center;
          const float b = math::dot(f, ray.d);
          textbook_wrong += (b * b - (math::dot(f, f) - s.radius * s.radius) >= 0.0f) != ref.hit;
        }
        if (got != ref.hit) {
          ++silhouette_mismatch;
          max_mismatch_distance = std::max(max_mismatch_distance, std::abs(ref.h - radius) / radius);
          continue;
        }
        if (!ref.hit) {
          miss_bad += value != 0.0f;
          continue;
        }
        ++hits;
        const V3L p = o + d * ref.t0;
        const V3L n = (p - center) / radius;
        const LD angle = angle_between(ld(hit.n), n);
        const LD expected = lambert(albedo, intensity, p, n, light);
        const LD peak = albedo / kPi * intensity / math::length_squared(light - p);
        const LD shade = std::abs(LD(value) - expected) / peak;
        max_angle = std::max(max_angle, angle);
        max_shade = std::max(max_shade, shade);
        normal_bad += !(angle <= kMaxNormalAngle);
        shade_bad += !(shade <= kMaxShadeError);
      }
    }
    const std::uint32_t total = kSide * kSide;
    const std::uint32_t bad = silhouette_mismatch + normal_bad + shade_bad + miss_bad;
    report(
        "[far] distance %.0e: %u/%u pixels agree (%u sphere pixels); silhouette mismatches %u (max |h-r|/r "
        "%.2Le), normal > %.0Le rad: %u (max %.3Le rad), shade > %.0Le: %u (max %.3Le), background wrong %u; "
        "textbook float discriminant wrong on %u\n",
        distance, total - bad, total, hits, silhouette_mismatch, max_mismatch_distance, kMaxNormalAngle, normal_bad,
        max_angle, kMaxShadeError, shade_bad, max_shade, miss_bad, textbook_wrong);
    REQUIRE(hits > total / 4);  // the sphere covers a good part of the image
    CHECK(double(total - bad) >= kMinAgreement * total);
  }
}

// =============================================================================================
// 2. A sphere resting on a plane, one point light at 1, 5 and 30 degrees of elevation, the whole
// scene scaled by 1e-3, 1 and 1e3 (light intensity by scale^2 so radiance is comparable).
//
// For each pixel centre the visible point and whether its segment to the light misses the
// sphere are decided in long double. Acne: a pixel the reference calls lit that renders darker
// than half its exact radiance, or a shadowed one brighter than half its unshadowed radiance.
// Pixels whose camera ray or shadow segment passes within kMargin * radius of the sphere's
// silhouette are skipped: there the float scene may legitimately decide either way.
TEST_CASE("sphere on a plane under grazing light: no shadow acne at any scale", "[hard][acne]") {
  constexpr std::uint32_t kSide = 96;
  constexpr LD kMargin = 1e-4;
  constexpr LD kSphereMinCos = 1e-2;  // lit side of the sphere, away from the terminator
  // Lit pixels must also match the closed form closely; 1e-3 leaves a wide margin over the
  // rounding of the float hit point and light vector (measured below 1e-5).
  constexpr LD kMaxLitError = 1e-3;

  for (const double scale : {1e-3, 1.0, 1e3}) {
    for (const double elevation_deg : {1.0, 5.0, 30.0}) {
      CAPTURE(scale, elevation_deg);
      const double e = elevation_deg * std::numbers::pi / 180.0;
      const double azimuth = 20.0 * std::numbers::pi / 180.0;
      scene::SceneDesc desc = make_desc(Vec3d{-4, 7, 6} * scale, Vec3d{3, 0, 1} * scale, 60.0, kSide);
      desc.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse()));
      desc.objects.push_back(sphere(Vec3d{0, 1, 0} * scale, scale, diffuse()));
      // Elevation as seen from the sphere's contact point, 8 radii away.
      const Vec3d light_pos =
          Vec3d{-std::cos(e) * std::cos(azimuth), std::sin(e), -std::cos(e) * std::sin(azimuth)} * (8.0 * scale);
      desc.lights.push_back(point_light(light_pos, 100.0 * scale * scale));

      const render::RenderScene rs = render::RenderScene::build(desc);
      const render::Tile tile = render_image(rs, desc.render);
      CHECK(tile.stats.nan_samples == 0);
      CHECK(tile.stats.inf_samples == 0);

      const accel::PlaneShape& pl = rs.geometry().shape(0).plane;
      const accel::SphereShape& sp = rs.geometry().shape(1).sphere;
      const V3L plane_point = ld(pl.point), plane_normal = ld(pl.normal);
      const V3L center = ld(sp.center);
      const LD radius = sp.radius;
      const V3L light = ld(rs.lights()[0].position);
      const LD intensity = rs.lights()[0].intensity.x;
      const LD albedo = rs.material(0).color.x;

      std::uint32_t lit = 0, shadowed = 0, sphere_lit = 0, sphere_dark = 0, skipped = 0, acne = 0, leaks = 0;
      std::uint32_t naive_blocked = 0;
      LD max_lit_error = 0, worst_acne_ratio = 1;
      for (std::uint32_t y = 0; y < kSide; ++y) {
        for (std::uint32_t x = 0; x < kSide; ++x) {
          const math::Ray ray = pixel_ray(rs, desc.render, x, y);
          const V3L o = ld(ray.o), d = ld(ray.d);
          const LD value = tile_pixel(tile, x, y)[0];
          const LineSphere ls = line_sphere(o, d, center, radius);
          if (std::abs(ls.h - radius) < kMargin * radius) {
            ++skipped;
            continue;
          }
          if (ls.hit && ls.t0 > 0) {
            const V3L p = o + d * ls.t0;
            const V3L n = (p - center) / radius;
            const LD cos_l = cos_to_light(p, n, light);
            if (cos_l > kSphereMinCos) {
              ++sphere_lit;
              naive_blocked += naive_shadow_blocked(rs, ray);
              const LD expected = lambert(albedo, intensity, p, n, light);
              if (value < 0.5 * expected) ++acne;
              worst_acne_ratio = std::min(worst_acne_ratio, value / expected);
              max_lit_error = std::max(max_lit_error, std::abs(value - expected) / expected);
            } else if (cos_l < -kSphereMinCos) {
              ++sphere_dark;
              if (value != 0) ++leaks;
            } else {
              ++skipped;
            }
            continue;
          }
          const LD t = line_plane(o, d, plane_point, plane_normal);
          if (!(t > 0)) {
            if (value != 0) ++leaks;  // sky: nothing lights it
            continue;
          }
          const V3L p = o + d * t;
          const LD unshadowed = lambert(albedo, intensity, p, plane_normal, light);
          const LD gap = segment_point_distance(p, light, center) - radius;
          if (std::abs(gap) < kMargin * radius) {
            ++skipped;
          } else if (gap > 0) {
            ++lit;
            naive_blocked += naive_shadow_blocked(rs, ray);
            if (value < 0.5 * unshadowed) ++acne;
            worst_acne_ratio = std::min(worst_acne_ratio, value / unshadowed);
            max_lit_error = std::max(max_lit_error, std::abs(value - unshadowed) / unshadowed);
          } else {
            ++shadowed;
            if (value > 0.5 * unshadowed) ++leaks;
          }
        }
      }
      report(
          "[acne] scale %.0e elevation %2.0f deg: plane lit %u shadowed %u, sphere lit %u dark %u, skipped %u; "
          "acne %u, leaks %u, min rendered/exact on lit %.6Lf, max rel. error on lit %.2Le; unoffset shadow "
          "rays blocked on %u lit pixels\n",
          scale, elevation_deg, lit, shadowed, sphere_lit, sphere_dark, skipped, acne, leaks, worst_acne_ratio,
          max_lit_error, naive_blocked);
      // The view must exercise every category.
      REQUIRE(lit > 1000);
      REQUIRE(shadowed > 100);
      REQUIRE(sphere_lit > 100);
      CHECK(acne == 0);
      CHECK(leaks == 0);
      CHECK(max_lit_error <= kMaxLitError);
    }
  }
}

// =============================================================================================
// 7. Self-intersection at scale: a radius-1e-3 sphere 1e3 from the origin (an ulp of a world
// coordinate there is 6e-5, 6 % of the radius) and a radius-1e3 sphere seen from just above
// its surface. The lit hemisphere must show no black speckles: a speckle is a pixel darker than
// half the closed form L = albedo / pi * I * cos / d^2 at the exact hit point.
//
// A float renderer cannot do better than store the hit point in float world coordinates, off
// by up to e = sqrt(3)/2 ulp(|p|). Seen from the light, at least d_min away, that turns the
// light direction by e / d_min (cos changes by as much) and 1 / d^2 by 2 e / d_min, so
// |L - exact| <= 3 e / d_min * L_peak (L_peak: the value at cos = 1) is the accuracy bound we
// hold every lit pixel to. For the tiny sphere it is 1.8 % of the peak; pixels with
// cos < 4 * bound (and within kMargin * radius of the silhouette) are left out of the speckle
// count, since there a correct renderer may already be off by a quarter of the value.
TEST_CASE("self-intersection at scale: tiny far sphere and huge sphere have no speckles", "[hard][scale]") {
  constexpr LD kMargin = 1e-3;
  constexpr LD kMinCos = 1e-2;
  struct Case {
    const char* name;
    Vec3d center;
    double radius;
    Vec3d eye, look_at;
    double fov;
    Vec3d light;
    double intensity;
  };
  const Vec3d tiny_center{600, 800, 0};  // |c| = 1e3
  const Case cases[] = {
      {"r = 1e-3 at |c| = 1e3", tiny_center, 1e-3, tiny_center + Vec3d{0, 0, 4e-3}, tiny_center, 40.0,
       tiny_center + Vec3d{6e-3, 5e-3, 6e-3}, 1e-4},
      {"r = 1e3, viewer 1.5 above", {0, 0, 0}, 1e3, {0, 1e3 + 1.5, 3}, {0, 1e3, -3}, 70.0, {2, 1e3 + 4, -2}, 16.0},
  };
  for (const Case& k : cases) {
    CAPTURE(k.name);
    scene::SceneDesc desc = make_desc(k.eye, k.look_at, k.fov, 64);
    desc.objects.push_back(sphere(k.center, k.radius, diffuse()));
    desc.lights.push_back(point_light(k.light, k.intensity));
    const LitSphere fixture = render_lit_sphere(desc);
    const auto& [rs, tile, s, c, r, light, intensity, albedo] = fixture;

    const float extent = math::max_component(math::abs(s.center)) + s.radius;
    const LD e = std::sqrt(LD(3)) / 2 * LD(std::nextafter(extent, 2 * extent) - extent);
    const LD bound = 3 * e / (math::length(light - c) - r);
    const LD min_cos = std::max(kMinCos, 4 * bound);

    std::uint32_t lit = 0, speckles = 0, naive_blocked = 0;
    LD max_error = 0, min_ratio = 1;
    for (std::uint32_t y = 0; y < 64; ++y) {
      for (std::uint32_t x = 0; x < 64; ++x) {
        const math::Ray ray = pixel_ray(rs, desc.render, x, y);
        const V3L o = ld(ray.o), d = ld(ray.d);
        const LineSphere ls = line_sphere(o, d, c, r);
        if (!ls.hit || !(ls.t0 > 0) || std::abs(ls.h - r) < kMargin * r) continue;
        const V3L p = o + d * ls.t0;
        const V3L n = (p - c) / r;
        const LD cos_l = cos_to_light(p, n, light);
        if (!(cos_l > 0)) continue;
        const LD expected = lambert(albedo, intensity, p, n, light);
        const LD peak = albedo / kPi * intensity / math::length_squared(light - p);
        const LD value = tile_pixel(tile, x, y)[0];
        max_error = std::max(max_error, std::abs(value - expected) / peak);
        if (cos_l < min_cos) continue;
        ++lit;
        naive_blocked += naive_shadow_blocked(rs, ray);
        speckles += value < 0.5 * expected;
        min_ratio = std::min(min_ratio, value / expected);
      }
    }
    report(
        "[scale] %s: %u lit pixels (cos >= %.3Lf), %u speckles, min rendered/exact %.6Lf; max |L - exact| / L_peak "
        "%.2Le (bound %.2Le); unoffset shadow rays blocked on %u\n",
        k.name, lit, min_cos, speckles, min_ratio, max_error, bound, naive_blocked);
    REQUIRE(lit > 500);
    CHECK(speckles == 0);
    CHECK(max_error <= bound);
  }
}

// =============================================================================================
// 8. A huge ground sphere against a plane at the same height.
//
// Small objects (a ball of radius 0.1, a slab 0.05 thick, a pole, a pebble of radius 0.02) stand
// on a ground that is either the plane y = 0 or a sphere of radius R whose top is at y = 0, for R
// from 1e5 to 1e7. Every pixel sees the ground within x = 6 units of the top, where the sphere
// sags at most x^2 / (2 R) = 18 / R below the plane and its normal tilts by at most 6 / R, so the
// two images must agree, shadows included:
// - a pixel is in shadow (exactly 0: there is no other light) in both images or in neither, but
//   for pixels whose centre lies within the sag's shift of a shadow edge: the shift is at most
//   ~2e-4 units at R = 1e5 against ~1e-2 units of ground per pixel, so about 2 of the ~100 edge
//   pixels; we allow kMaxShadowFlips;
// - a pixel lit in both differs by at most the geometric change of cos / d^2: with the light at
//   least d = 1.2 above the ground and cos >= 0.17, (tilt + sag / d) / cos + 2 sag / d <= 154 / R
//   relative; we allow 200 / R (4.2e-4 measured at R = 1e5, 1/R beyond).
// A hit-point error bound meant for a point computed in float (gamma(5) |p - c|, 0.3 at R = 1e6)
// starts the shadow rays that far above the ground, past the pebble and the slab, and their
// shadows vanish or detach: 47, 168 and 204 pixels flip at R = 1e5, 1e6, 1e7.
TEST_CASE("a huge ground sphere renders like a plane at the same height, shadows included", "[hard][scale]") {
  constexpr std::uint32_t kSide = 96;
  constexpr std::uint32_t kMaxShadowFlips = 5;

  scene::SceneDesc base = make_desc({0.2, 0.9, 1.8}, {0, 0, 0}, 35.0, kSide);
  base.objects.push_back(sphere({0, 0.1, 0}, 0.1, diffuse({0.9, 0.3, 0.2})));
  base.objects.push_back(box({-0.7, 0, 0.2}, {-0.3, 0.05, 0.5}, diffuse({0.2, 0.6, 0.3})));
  base.objects.push_back(box({0.5, 0, -0.4}, {0.54, 0.5, -0.36}, diffuse({0.3, 0.3, 0.8})));
  base.objects.push_back(sphere({0.35, 0.02, 0.55}, 0.02, diffuse({0.8, 0.8, 0.2})));
  base.lights.push_back(point_light({1.5, 1.2, 0.8}, 4.0));

  scene::SceneDesc flat = base;
  flat.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse()));
  const render::RenderScene flat_scene = render::RenderScene::build(flat);
  const render::Tile want = render_image(flat_scene, flat.render);
  std::uint32_t flat_shadowed = 0;
  for (std::size_t i = 0; i < want.rgb.size(); i += 3) flat_shadowed += want.rgb[i] == 0.0f;

  for (const double radius : {1e5, 1e6, 1e7}) {
    CAPTURE(radius);
    scene::SceneDesc round = base;
    round.objects.push_back(sphere({0, -radius, 0}, radius, diffuse()));
    const render::Tile got = render_image(render::RenderScene::build(round), round.render);
    CHECK(got.stats.nan_samples == 0);
    CHECK(got.stats.inf_samples == 0);
    const double max_lit_diff_allowed = 200 / radius;
    std::uint32_t flips = 0, lit_over = 0, round_shadowed = 0;
    double max_lit_diff = 0;
    for (std::size_t i = 0; i < want.rgb.size(); i += 3) {
      const bool want_dark = want.rgb[i] == 0.0f, got_dark = got.rgb[i] == 0.0f;
      round_shadowed += got_dark;
      if (want_dark != got_dark) {
        ++flips;
        continue;
      }
      for (int c = 0; c < 3 && !want_dark; ++c) {
        const double diff =
            std::abs(double(got.rgb[i + c]) - want.rgb[i + c]) / std::max(1e-30, double(want.rgb[i + c]));
        max_lit_diff = std::max(max_lit_diff, diff);
        lit_over += diff > max_lit_diff_allowed;
      }
    }
    report(
        "[huge ground] R = %.0e: %u shadowed pixels (plane: %u), %u flip between lit and shadowed, max relative "
        "difference where both are lit %.2e (%u channels over %.1e)\n",
        radius, round_shadowed, flat_shadowed, flips, max_lit_diff, lit_over, max_lit_diff_allowed);
    REQUIRE(flat_shadowed > 200);  // the view shows shadows worth comparing
    CHECK(flips <= kMaxShadowFlips);
    CHECK(lit_over == 0);
  }
}

}  // namespace dtraced
