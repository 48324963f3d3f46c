// dtraced::accel internal: the ray/shape and ray/box kernels shared by the BVH traversal
// (bvh.cpp) and the single-shape entry points (geometry.cpp). Not part of the public API; every
// function is pure and inline so the traversal loop can inline it.
//
// Conventions: a kernel returns the nearest ray parameter t > t_min as a float, or NaN on a miss,
// so callers can write `if (t < best)` and a miss (or any NaN that crept in) never counts.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "accel/geometry.h"
#include "math/float_util.h"

namespace dtraced::accel::detail {

inline constexpr float kInf = std::numeric_limits<float>::infinity();
inline constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// Far slab distances are multiplied by this (Ize 2013; pbrt-v4 Bounds3::IntersectP): it covers
// the rounding of (p - o) * inv_d on both the near and the far side, so a box the ray really
// crosses is never rejected.
inline constexpr float kFarScale = 1.0f + 2.0f * math::gamma(3);

// A ray with its per-ray constants: the inverse direction (a zero component gives +-inf with the
// sign of the zero) and, per axis, the index into a 6-float [lo, hi] array of the near and far
// slab coordinates.
struct RayPre {
  float o[3];
  float d[3];
  float inv_d[3];
  std::uint32_t near_idx[3];
  std::uint32_t far_idx[3];
  std::uint32_t neg[3];  // 1 where the direction's sign bit is set
};

inline RayPre precompute(const Ray& ray) {
  RayPre r;
  for (int i = 0; i < 3; ++i) {
    r.o[i] = ray.o[i];
    r.d[i] = ray.d[i];
    r.inv_d[i] = 1.0f / ray.d[i];
    r.neg[i] = std::signbit(ray.d[i]) ? 1u : 0u;
    r.near_idx[i] = r.neg[i] ? 3 + i : i;
    r.far_idx[i] = r.neg[i] ? i : 3 + i;
  }
  return r;
}

// The parametric span of the ray inside the box b = [lo.x, lo.y, lo.z, hi.x, hi.y, hi.z] on the
// three slabs, before clipping to the ray's interval. A NaN slab distance (0 * inf: the origin
// lies exactly on a slab plane and the direction has a zero component there) leaves the span
// unconstrained on that axis; the `>`/`<` comparisons below are written so that NaN is skipped.
struct Span {
  float t_near = -kInf;
  float t_far = kInf;  // not enlarged
  std::uint32_t near_axis = 0;
  std::uint32_t far_axis = 0;
};

inline Span slab_span(const float* b, const RayPre& r) {
  Span s;
  for (std::uint32_t i = 0; i < 3; ++i) {
    const float tn = (b[r.near_idx[i]] - r.o[i]) * r.inv_d[i];
    const float tf = (b[r.far_idx[i]] - r.o[i]) * r.inv_d[i];
    if (tn > s.t_near) {
      s.t_near = tn;
      s.near_axis = i;
    }
    if (tf < s.t_far) {
      s.t_far = tf;
      s.far_axis = i;
    }
  }
  return s;
}

// BVH node test: does the ray cross box b with some t in [t0, t1]? Same arithmetic as
// slab_span, so a node test can never be stricter than the test of a box shape inside it (both
// are monotone in the box coordinates). `<=` keeps flat boxes.
// Scaling the minimum far distance once equals scaling each (rounding is monotone).
inline bool node_hit(const float* b, const RayPre& r, float t0, float t1) {
  float tf_min = kInf;
  for (int i = 0; i < 3; ++i) {
    const float tn = (b[r.near_idx[i]] - r.o[i]) * r.inv_d[i];
    const float tf = (b[r.far_idx[i]] - r.o[i]) * r.inv_d[i];
    t0 = tn > t0 ? tn : t0;
    tf_min = tf < tf_min ? tf : tf_min;
  }
  tf_min *= kFarScale;
  return t0 <= (tf_min < t1 ? tf_min : t1);
}

// Which face of a box a hit is on.
struct BoxFace {
  std::uint32_t axis = 0;
  bool hi = false;  // the face at hi[axis] (outward normal +axis) rather than lo[axis]
};

// Box shape: nearest t > t_min where the ray meets the surface of b. A ray starting inside (or on
// the surface, heading in) gets the far face, so refracted rays leave glass boxes.
inline float box_t(const float* b, const RayPre& r, float t_min, BoxFace* face = nullptr) {
  const Span s = slab_span(b, r);
  if (!(s.t_near <= s.t_far * kFarScale)) return kNaN;
  if (s.t_near > t_min) {
    if (face) *face = {s.near_axis, r.neg[s.near_axis] != 0};
    return s.t_near;
  }
  if (s.t_far > t_min && s.t_far < kInf) {
    if (face) *face = {s.far_axis, r.neg[s.far_axis] == 0};
    return s.t_far;
  }
  return kNaN;
}

// Sphere roots in double (Ray Tracing Gems ch. 7 with the cross-product discriminant of the
// accuracy notes 1.3): f = o - c is exact in double for float inputs, the products of f x d lose
// no bits that matter, and the Numerical-Recipes form q = -(b + sign(b) sqrt(disc)) avoids the
// cancellation of -b - sqrt(disc). The direction need not be exactly unit length: with
// a = |d|^2 the quadratic is a t^2 + 2 b t + c with disc/4 = a r^2 - |f x d|^2.
struct SphereRoots {
  double f[3];    // o - c
  double t0, t1;  // t0 <= t1 unless one is NaN
};

inline bool sphere_roots(const float* s, const RayPre& r, SphereRoots& out) {
  const double fx = double(r.o[0]) - double(s[0]);
  const double fy = double(r.o[1]) - double(s[1]);
  const double fz = double(r.o[2]) - double(s[2]);
  const double dx = r.d[0], dy = r.d[1], dz = r.d[2];
  const double rr = double(s[3]) * double(s[3]);
  const double cx = fy * dz - fz * dy;
  const double cy = fz * dx - fx * dz;
  const double cz = fx * dy - fy * dx;
  const double a = dx * dx + dy * dy + dz * dz;
  const double disc = a * rr - (cx * cx + cy * cy + cz * cz);
  if (!(disc >= 0.0)) return false;
  const double b = fx * dx + fy * dy + fz * dz;
  const double c = (fx * fx + fy * fy + fz * fz) - rr;
  const double q = -(b + std::copysign(std::sqrt(disc), b));
  double t0 = c / q;
  double t1 = q / a;
  if (t0 > t1) std::swap(t0, t1);
  out = {{fx, fy, fz}, t0, t1};
  return true;
}

// Sphere s = [cx, cy, cz, radius]: nearest root whose float value is finite and > t_min (the far
// root when the near one is <= t_min: rays from inside). `root` receives 0 or 1.
inline float sphere_t(const float* s, const RayPre& r, float t_min, SphereRoots* roots = nullptr, int* root = nullptr) {
  SphereRoots sr;
  if (!sphere_roots(s, r, sr)) return kNaN;
  if (roots) *roots = sr;
  const float t0 = float(sr.t0);
  if (t0 > t_min && t0 < kInf) {
    if (root) *root = 0;
    return t0;
  }
  const float t1 = float(sr.t1);
  if (t1 > t_min && t1 < kInf) {
    if (root) *root = 1;
    return t1;
  }
  return kNaN;
}

// Plane through `point` with normal n: t = dot(point - o, n) / dot(d, n), in float.
inline float plane_t(const PlaneShape& pl, const RayPre& r, float t_min) {
  const float dn = r.d[0] * pl.normal.x + r.d[1] * pl.normal.y + r.d[2] * pl.normal.z;
  if (dn == 0.0f) return kNaN;
  const float num =
      (pl.point.x - r.o[0]) * pl.normal.x + (pl.point.y - r.o[1]) * pl.normal.y + (pl.point.z - r.o[2]) * pl.normal.z;
  const float t = num / dn;
  if (!(t > t_min && t < kInf)) return kNaN;
  return t;
}

// Full hit record (p, n, p_error) for a shape already known to be hit at t; computed once per
// query, for the final nearest hit only. Defined in geometry.cpp.
void finish_hit(const Shape& shape, std::uint32_t id, const Ray& ray, const RayPre& r, float t, Hit& hit);

bool shape_is_valid(const Shape& shape);

}  // namespace dtraced::accel::detail
