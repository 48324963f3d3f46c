// Definitions of the hard-case tests' shared references (test_hard_cases.h).
#include <algorithm>
#include <cmath>
#include <cstdarg>
#include <cstdio>
#include <cstdlib>

#include <catch2/catch.hpp>

#include "test_hard_cases.h"

namespace dtraced::testing {

using math::Vec3d;
using math::Vec3f;

void report(const char* format, ...) {
  static const bool verbose = std::getenv("DTRACED_HARD_VERBOSE") != nullptr;
  if (!verbose) return;
  va_list args;
  va_start(args, format);
  std::vfprintf(stdout, format, args);
  va_end(args);
  std::fflush(stdout);
}

scene::SceneDesc make_desc(math::Vec3d eye, math::Vec3d look_at, double fov_deg, std::uint32_t side) {
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

double fov_for(double half_extent, double distance) {
  return 2.0 * std::atan(half_extent / distance) * 180.0 / std::numbers::pi;
}

math::Ray pixel_ray(const render::RenderScene& rs, const scene::RenderSettings& s, std::uint32_t x, std::uint32_t y) {
  return rs.camera().generate(x + 0.5, y + 0.5, s.width, s.height);
}

render::Tile render_image(const render::RenderScene& rs, const scene::RenderSettings& s) {
  return render::render_tile(rs, s, {0, 0, s.width, s.height});
}

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

LD line_plane(const V3L& o, const V3L& d, const V3L& p, const V3L& n) { return math::dot(p - o, n) / math::dot(d, n); }

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

LD segment_point_distance(const V3L& a, const V3L& b, const V3L& c) {
  const V3L ab = b - a;
  const LD s = std::clamp(math::dot(c - a, ab) / math::dot(ab, ab), LD(0), LD(1));
  return math::length(c - (a + ab * s));
}

LD angle_between(const V3L& a, const V3L& b) { return std::atan2(math::length(math::cross(a, b)), math::dot(a, b)); }

LD lambert(LD albedo, LD intensity, const V3L& p, const V3L& n, const V3L& light) {
  const V3L to_l = light - p;
  const LD dist2 = math::dot(to_l, to_l);
  const LD cos_l = math::dot(n, to_l) / std::sqrt(dist2);
  return albedo / kPi * intensity * std::max(LD(0), cos_l) / dist2;
}

LD cos_to_light(const V3L& p, const V3L& n, const V3L& light) { return math::dot(n, math::normalize(light - p)); }

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

namespace {
// The renderer's kMinBranchWeight, as the float it compares against.
constexpr LD kCutoff = LD(1e-6f);
// Hits closer than this to the origin are the surface being left (the reference spawns from
// the exact point, without offset). All gaps in the scenes here are >= 1e-5.
constexpr LD kSelf = 1e-10;
}  // namespace

DielectricReference::DielectricReference(const render::RenderScene& rs, std::uint32_t max_depth)
    : max_depth_(max_depth) {
  const accel::LayeredGeometry& geometry = rs.geometry();
  for (std::uint32_t i = 0; i < geometry.shape_count(); ++i) {
    const accel::Shape& shape = geometry.shape(i);
    const render::MaterialF& m = rs.material(i);
    // Only clear dielectrics: anything else would need lights and local shading.
    REQUIRE(m.transparency == 1.0f);
    REQUIRE(m.reflectivity == 0.0f);
    REQUIRE(shape.type != accel::ShapeType::kPlane);
    shapes_.push_back(shape);
    iors_.push_back(m.ior);
  }
}

DielectricReference::Result DielectricReference::trace_camera_ray(const math::Ray& ray,
                                                                  const std::vector<std::uint32_t>& media) const {
  Result out;
  trace(ld(ray.o), math::normalize(ld(ray.d)), 0, 0, 1, media, out);
  return out;
}

bool DielectricReference::nearest(const V3L& o, const V3L& d, LD t_min, LD& t_hit, std::uint32_t& id,
                                  V3L& normal) const {
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

LD DielectricReference::current_ior(const std::vector<std::uint32_t>& media) const {
  return media.empty() ? 1 : iors_[media.back()];
}

void DielectricReference::trace(V3L o, const V3L& d, LD t_min, std::uint32_t depth, LD weight,
                                std::vector<std::uint32_t> media, Result& out) const {
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

ReferenceComparison compare_with_reference(const scene::SceneDesc& desc, LD tolerance,
                                           const std::vector<std::uint32_t>& camera_media) {
  const render::RenderScene rs = render::RenderScene::build(desc);
  const render::Tile tile = render_image(rs, desc.render);
  const DielectricReference reference(rs, desc.render.max_depth);
  ReferenceComparison out;
  out.energy = energy_of(tile, desc.render.background);
  out.stats = tile.stats;
  for (std::uint32_t y = 0; y < desc.render.height; ++y) {
    for (std::uint32_t x = 0; x < desc.render.width; ++x) {
      const DielectricReference::Result ref =
          reference.trace_camera_ray(pixel_ray(rs, desc.render, x, y), camera_media);
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
void check_clear_dielectrics(const char* name, const scene::SceneDesc& desc, double loss_tolerance,
                             const std::vector<std::uint32_t>& camera_media) {
  CAPTURE(name);
  const ReferenceComparison r = compare_with_reference(desc, kReferenceTolerance, camera_media);
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

}  // namespace dtraced::testing
