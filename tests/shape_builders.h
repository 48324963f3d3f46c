// Pieces the accel tests build their scenes and queries from: accel shapes, rays, a seeded test
// random generator, the brute-force nearest hit and bitwise hit comparison.
//
// Header-only and stateless (a TestRng is a local object of each test), so any test file may
// include it; nothing here is shared between threads.
#pragma once

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>
#include <vector>

#include "accel/geometry.h"
#include "math/float_util.h"
#include "math/rng.h"
#include "math/vec.h"

namespace dtraced::testing {

// The vocabulary of the accel tests, so a test file needs only `using namespace` this namespace
// and dtraced::accel.
using math::next_float_down;
using math::next_float_up;
using math::Ray;
using math::Vec3d;
using math::Vec3f;

inline constexpr float kInf = std::numeric_limits<float>::infinity();

// Counter-based test random numbers (a local object per test: no shared state). Draw at most one
// number per full expression: the order operands and arguments are evaluated in is unspecified,
// and the scenes must not depend on the compiler or the optimisation level.
struct TestRng {
  std::uint64_t state;
  std::uint64_t next() { return math::mix64(state += 0x9e3779b97f4a7c15ULL); }
  double uniform() { return double(next() >> 11) * 0x1p-53; }  // [0, 1)
  double uniform(double a, double b) { return a + (b - a) * uniform(); }
  double log_uniform(double a, double b) { return std::exp(uniform(std::log(a), std::log(b))); }
  int index(int n) { return int(uniform() * n); }
  math::Vec3d unit() {
    const double z = uniform(-1.0, 1.0);
    const double phi = uniform(0.0, 2.0 * std::numbers::pi);
    const double s = std::sqrt(std::max(0.0, 1.0 - z * z));
    return {s * std::cos(phi), s * std::sin(phi), z};
  }
  math::Vec3d in_cube(double h) { return {uniform(-h, h), uniform(-h, h), uniform(-h, h)}; }
};

inline math::Vec3f to_f(const math::Vec3d& v) { return math::Vec3f(v); }
inline math::Vec3d to_d(const math::Vec3f& v) { return math::Vec3d(v); }
inline math::Vec3f unit_f(const math::Vec3d& v) { return to_f(math::normalize(v)); }

inline accel::Shape sphere(const math::Vec3f& c, float r) {
  accel::Shape s;
  s.type = accel::ShapeType::kSphere;
  s.sphere = {c, r};
  return s;
}
inline accel::Shape box(const math::Vec3f& lo, const math::Vec3f& hi) {
  accel::Shape s;
  s.type = accel::ShapeType::kBox;
  s.box = {lo, hi};
  return s;
}
inline accel::Shape plane(const math::Vec3f& p, const math::Vec3f& n) {
  accel::Shape s;
  s.type = accel::ShapeType::kPlane;
  s.plane = {p, n};
  return s;
}
inline accel::Shape triangle(const math::Vec3f& a, const math::Vec3f& b, const math::Vec3f& c) {
  accel::Shape s;
  s.type = accel::ShapeType::kTriangle;
  s.triangle = {a, b, c};
  return s;
}

inline math::Ray make_ray(const math::Vec3f& o, const math::Vec3f& d, float t_min = 0.0f, float t_max = kInf) {
  math::Ray r;
  r.o = o;
  r.d = d;
  r.t_min = t_min;
  r.t_max = t_max;
  return r;
}

// The reference nearest hit: every shape in id order, keeping strictly nearer hits, so ties go
// to the smaller id (the BVH's tie rule).
inline bool brute_force(const std::vector<accel::Shape>& shapes, math::Ray ray, accel::Hit& hit) {
  bool found = false;
  for (std::uint32_t id = 0; id < shapes.size(); ++id) {
    accel::Hit h;
    if (accel::intersect_shape(shapes[id], id, ray, h)) {
      hit = h;
      ray.t_max = h.t;
      found = true;
    }
  }
  return found;
}

inline bool same_bits(float a, float b) { return std::bit_cast<std::uint32_t>(a) == std::bit_cast<std::uint32_t>(b); }
inline bool same_bits(const math::Vec3f& a, const math::Vec3f& b) {
  return same_bits(a.x, b.x) && same_bits(a.y, b.y) && same_bits(a.z, b.z);
}
// Every field of the two hit records, bit for bit.
inline bool same_hit(const accel::Hit& a, const accel::Hit& b) {
  return a.shape == b.shape && same_bits(a.t, b.t) && same_bits(a.p, b.p) && same_bits(a.n, b.n) &&
         same_bits(a.p_error, b.p_error);
}

inline bool hit_is_finite(const accel::Hit& h) {
  return std::isfinite(h.t) && math::is_finite(h.p) && math::is_finite(h.n) && math::is_finite(h.p_error);
}

inline std::string describe(const math::Ray& r) {
  std::ostringstream s;
  s.precision(9);
  s << "o=(" << r.o.x << "," << r.o.y << "," << r.o.z << ") d=(" << r.d.x << "," << r.d.y << "," << r.d.z << ") t=("
    << r.t_min << "," << r.t_max << ")";
  return s.str();
}

}  // namespace dtraced::testing
