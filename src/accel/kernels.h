// dtraced::accel internal: the ray/shape and ray/box kernels shared by the BVH traversal
// (bvh.cpp) and the single-shape entry points (geometry.cpp). Not part of the public API; every
// function is pure and inline so the traversal loop can inline it.
//
// Conventions: a kernel returns the nearest ray parameter t > t_min as a float, or NaN on a miss,
// so callers can write `if (t < best)` and a miss (or any NaN that crept in) never counts.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>
#include <vector>

#include "accel/geometry.h"
#include "math/float_util.h"

namespace dtraced::accel::detail {

inline constexpr float kInf = std::numeric_limits<float>::infinity();
inline constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

// Far slab distances are multiplied by this (Ize 2013; pbrt-v4 Bounds3::IntersectP): it covers
// the rounding of (p - o) * inv_d on both the near and the far side, so a box the ray really
// crosses is never rejected.
inline constexpr float kFarScale = 1.0f + 2.0f * math::gamma(3);

// The part of a sphere hit's error bound that comes from double arithmetic, per unit of
// |local point| + |centre| on each axis. The point is computed in double, so its bound is made of
// double roundings (pbrt-v4's gamma(5) |p| is the bound of the same steps in float, which for a
// sphere of radius 1e6 is 0.3: shadow rays then start 0.3 above a ground sphere and small objects
// lose their shadows). Re-projecting the local point onto the sphere, pl * (r / |pl|), leaves each
// coordinate within gamma_d(5) |pl_i| of a point exactly on it (pbrt-v4's analysis, with double's
// epsilon); adding the centre rounds once more, eps_d (|c_i| + |pl_i|). An origin offset by the
// bound must also be seen as outside (or inside) by the next ray's own sphere test, whose
// c = |f|^2 - r^2 carries about 2.5 eps_d r of radial uncertainty (f = o - c rounded, three
// squares and two sums); the offset along n is at least the bound times r / (|pl| + |c|) <= 1
// per axis, so 6 + 3 roundings are needed. gamma_d(16) leaves room for rounding the bound itself.
// Rounding the point to float is the separate gamma(1) |p_i| term.
inline constexpr double kSphereDoubleError = math::gamma_d(16);

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
  // Watertight triangle test (Woop, Benthin, Wald 2013): kz is the axis of the direction's
  // largest magnitude, kx and ky the other two (swapped when d[kz] < 0 to keep the winding), and
  // the shear that maps the ray onto +z: x' = x - sx z, y' = y - sy z, z' = sz z.
  std::uint32_t kx, ky, kz;
  float sx, sy, sz;
};

inline void set_shear(RayPre& r) {
  const float ax = std::abs(r.d[0]), ay = std::abs(r.d[1]), az = std::abs(r.d[2]);
  r.kz = ax > ay ? (ax > az ? 0u : 2u) : (ay > az ? 1u : 2u);
  r.kx = r.kz == 2 ? 0u : r.kz + 1;
  r.ky = r.kx == 2 ? 0u : r.kx + 1;
  if (r.d[r.kz] < 0.0f) std::swap(r.kx, r.ky);
  r.sx = r.d[r.kx] / r.d[r.kz];
  r.sy = r.d[r.ky] / r.d[r.kz];
  r.sz = 1.0f / r.d[r.kz];
}

// `shear`: also the triangle test's constants (three divisions), needed only where triangles
// may be tested or finished.
inline RayPre precompute(const Ray& ray, bool shear = true) {
  RayPre r;
  for (int i = 0; i < 3; ++i) {
    r.o[i] = ray.o[i];
    r.d[i] = ray.d[i];
    r.inv_d[i] = 1.0f / ray.d[i];
    r.neg[i] = std::signbit(ray.d[i]) ? 1u : 0u;
    r.near_idx[i] = r.neg[i] ? 3 + i : i;
    r.far_idx[i] = r.neg[i] ? i : 3 + i;
  }
  if (shear) set_shear(r);
  return r;
}

// Only the origin and direction: all that the sphere and plane kernels (and their finish_hit)
// read. The rest is left zero; box and triangle tests need precompute().
inline RayPre precompute_od(const Ray& ray) {
  RayPre r{};
  for (int i = 0; i < 3; ++i) {
    r.o[i] = ray.o[i];
    r.d[i] = ray.d[i];
  }
  return r;
}

// What testing or finishing a shape of type `type` needs (same bits as precompute() for it).
inline RayPre precompute_for(const Ray& ray, ShapeType type) {
  switch (type) {
    case ShapeType::kSphere:
    case ShapeType::kPlane:
      return precompute_od(ray);
    case ShapeType::kBox:
      return precompute(ray, false);
    case ShapeType::kTriangle:
      break;
  }
  return precompute(ray, true);
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

// Sphere roots in double (Ray Tracing Gems ch. 7, with the discriminant taken from the cross
// product f x d rather than b^2 - c): f = o - c is exact in double for float inputs unless their
// magnitudes differ by more than 2^29 (then it is within half a double ulp, which the hit-point
// bound in geometry.cpp allows for), the products of f x d lose no bits that matter, and the
// Numerical-Recipes form q = -(b + sign(b) sqrt(disc)) avoids the cancellation of -b - sqrt(disc). The direction need
// not be exactly unit length: with a = |d|^2 the quadratic is a t^2 + 2 b t + c with disc/4 = a r^2 - |f x d|^2.
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

// Watertight ray/triangle test for vertices v = [a.xyz, b.xyz, c.xyz]. Every operation is a
// single IEEE float operation in a fixed order (the SIMD kernels repeat exactly this sequence),
// and the edge functions fall back to double when one is exactly zero, as the paper prescribes,
// so a ray through a shared edge or vertex hits at least one of the triangles sharing it.
struct TriangleUvw {
  double u, v, w, det;  // edge functions and their sum (all of one sign on a hit)
};

// pbrt-v4's conservative bound on the rounding error of a triangle's t (Pharr, Jakob, Humphreys,
// "Physically Based Rendering" 4th ed., 6.5.3), from the sheared vertices (x, y, z per vertex),
// the edge functions and their sum. A hit at t <= this bound may really be at t <= 0: a ray that
// starts on the triangle (a secondary ray leaving a flat mesh whose hit point is exact and so
// gets no offset) must not hit it again. Every operation is in a fixed order; the SIMD kernels
// repeat it exactly. T is float or double (the zero-edge-function fallback).
template <typename T>
inline T triangle_t_error(T sax, T say, T sbx, T sby, T scx, T scy, T saz, T sbz, T scz, T u, T v, T w, T det) {
  const T g2 = T(math::gamma(2)), g3 = T(math::gamma(3)), g5 = T(math::gamma(5));
  const T max_zt = std::max(std::max(std::abs(saz), std::abs(sbz)), std::abs(scz));
  const T max_xt = std::max(std::max(std::abs(sax), std::abs(sbx)), std::abs(scx));
  const T max_yt = std::max(std::max(std::abs(say), std::abs(sby)), std::abs(scy));
  const T delta_z = g3 * max_zt;
  const T delta_x = g5 * (max_xt + max_zt);
  const T delta_y = g5 * (max_yt + max_zt);
  const T delta_e = T(2) * (g2 * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
  const T max_e = std::max(std::max(std::abs(u), std::abs(v)), std::abs(w));
  return T(3) * (g3 * max_e * max_zt + delta_e * max_zt + delta_z * max_e) / std::abs(det);
}

// The rest of the test when a float edge function came out exactly zero: the products of floats
// are exact in double, so the signs of the edge functions are then right and a ray through a
// shared edge or vertex is not lost. Rare; the SIMD kernels call this same function for such lanes.
inline float triangle_t_double(float sax, float say, float sbx, float sby, float scx, float scy, float az, float bz,
                               float cz, const RayPre& r, float t_min, TriangleUvw* uvw) {
  const double u = double(scx) * double(sby) - double(scy) * double(sbx);
  const double v = double(sax) * double(scy) - double(say) * double(scx);
  const double w = double(sbx) * double(say) - double(sby) * double(sax);
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return kNaN;
  const double det = u + v + w;
  if (!(det != 0.0)) return kNaN;
  const double saz = double(r.sz) * az, sbz = double(r.sz) * bz, scz = double(r.sz) * cz;
  const double tt = u * saz + v * sbz + w * scz;
  const float t = float(tt / det);
  if (!(t > t_min && t < kInf)) return kNaN;
  if (!(tt / det > triangle_t_error<double>(sax, say, sbx, sby, scx, scy, saz, sbz, scz, u, v, w, det))) return kNaN;
  if (uvw) *uvw = {u, v, w, det};
  return t;
}

inline float triangle_t(const float* v, const RayPre& r, float t_min, TriangleUvw* uvw = nullptr) {
  const float ax = v[r.kx] - r.o[r.kx], ay = v[r.ky] - r.o[r.ky], az = v[r.kz] - r.o[r.kz];
  const float bx = v[3 + r.kx] - r.o[r.kx], by = v[3 + r.ky] - r.o[r.ky], bz = v[3 + r.kz] - r.o[r.kz];
  const float cx = v[6 + r.kx] - r.o[r.kx], cy = v[6 + r.ky] - r.o[r.ky], cz = v[6 + r.kz] - r.o[r.kz];
  const float sax = ax - r.sx * az, say = ay - r.sy * az;
  const float sbx = bx - r.sx * bz, sby = by - r.sy * bz;
  const float scx = cx - r.sx * cz, scy = cy - r.sy * cz;
  float u = scx * sby - scy * sbx;
  float vv = sax * scy - say * scx;
  float w = sbx * say - sby * sax;
  if (u == 0.0f || vv == 0.0f || w == 0.0f)
    return triangle_t_double(sax, say, sbx, sby, scx, scy, az, bz, cz, r, t_min, uvw);
  if ((u < 0.0f || vv < 0.0f || w < 0.0f) && (u > 0.0f || vv > 0.0f || w > 0.0f)) return kNaN;
  const float det = u + vv + w;
  if (!(det != 0.0f)) return kNaN;  // edge-on, degenerate, or NaN
  const float saz = r.sz * az, sbz = r.sz * bz, scz = r.sz * cz;
  const float tt = u * saz + vv * sbz + w * scz;
  const float t = tt / det;
  if (!(t > t_min && t < kInf)) return kNaN;
  if (!(t > triangle_t_error(sax, say, sbx, sby, scx, scy, saz, sbz, scz, u, vv, w, det))) return kNaN;
  if (uvw) *uvw = {u, vv, w, det};
  return t;
}

// Full hit record (p, n, p_error) for a shape already known to be hit at t; computed once per
// query, for the final nearest hit only. Defined in geometry.cpp.
void finish_hit(const Shape& shape, std::uint32_t id, const Ray& ray, const RayPre& r, float t, Hit& hit);

// finish_hit's triangle case from the edge functions the test itself produced (`uvw` exactly as
// triangle_t reports it for this ray, which the SIMD kernels keep for their nearest hit): the
// same bits without testing the triangle again or computing the ray's shear constants.
void finish_triangle_hit(const TriangleShape& tri, std::uint32_t id, float t, const TriangleUvw& uvw, Hit& hit);

// finish_hit for up to kPacketSize sphere hits at once (shapes[k] is a sphere hit by *rays[k] at
// ts[k] as the kernels found it), with the same bits; *hits[k] receives lane k's record.
void finish_sphere_hits(const Shape* const* shapes, const std::uint32_t* ids, const Ray* const* rays, const float* ts,
                        Hit* const* hits, int n);

bool shape_is_valid(const Shape& shape);

// Tiny scenes (Geometry::build's small-scene layout): no tree at all. Each group of `groups` (at
// most kNodeWidth; ids of valid bounded shapes of `shapes`) becomes one leaf of SoA blocks, a child
// of a single root node whose box for it is the union of its shapes' bounds: the SIMD kernels
// then test 8 rays (or one) against every shape of a group directly, after one node test that lets
// rays missing a group skip it. Geometry uses two groups: the ordinary shapes and the huge ones.
// Empty groups are left out; all empty gives an empty WideBvh. Defined in geometry.cpp.
WideBvh flat_wide(const std::vector<Shape>& shapes, const std::vector<std::vector<std::uint32_t>>& groups);

// Whether `w` is a flat_wide layout (one node over one or two leaves; a collapsed tree of 64 or
// more shapes never is).
inline bool is_flat(const WideBvh& w) { return w.nodes.size() == 1 && !w.leaves.empty() && w.leaves.size() <= 2; }

// cross(v1 - v0, v2 - v0) in double (exact inputs, one rounding per product and difference).
math::Vec3d triangle_normal_d(const TriangleShape& t);

}  // namespace dtraced::accel::detail
