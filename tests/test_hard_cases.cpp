// Numerical hard cases for the renderer: far, tiny and huge spheres, grazing light, grazing rays,
// total internal reflection, touching, nested and index-matched dielectrics.
//
// Every reference here is computed in long double from the very float rays the renderer traces
// (CameraF::generate) and the float shapes it intersects (RenderScene::geometry().shapes()), so
// the only error under test is the renderer's own rounding, not the float conversion of the
// scene description. Images are small (64-128 px, one sample through each pixel centre unless
// said otherwise) so the file runs in a few seconds in a Release build.
//
// Set DTRACED_HARD_VERBOSE=1 to print the measured margins of every check.

#include <algorithm>
#include <cmath>
#include <cstdarg>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <numbers>
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

namespace dtraced {
namespace {

using LD = long double;
using V3L = math::Vec3<LD>;
using math::Vec3d;
using math::Vec3f;

constexpr LD kPi = std::numbers::pi_v<LD>;

__attribute__((format(printf, 1, 2))) void report(const char* format, ...) {
  static const bool verbose = std::getenv("DTRACED_HARD_VERBOSE") != nullptr;
  if (!verbose) return;
  va_list args;
  va_start(args, format);
  std::vfprintf(stdout, format, args);
  va_end(args);
  std::fflush(stdout);
}

V3L ld(const Vec3f& v) { return V3L(v); }

// ---------------------------------------------------------------------------------------------
// Scene construction.

scene::Material diffuse(Vec3d color = {0.8, 0.8, 0.8}) {
  scene::Material m;
  m.color = color;
  m.diffuse = 1.0;
  m.specular = 0.0;
  return m;
}

// Clear dielectric: no local shading, no mirror coat; Fresnel alone splits the light.
scene::Material glass(double ior, double transparency = 1.0) {
  scene::Material m;
  m.color = {1, 1, 1};
  m.diffuse = 0.0;
  m.transparency = transparency;
  m.ior = ior;
  return m;
}

scene::Material mirror(double reflectivity) {
  scene::Material m;
  m.color = {1, 1, 1};
  m.diffuse = 0.0;
  m.reflectivity = reflectivity;
  return m;
}

scene::Object sphere(Vec3d center, double radius, const scene::Material& m) {
  scene::Object o;
  o.type = scene::ObjectType::kSphere;
  o.sphere = {center, radius};
  o.material = m;
  return o;
}

scene::Object box(Vec3d lo, Vec3d hi, const scene::Material& m) {
  scene::Object o;
  o.type = scene::ObjectType::kBox;
  o.box = {lo, hi};
  o.material = m;
  return o;
}

scene::Object plane(Vec3d point, Vec3d normal, const scene::Material& m) {
  scene::Object o;
  o.type = scene::ObjectType::kPlane;
  o.plane = {point, normal};
  o.material = m;
  return o;
}

scene::Light point_light(Vec3d position, double intensity) {
  scene::Light l;
  l.position = position;
  l.color = {1, 1, 1};
  l.intensity = intensity;
  return l;
}

scene::SceneDesc make_desc(Vec3d eye, Vec3d look_at, double fov_deg, std::uint32_t side) {
  scene::SceneDesc desc;
  desc.camera.position = eye;
  desc.camera.look_at = look_at;
  desc.camera.up = {0, 1, 0};
  desc.camera.fov_deg = fov_deg;
  desc.render.width = side;
  desc.render.height = side;
  desc.render.samples = 1;
  desc.render.max_depth = 8;
  desc.render.background = {0, 0, 0};
  desc.render.seed = 1;
  return desc;
}

// Vertical field of view (degrees) that shows `half_extent` above and below the look-at point
// from `distance` away.
double fov_for(double half_extent, double distance) {
  return 2.0 * std::atan(half_extent / distance) * 180.0 / std::numbers::pi;
}

// The ray the renderer traces for the single sample of pixel (x, y): through the pixel centre.
math::Ray pixel_ray(const render::RenderScene& rs, const scene::RenderSettings& s, std::uint32_t x, std::uint32_t y) {
  return rs.camera().generate(x + 0.5, y + 0.5, s.width, s.height);
}

render::Tile render_image(const render::RenderScene& rs, const scene::RenderSettings& s) {
  return render::render_tile(rs, s, {0, 0, s.width, s.height});
}

const float* tile_pixel(const render::Tile& t, std::uint32_t x, std::uint32_t y) {
  return &t.rgb[(std::size_t(y) * t.rect.width + x) * 3];
}

// ---------------------------------------------------------------------------------------------
// Long-double reference geometry. Directions need not have unit length: the references are
// about the exact line through the float origin along the float direction.

struct LineSphere {
  LD h = 0;  // distance from the centre to the line
  bool hit = false;
  LD t0 = 0, t1 = 0;  // roots, t0 <= t1, valid when hit
};

LineSphere line_sphere(const V3L& o, const V3L& d, const V3L& c, LD r) {
  LineSphere out;
  const V3L f = o - c;
  const LD dd = math::dot(d, d);
  const V3L fxd = math::cross(f, d);
  const LD fxd2 = math::dot(fxd, fxd);
  out.h = std::sqrt(fxd2 / dd);
  // Lagrange's identity: b^2 - dd (|f|^2 - r^2) = dd r^2 - |f x d|^2, free of cancellation.
  const LD disc = dd * r * r - fxd2;
  if (disc < 0) return out;
  out.hit = true;
  const LD b = math::dot(f, d);
  const LD q = -(b + std::copysign(std::sqrt(disc), b));
  const LD ta = q / dd;
  const LD tb = q != 0 ? (math::dot(f, f) - r * r) / q : ta;
  out.t0 = std::min(ta, tb);
  out.t1 = std::max(ta, tb);
  return out;
}

// Parameter of the line's crossing of a plane (infinite when parallel).
LD line_plane(const V3L& o, const V3L& d, const V3L& p, const V3L& n) { return math::dot(p - o, n) / math::dot(d, n); }

struct LineBox {
  bool hit = false;
  LD t_near = 0, t_far = 0;
  int axis = -1;         // axis of the face the line enters through
  LD edge_distance = 0;  // distance of the entry point from the entry face's border
};

LineBox line_box(const V3L& o, const V3L& d, const V3L& lo, const V3L& hi) {
  LineBox out;
  out.t_near = -std::numeric_limits<LD>::infinity();
  out.t_far = std::numeric_limits<LD>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0) {
      if (o[a] < lo[a] || o[a] > hi[a]) return out;
      continue;
    }
    LD t_a = (lo[a] - o[a]) / d[a], t_b = (hi[a] - o[a]) / d[a];
    if (t_a > t_b) std::swap(t_a, t_b);
    if (t_a > out.t_near) {
      out.t_near = t_a;
      out.axis = a;
    }
    out.t_far = std::min(out.t_far, t_b);
  }
  out.hit = out.t_near <= out.t_far && out.t_far > 0;
  if (out.hit && out.axis >= 0) {
    const V3L p = o + d * out.t_near;
    out.edge_distance = std::numeric_limits<LD>::infinity();
    for (int a = 0; a < 3; ++a) {
      if (a == out.axis) continue;
      out.edge_distance = std::min({out.edge_distance, p[a] - lo[a], hi[a] - p[a]});
    }
  }
  return out;
}

// Distance from c to the segment [a, b].
LD segment_point_distance(const V3L& a, const V3L& b, const V3L& c) {
  const V3L ab = b - a;
  const LD s = std::clamp(math::dot(c - a, ab) / math::dot(ab, ab), LD(0), LD(1));
  return math::length(c - (a + ab * s));
}

LD angle_between(const V3L& a, const V3L& b) { return std::atan2(math::length(math::cross(a, b)), math::dot(a, b)); }

// Radiance of a Lambertian point under one unshadowed point light (the renderer's local term
// with diffuse = 1, specular = 0): albedo / pi * I * max(0, cos) / dist^2.
LD lambert(LD albedo, LD intensity, const V3L& p, const V3L& n, const V3L& light) {
  const V3L to_l = light - p;
  const LD dist2 = math::dot(to_l, to_l);
  const LD cos_l = math::dot(n, to_l) / std::sqrt(dist2);
  return albedo / kPi * intensity * std::max(LD(0), cos_l) / dist2;
}

LD cos_to_light(const V3L& p, const V3L& n, const V3L& light) { return math::dot(n, math::normalize(light - p)); }

// Control for the acne tests: would a shadow ray that starts exactly at the hit point the
// geometry reports, with no offset, be blocked? Counted on pixels the reference calls lit, it
// shows how much work offset_ray_origin does in each scene (reported, not asserted: it depends
// on how the intersector treats t near 0).
bool naive_shadow_blocked(const render::RenderScene& rs, const math::Ray& camera_ray) {
  accel::Hit hit;
  if (!rs.geometry().intersect(camera_ray, hit)) return false;
  const Vec3f to_light = rs.lights()[0].position - hit.p;
  math::Ray shadow;
  shadow.o = hit.p;
  shadow.t_max = math::length(to_light);
  shadow.d = to_light / shadow.t_max;
  accel::Hit blocker;
  return rs.geometry().intersect(shadow, blocker);
}

// ---------------------------------------------------------------------------------------------
// Energy bookkeeping for clear dielectrics under a uniform background B and no light.
//
// Whitted splitting gives every leaf of the ray tree the background, with weights that are
// products of F and 1 - F, so the pixel is exactly B when every branch is followed to its end.
// The renderer drops branches whose weight falls below 1e-6 and stops at max_depth; both only
// lose energy. Float rounding of F, 1 - F and the weighted sums can add a few ulps per interface.

struct EnergyStats {
  double min_ratio = std::numeric_limits<double>::infinity();  // min over pixels and channels of L / B
  double max_ratio = 0.0;
  std::uint64_t non_finite = 0;
  std::uint64_t pixels = 0;
};

EnergyStats energy_of(const render::Tile& tile, const Vec3d& background) {
  EnergyStats e;
  for (std::uint32_t y = 0; y < tile.rect.height; ++y) {
    for (std::uint32_t x = 0; x < tile.rect.width; ++x) {
      const float* px = tile_pixel(tile, x, y);
      ++e.pixels;
      for (int c = 0; c < 3; ++c) {
        if (!std::isfinite(px[c])) {
          ++e.non_finite;
          continue;
        }
        const double ratio = double(px[c]) / background[c];
        e.min_ratio = std::min(e.min_ratio, ratio);
        e.max_ratio = std::max(e.max_ratio, ratio);
      }
    }
  }
  return e;
}

// Energy never increases: a few ulps per interface on up to ~64 interfaces.
constexpr double kEnergyGainTolerance = 1e-5;

// Long-double Whitted reference for scenes made only of clear dielectrics (transparency 1,
// reflectivity 0, spheres and boxes) under a uniform background and no lights. It follows the
// renderer's documented rules: exact Fresnel, total internal reflection, the stack of media the
// path is in (entering when the shape is not on the stack; eta = n_to / n_from; eta == 1
// continues the same ray), no branch below kMinBranchWeight, no bounce past max_depth. It
// returns the fraction of the background that reaches the pixel and, separately, the weight
// dropped by each of the two cut-offs, which must add up to 1: that is the bookkeeping the
// renderer's float result is held to.
class DielectricReference {
 public:
  struct Result {
    LD background = 0;   // fraction of the background colour in the pixel
    LD lost_depth = 0;   // weight of branches stopped at max_depth
    LD lost_cutoff = 0;  // weight of branches below the 1e-6 cut-off
  };

  DielectricReference(const render::RenderScene& rs, std::uint32_t max_depth) : max_depth_(max_depth) {
    const std::vector<accel::Shape>& shapes = rs.geometry().shapes();
    for (std::uint32_t i = 0; i < shapes.size(); ++i) {
      const render::MaterialF& m = rs.material(i);
      // Only clear dielectrics: anything else would need lights and local shading.
      REQUIRE(m.transparency == 1.0f);
      REQUIRE(m.reflectivity == 0.0f);
      REQUIRE(shapes[i].type != accel::ShapeType::kPlane);
      shapes_.push_back(shapes[i]);
      iors_.push_back(m.ior);
    }
  }

  Result trace_camera_ray(const math::Ray& ray) const {
    Result out;
    trace(ld(ray.o), math::normalize(ld(ray.d)), 0, 0, 1, {}, out);
    return out;
  }

 private:
  // Renderer's kMinBranchWeight, as the float it compares against.
  static constexpr LD kCutoff = LD(1e-6f);
  // Hits closer than this to the origin are the surface being left (the reference spawns from
  // the exact point, without offset). All gaps in the scenes here are >= 1e-5.
  static constexpr LD kSelf = 1e-10;

  bool nearest(const V3L& o, const V3L& d, LD t_min, LD& t_hit, std::uint32_t& id, V3L& normal) const {
    t_hit = std::numeric_limits<LD>::infinity();
    for (std::uint32_t i = 0; i < shapes_.size(); ++i) {
      const accel::Shape& s = shapes_[i];
      if (s.type == accel::ShapeType::kSphere) {
        const V3L c = ld(s.sphere.center);
        const LD r = s.sphere.radius;
        const LineSphere ls = line_sphere(o, d, c, r);
        if (!ls.hit) continue;
        for (const LD t : {ls.t0, ls.t1}) {
          if (t > t_min && t < t_hit) {
            t_hit = t;
            id = i;
            normal = (o + d * t - c) / r;
            break;
          }
        }
      } else {
        const V3L lo = ld(s.box.lo), hi = ld(s.box.hi);
        LD t_near = -std::numeric_limits<LD>::infinity(), t_far = std::numeric_limits<LD>::infinity();
        int near_axis = -1, far_axis = -1;
        for (int a = 0; a < 3; ++a) {
          if (d[a] == 0) continue;  // the cameras here never produce an axis-parallel ray
          LD ta = (lo[a] - o[a]) / d[a], tb = (hi[a] - o[a]) / d[a];
          if (ta > tb) std::swap(ta, tb);
          if (ta > t_near) {
            t_near = ta;
            near_axis = a;
          }
          if (tb < t_far) {
            t_far = tb;
            far_axis = a;
          }
        }
        if (!(t_near <= t_far)) continue;
        if (t_near > t_min && t_near < t_hit) {
          t_hit = t_near;
          id = i;
          normal = {0, 0, 0};
          normal[near_axis] = d[near_axis] > 0 ? -1 : 1;
        } else if (t_near <= t_min && t_far > t_min && t_far < t_hit) {
          t_hit = t_far;
          id = i;
          normal = {0, 0, 0};
          normal[far_axis] = d[far_axis] > 0 ? 1 : -1;
        }
      }
    }
    return std::isfinite(t_hit);
  }

  LD current_ior(const std::vector<std::uint32_t>& media) const { return media.empty() ? 1 : iors_[media.back()]; }

  void trace(V3L o, const V3L& d, LD t_min, std::uint32_t depth, LD weight, std::vector<std::uint32_t> media,
             Result& out) const {
    for (;;) {
      LD t;
      std::uint32_t id = 0;
      V3L n;
      if (!nearest(o, d, t_min, t, id, n)) {
        out.background += weight;
        return;
      }
      const bool entering = std::find(media.begin(), media.end(), id) == media.end();
      std::vector<std::uint32_t> inside = media;
      if (entering) {
        inside.push_back(id);
      } else {
        inside.erase(std::find(inside.begin(), inside.end(), id));
      }
      const float n_from = float(current_ior(media));
      const float n_to = entering ? iors_[id] : float(current_ior(inside));
      if (n_to == n_from) {  // index-matched: the same ray goes on
        t_min = t;
        media = std::move(inside);
        continue;
      }
      if (depth >= max_depth_) {
        out.lost_depth += weight;
        return;
      }
      const LD eta = LD(n_to) / LD(n_from);
      const V3L p = o + d * t;
      const V3L wo = -d;
      const V3L nf = math::dot(wo, n) >= 0 ? n : -n;
      const LD cos_i = std::clamp(math::dot(wo, nf), LD(0), LD(1));
      const LD sin2_t = (1 - cos_i * cos_i) / (eta * eta);
      LD fresnel = 1;
      V3L wt;
      const bool refracts = sin2_t < 1;
      if (refracts) {
        const LD cos_t = std::sqrt(1 - sin2_t);
        const LD r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
        const LD r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
        fresnel = (r_parl * r_parl + r_perp * r_perp) / 2;
        wt = math::normalize(wo * LD(-1) / eta + nf * (cos_i / eta - cos_t));
      }
      const LD w_reflect = weight * fresnel;
      if (w_reflect >= kCutoff) {
        trace(p, math::normalize(d - nf * (2 * math::dot(d, nf))), kSelf, depth + 1, w_reflect, media, out);
      } else {
        out.lost_cutoff += w_reflect;
      }
      const LD w_refract = weight * (1 - fresnel);
      if (refracts && w_refract >= kCutoff) {
        trace(p, wt, kSelf, depth + 1, w_refract, inside, out);
      } else {
        out.lost_cutoff += w_refract;
      }
      return;
    }
  }

  std::vector<accel::Shape> shapes_;
  std::vector<float> iors_;
  std::uint32_t max_depth_;
};

// Agreement of the float renderer with the long-double reference, in units of the background:
// float directions, Fresnel terms and weights carried through up to 64 interfaces (measured
// at most 2e-5, on the 64-deep chains of the grazing cube view).
constexpr LD kReferenceTolerance = 1e-4;
// Loss allowed in the cube's corner view (test 4), where no path comes near max_depth: the
// chain of internal reflections ends once its weight falls under the 1e-6 cut-off, and the
// leaves it drops on the way are under 1e-6 each; a few 1e-6 in all (1.2e-6 measured), so a
// single lost exit (>= 1e-4 of the pixel here) or a missed Fresnel split cannot hide.
constexpr double kCubeLossTolerance = 1e-5;

// Renders a clear-dielectric scene under a uniform background and compares every pixel with the
// long-double reference. `max_diff` is in units of the background.
struct ReferenceComparison {
  EnergyStats energy;
  LD max_diff = 0;  // max over pixels and channels of |L / B - reference|
  LD max_lost = 0;  // max over pixels of the weight the reference drops
  LD max_lost_depth = 0;
  LD max_bookkeeping = 0;  // max |background + lost - 1| of the reference itself
  std::uint32_t over_tolerance = 0;
  render::TraceStats stats;
};

ReferenceComparison compare_with_reference(const scene::SceneDesc& desc, LD tolerance) {
  const render::RenderScene rs = render::RenderScene::build(desc);
  const render::Tile tile = render_image(rs, desc.render);
  const DielectricReference reference(rs, desc.render.max_depth);
  ReferenceComparison out;
  out.energy = energy_of(tile, desc.render.background);
  out.stats = tile.stats;
  for (std::uint32_t y = 0; y < desc.render.height; ++y) {
    for (std::uint32_t x = 0; x < desc.render.width; ++x) {
      const DielectricReference::Result ref = reference.trace_camera_ray(pixel_ray(rs, desc.render, x, y));
      const LD lost = ref.lost_depth + ref.lost_cutoff;
      out.max_lost = std::max(out.max_lost, lost);
      out.max_lost_depth = std::max(out.max_lost_depth, ref.lost_depth);
      out.max_bookkeeping = std::max(out.max_bookkeeping, std::abs(ref.background + lost - 1));
      LD diff = 0;
      for (int c = 0; c < 3; ++c) {
        diff = std::max(diff, std::abs(LD(tile_pixel(tile, x, y)[c]) / LD(desc.render.background[c]) - ref.background));
      }
      out.max_diff = std::max(out.max_diff, diff);
      out.over_tolerance += !(diff <= tolerance);
    }
  }
  return out;
}

// Checks a scene of clear dielectrics under a uniform background: no NaN or Inf, no energy
// created, every pixel equal to the long-double reference, and, when loss_tolerance >= 0,
// nothing lost beyond it (energy conservation of Fresnel splitting: F + (1 - F) = 1 at every
// interface, so only the renderer's two cut-offs can lose light).
void check_clear_dielectrics(const char* name, const scene::SceneDesc& desc, double loss_tolerance) {
  CAPTURE(name);
  const ReferenceComparison r = compare_with_reference(desc, kReferenceTolerance);
  report(
      "[dielectric] %-22s L/B in [%.8f, %.8f]; reference drops up to %.3Le (max_depth %.3Le), bookkeeping "
      "%.1Le; max |L/B - ref| %.3Le, %u px over %.0Le; nan %llu inf %llu\n",
      name, r.energy.min_ratio, r.energy.max_ratio, r.max_lost, r.max_lost_depth, r.max_bookkeeping, r.max_diff,
      r.over_tolerance, kReferenceTolerance, static_cast<unsigned long long>(r.stats.nan_samples),
      static_cast<unsigned long long>(r.stats.inf_samples));
  CHECK(r.stats.nan_samples == 0);
  CHECK(r.stats.inf_samples == 0);
  CHECK(r.energy.non_finite == 0);
  CHECK(r.energy.max_ratio <= 1 + kEnergyGainTolerance);
  REQUIRE(r.max_bookkeeping < 1e-12);  // the reference accounts for every branch
  CHECK(r.over_tolerance == 0);
  if (loss_tolerance >= 0) {
    CHECK(r.max_lost <= loss_tolerance);
    CHECK(r.energy.min_ratio >= 1 - loss_tolerance);
  }
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
  // 1e-4 rad: 8x the error of a local-frame hit point at 1e6 (1.2e-5 rad in the accuracy
  // notes), 100x below what o + t d gives at 1e5 (0.8 degrees).
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

    const render::RenderScene rs = render::RenderScene::build(desc);
    const render::Tile tile = render_image(rs, desc.render);
    CHECK(tile.stats.nan_samples == 0);
    CHECK(tile.stats.inf_samples == 0);

    const accel::SphereShape& s = rs.geometry().shapes()[0].sphere;
    const V3L center = ld(s.center);
    const LD radius = s.radius;
    const V3L light = ld(rs.lights()[0].position);
    const LD intensity = rs.lights()[0].intensity.x;
    const LD albedo = rs.material(0).color.x;

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

      const accel::PlaneShape& pl = rs.geometry().shapes()[0].plane;
      const accel::SphereShape& sp = rs.geometry().shapes()[1].sphere;
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
// 3. Grazing rays at a sphere's silhouette.
//
// Families of rays with one direction (no y component) whose origins step by single ulps in y
// across the tangent: the exact distance h from the centre to the line then grows strictly with
// the step, so the hit/miss answer of Geometry::intersect must switch exactly once, from hit to
// miss. Every ray is also traced through the whole integrator with glass, mirror and diffuse
// materials: no NaN or Inf may come out, and clear glass under a uniform background may not
// create energy.
TEST_CASE("grazing rays at a sphere's silhouette: monotone hit/miss and finite radiance", "[hard][grazing]") {
  struct Family {
    const char* name;
    Vec3d center;
    double radius;
    double angle_deg;  // direction in the xz-plane
    double back;       // distance of the ray origin from the tangent point, along the ray
  };
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
      scene::SceneDesc desc = make_desc({0, 0, 0}, {0, 0, -1}, 45.0, 16);
      desc.render.background = background;
      desc.render.max_depth = 64;
      desc.objects.push_back(sphere(fam.center, fam.radius, glass(1.5)));
      const render::RenderScene glass_scene = render::RenderScene::build(desc);
      desc.objects[0].material = mirror(1.0);
      const render::RenderScene mirror_scene = render::RenderScene::build(desc);
      desc.objects[0].material = diffuse();
      desc.objects[0].material.specular = 0.5;
      desc.lights.push_back(point_light(fam.center + Vec3d{0, 3, 1} * fam.radius, 10.0 * fam.radius * fam.radius));
      const render::RenderScene diffuse_scene = render::RenderScene::build(desc);
      const render::TraceLimits limits{Vec3f(background), 64};

      const accel::Geometry& geometry = glass_scene.geometry();
      const accel::SphereShape& s = geometry.shapes()[0].sphere;
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
      // Origins' y, one ulp apart, ordered outwards.
      std::vector<float> ys(2 * kSteps + 1);
      ys[kSteps] = oy_tangent;
      const float outwards = side * std::numeric_limits<float>::infinity();
      for (int j = 1; j <= kSteps; ++j) {
        ys[kSteps + j] = std::nextafter(ys[kSteps + j - 1], outwards);
        ys[kSteps - j] = std::nextafter(ys[kSteps - j + 1], -outwards);
      }
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

// =============================================================================================
// 4. Total internal reflection in a glass cube (ior 1.5, transparency 1).
//
// In a cube of index n > sqrt(2), light that enters through one face can leave only through
// that face or the opposite one: every side face meets it beyond the critical angle. A lit red
// wall beside the cube, level with it, is therefore invisible through the top face: the red
// channel of every pixel that enters through the top must be exactly 0 (background and glass
// carry no red). With n = 1.3 < sqrt(2) the same view shows the wall, which proves the check can
// fail. Then, with a uniform background and nothing else, Fresnel splitting conserves energy:
// the pixel equals the background to within the energy dropped at the 1e-6 branch cut-off and
// the depth limit, and never exceeds it beyond rounding.
TEST_CASE("glass cube: total internal reflection and energy conservation", "[hard][tir]") {
  const Vec3d background{0.25, 0.5, 1.0};

  SECTION("light entering the top face cannot leave through a side face") {
    for (const double ior : {1.5, 1.3}) {
      CAPTURE(ior);
      scene::SceneDesc desc = make_desc({-3, 1.5, 0}, {0.2, 1, 0}, 10.0, 64);
      desc.render.background = {0, 0.5, 1};
      desc.render.max_depth = 64;
      desc.objects.push_back(box({-1, -1, -1}, {1, 1, 1}, glass(ior)));
      desc.objects.push_back(box({1.5, -1, -3}, {2, 1, 3}, diffuse({1, 0, 0})));
      desc.lights.push_back(point_light({1.25, 0, 0}, 1.0));
      const render::RenderScene rs = render::RenderScene::build(desc);
      const render::Tile tile = render_image(rs, desc.render);
      CHECK(tile.stats.nan_samples == 0);
      CHECK(tile.stats.inf_samples == 0);
      const accel::BoxShape& cube = rs.geometry().shapes()[0].box;
      std::uint32_t top = 0, red = 0, gain = 0;
      for (std::uint32_t y = 0; y < 64; ++y) {
        for (std::uint32_t x = 0; x < 64; ++x) {
          const math::Ray ray = pixel_ray(rs, desc.render, x, y);
          const LineBox lb = line_box(ld(ray.o), ld(ray.d), ld(cube.lo), ld(cube.hi));
          if (!lb.hit || lb.axis != 1 || lb.edge_distance < 1e-4) continue;
          ++top;
          const float* px = tile_pixel(tile, x, y);
          red += px[0] != 0.0f;
          gain += px[1] > 0.5f * (1 + kEnergyGainTolerance) || px[2] > 1.0f * (1 + kEnergyGainTolerance);
        }
      }
      report("[tir] ior %.1f: %u pixels enter through the top face, %u of them see red\n", ior, top, red);
      REQUIRE(top > 1000);
      CHECK(gain == 0);
      if (ior == 1.5) {
        CHECK(red == 0);
      } else {
        CHECK(red > 20);  // the control: below sqrt(2) the wall shows through
      }
    }
  }

  SECTION("uniform background, corner view: a clear cube returns the background") {
    // Seen from a corner, rays enter the three visible faces at 40-70 degrees, so inside they
    // meet the exit faces well below the critical angle (F < 0.2): the internal chain fades below
    // the 1e-6 cut-off within ~10 interfaces, far from max_depth.
    scene::SceneDesc desc = make_desc({4, 3.5, 5}, {0, 0, 0}, 40.0, 64);
    desc.render.background = background;
    desc.render.max_depth = 64;
    desc.objects.push_back(box({-1, -1, -1}, {1, 1, 1}, glass(1.5)));
    check_clear_dielectrics("cube, corner view", desc, kCubeLossTolerance);
  }

  SECTION("uniform background, grazing entry: near-critical chains are cut, never amplified") {
    // Entering almost parallel to the top face the inside angle approaches the critical one, F
    // approaches 1 and the chain of internal reflections outlives max_depth: energy is lost, as
    // much as the reference says, but never created.
    scene::SceneDesc desc = make_desc({-6, 1.05, 0.3}, {0, 1, 0}, 12.0, 64);
    desc.render.background = background;
    desc.render.max_depth = 64;
    desc.objects.push_back(box({-1, -1, -1}, {1, 1, 1}, glass(1.5)));
    check_clear_dielectrics("cube, grazing view", desc, -1);
  }
}

// =============================================================================================
// 5. Touching and nested glass spheres under a uniform background: no NaN or Inf, no energy
// created, every pixel equal to the long-double reference (which applies the same media-stack
// rules and cut-offs), and energy conserved up to what the cut-offs drop.
//
// Loss tolerance 1e-3 for spheres: reflections between spheres and inside thin shells branch
// the ray tree, every node can drop two branches just under 1e-6, and a pixel has up to a few
// hundred nodes (the 1e-5 glass skin: 2e-4 measured, all of it below the cut-off). The air bubble
// is the exception: light that totally reflects off the bubble can meet the outer surface beyond
// the critical angle and then circles inside it (a whispering-gallery orbit) until it happens to
// meet the bubble again, far past max_depth = 64. The renderer loses that light by design; the
// reference loses the same amount, which is what is checked there.
TEST_CASE("touching and nested glass spheres: finite and energy-conserving", "[hard][nested]") {
  const Vec3d background{0.25, 0.5, 1.0};
  constexpr double kSphereLossTolerance = 1e-3;
  auto check = [&](const char* name, const std::vector<scene::Object>& objects, Vec3d eye, double loss_tolerance) {
    scene::SceneDesc desc = make_desc(eye, {0, 0, 0}, 45.0, 64);
    desc.render.background = background;
    desc.render.max_depth = 64;
    desc.objects = objects;
    check_clear_dielectrics(name, desc, loss_tolerance);
  };

  SECTION("(a) two glass spheres touching at one point") {
    check("touching", {sphere({-1, 0, 0}, 1.0, glass(1.5)), sphere({1, 0, 0}, 1.0, glass(1.5))}, {0.3, 0.8, 5.5},
          kSphereLossTolerance);
  }
  SECTION("(c) an air bubble inside a glass sphere") {
    check("air bubble", {sphere({0, 0, 0}, 1.0, glass(1.5)), sphere({0.2, 0.1, 0}, 0.5, glass(1.0))}, {0.3, 0.8, 3.5},
          /* loss_tolerance = */ -1);
  }
  SECTION("(d) glass holding water, a 1e-5 thick glass skin") {
    check("glass + water", {sphere({0, 0, 0}, 1.0, glass(1.5)), sphere({0, 0, 0}, 1.0 - 1e-5, glass(1.33))},
          {0.3, 0.8, 3.5}, kSphereLossTolerance);
  }
}

// 5(b). A glass sphere holding a smaller glass sphere of the same ior: the inner surface is
// index-matched and must be invisible.
//
// A camera path that crosses the inner surface finds eta == 1 there and continues the very same
// ray (same origin, same direction, only t_min moves), so the hits it makes next are the hits the
// path makes without the inner sphere, to the bit. The comparison is therefore bitwise; any
// difference is a path that was bent, split or re-originated at an index-matched surface.
namespace {

scene::SceneDesc index_matched_scene(bool lit, bool with_inner, double inner_ior = 1.5) {
  scene::SceneDesc desc = make_desc({0.5, 2.2, 5}, {0, 0.9, 0}, 40.0, 64);
  desc.render.samples = 4;
  desc.render.max_depth = 16;
  desc.render.background = {0.25, 0.5, 1.0};
  desc.objects.push_back(sphere({0, 1, 0}, 1.0, glass(1.5)));
  if (lit) {
    desc.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.8, 0.7, 0.6})));
    desc.objects.push_back(box({-3, 0, -3}, {3, 3, -2.5}, diffuse({0.3, 0.6, 0.3})));
    desc.lights.push_back(point_light({-2, 5, 4}, 40.0));
  } else {
    // No light, so no shadow rays: coloured mirrors give the refracted paths something to show.
    scene::Material floor = mirror(0.5);
    floor.color = {0.9, 0.6, 0.3};
    desc.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, floor));
    scene::Material wall = mirror(0.8);
    wall.color = {0.3, 0.9, 0.4};
    desc.objects.push_back(box({-3, 0, -3}, {0.3, 3, -2.5}, wall));
  }
  if (with_inner) desc.objects.push_back(sphere({0.2, 1.1, 0.1}, 0.5, glass(inner_ior)));
  return desc;
}

std::uint32_t index_matched_differences(bool lit, double inner_ior = 1.5) {
  const scene::SceneDesc without = index_matched_scene(lit, /* with_inner = */ false);
  const scene::SceneDesc with = index_matched_scene(lit, /* with_inner = */ true, inner_ior);
  const render::Tile a = render_image(render::RenderScene::build(without), without.render);
  const render::Tile b = render_image(render::RenderScene::build(with), with.render);
  CHECK(b.stats.nan_samples == 0);
  CHECK(b.stats.inf_samples == 0);
  std::uint32_t differ = 0;
  double max_diff = 0;
  for (std::size_t i = 0; i < a.rgb.size(); i += 3) {
    differ += std::memcmp(&a.rgb[i], &b.rgb[i], 3 * sizeof(float)) != 0;
    for (int c = 0; c < 3; ++c) max_diff = std::max(max_diff, double(std::abs(a.rgb[i + c] - b.rgb[i + c])));
  }
  report("[nested] inner sphere of ior %.2f in ior 1.5, %s: %u of %zu pixels differ (max abs diff %.3g)\n", inner_ior,
         lit ? "lit diffuse floor (shadow rays cross it)" : "mirrors only (camera paths)", differ, a.rgb.size() / 3,
         max_diff);
  return differ;
}

}  // namespace

TEST_CASE("index-matched sphere inside glass: camera paths do not see it, bitwise", "[hard][nested]") {
  CHECK(index_matched_differences(/* lit = */ false) == 0);
  // Control: an inner sphere of slightly different index shows, so the view can tell.
  CHECK(index_matched_differences(/* lit = */ false, /* inner_ior = */ 1.45) > 200);
}

// Shadow rays follow the same media stack as camera paths, so crossing an index-matched inner
// sphere is an eta == 1 interface and changes nothing.
TEST_CASE("index-matched sphere inside glass casts no shadow of its own", "[hard][nested]") {
  CHECK(index_matched_differences(/* lit = */ true) == 0);
}

// =============================================================================================
// 6. A clear sphere of ior exactly 1 is invisible, bitwise.
//
// eta == 1 continues the same ray past the surface and shadow rays pass it with weight exactly
// 1, so nothing downstream can tell it is there: the image must be bitwise the image of the
// scene without it, whatever else is around. The scene has shadows (it straddles the floor and
// sits between the light and other objects), reflections (a mirror sees it), refraction (a glass
// sphere behind and a small glass sphere inside it), a diffuse sphere inside it, and 4 jittered
// samples per pixel rendered on 2 threads.
TEST_CASE("a clear sphere of ior 1 is invisible, bitwise", "[hard][invisible]") {
  scene::SceneDesc desc = make_desc({0, 2.5, 7}, {0, 0.8, 0}, 45.0, 64);
  desc.render.samples = 4;
  desc.render.max_depth = 12;
  desc.render.background = {0.1, 0.15, 0.3};
  desc.render.seed = 7;
  desc.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, diffuse({0.8, 0.8, 0.8})));
  desc.objects.push_back(sphere({-2.2, 1, -1.5}, 1.0, mirror(0.9)));
  scene::Material tinted_glass = glass(1.5, 0.9);
  tinted_glass.diffuse = 1.0;  // 10 % local shading, so shadow rays through it matter too
  tinted_glass.specular = 0.5;
  desc.objects.push_back(sphere({2.0, 0.8, -1.0}, 0.8, tinted_glass));
  desc.objects.push_back(box({-0.5, 0, -4}, {0.5, 2.5, -3}, diffuse({0.7, 0.3, 0.2})));
  desc.objects.push_back(sphere({0.3, 0.5, 0.2}, 0.3, diffuse({0.2, 0.4, 0.9})));  // inside the clear sphere
  desc.objects.push_back(sphere({-0.4, 1.2, 0.1}, 0.25, glass(1.5)));              // inside the clear sphere
  desc.lights.push_back(point_light({1, 6, 3}, 50.0));
  desc.lights.push_back(point_light({-4, 3, 4}, 20.0));

  scene::SceneDesc with_clear = desc;
  scene::Material clear = glass(1.0);
  clear.diffuse = 1.0;  // has no effect: 1 - reflectivity - transparency = 0
  clear.specular = 0.3;
  with_clear.objects.push_back(sphere({0, 0.8, 0.3}, 1.2, clear));  // dips below the floor

  render::LocalOptions options;
  options.threads = 2;
  options.tile_size = 16;
  const render::LocalResult a = render::render_local(render::RenderScene::build(desc), desc.render, options);
  const render::LocalResult b =
      render::render_local(render::RenderScene::build(with_clear), with_clear.render, options);
  REQUIRE(a.image.rgb.size() == b.image.rgb.size());
  CHECK(b.stats.nan_samples == 0);
  CHECK(b.stats.inf_samples == 0);
  std::uint32_t differ = 0;
  for (std::size_t i = 0; i < a.image.rgb.size(); i += 3) {
    differ += std::memcmp(&a.image.rgb[i], &b.image.rgb[i], 3 * sizeof(float)) != 0;
  }
  report("[invisible] ior-1 sphere: %u of %zu pixels differ; rays %llu without, %llu with\n", differ,
         a.image.rgb.size() / 3, static_cast<unsigned long long>(a.stats.rays),
         static_cast<unsigned long long>(b.stats.rays));
  CHECK(b.stats.rays > a.stats.rays);  // the clear sphere really was met
  CHECK(differ == 0);
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
    const render::RenderScene rs = render::RenderScene::build(desc);
    const render::Tile tile = render_image(rs, desc.render);
    CHECK(tile.stats.nan_samples == 0);
    CHECK(tile.stats.inf_samples == 0);
    const accel::SphereShape& s = rs.geometry().shapes()[0].sphere;
    const V3L c = ld(s.center);
    const LD r = s.radius;
    const V3L light = ld(rs.lights()[0].position);
    const LD intensity = rs.lights()[0].intensity.x;
    const LD albedo = rs.material(0).color.x;

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
// The demo scenes in scenes/hard/ load without errors, and the invisible-sphere demo keeps its
// promise through the file format too: without its last object (the clear ior-1 sphere) it
// renders the same bits.
TEST_CASE("hard-case demo scenes load, and the ior-1 demo sphere is invisible", "[hard][scenes]") {
  const std::string dir = std::string(DTRACED_SOURCE_DIR) + "/scenes/hard/";
  for (const char* name :
       {"far_sphere.json", "grazing_light.json", "glass_cube_tir.json", "nested_glass.json", "invisible_ior1.json"}) {
    CAPTURE(name);
    const scene::LoadResult loaded = scene::load_scene_file(dir + name);
    INFO(scene::format_errors(loaded.errors));
    CHECK(loaded.ok());
    CHECK(loaded.warnings.empty());
  }
  const scene::LoadResult loaded = scene::load_scene_file(dir + "invisible_ior1.json");
  REQUIRE(loaded.ok());
  scene::SceneDesc with_clear = *loaded.scene;
  with_clear.render.width = with_clear.render.height = 64;
  REQUIRE(!with_clear.objects.empty());
  const scene::Material& clear = with_clear.objects.back().material;
  REQUIRE(clear.ior == 1.0);
  REQUIRE(clear.transparency == 1.0);
  scene::SceneDesc without = with_clear;
  without.objects.pop_back();
  const render::Tile a = render_image(render::RenderScene::build(without), without.render);
  const render::Tile b = render_image(render::RenderScene::build(with_clear), with_clear.render);
  CHECK(std::memcmp(a.rgb.data(), b.rgb.data(), a.rgb.size() * sizeof(float)) == 0);
}

}  // namespace dtraced
