// dtraced::math rays and axis-aligned boxes. Plain values: thread-safe.
#pragma once

#include <limits>

#include "math/vec.h"

namespace dtraced::math {

// A ray o + t d with t in the open interval (t_min, t_max). `d` is normalised by every producer in
// dtraced (camera, reflection, refraction, shadow rays); intersection code relies on |d| = 1.
struct Ray {
  Vec3f o;
  Vec3f d;
  float t_min = 0.0f;
  float t_max = std::numeric_limits<float>::infinity();
};

struct Bounds3f {
  Vec3f lo{std::numeric_limits<float>::infinity(), std::numeric_limits<float>::infinity(),
           std::numeric_limits<float>::infinity()};
  Vec3f hi{-std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity(),
           -std::numeric_limits<float>::infinity()};

  void extend(const Vec3f& p) {
    lo = min(lo, p);
    hi = max(hi, p);
  }
  void extend(const Bounds3f& b) {
    lo = min(lo, b.lo);
    hi = max(hi, b.hi);
  }
  bool empty() const { return lo.x > hi.x || lo.y > hi.y || lo.z > hi.z; }
  Vec3f centroid() const { return (lo + hi) * 0.5f; }
  Vec3f extent() const { return hi - lo; }
  float surface_area() const {
    if (empty()) return 0.0f;
    const Vec3f e = extent();
    return 2.0f * (e.x * e.y + e.y * e.z + e.z * e.x);
  }
};

}  // namespace dtraced::math
