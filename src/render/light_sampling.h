// dtraced::render light sampling, internal to the render module: points on area lights and their
// Monte Carlo weights, a camera ray's meeting with an area light's emitting surface, and the
// light a shading point receives from one light (sample) computed so it cannot overflow.
// Pure functions of their arguments: thread-safe.
#pragma once

#include <algorithm>
#include <cmath>
#include <limits>

#include "math/ray.h"
#include "math/vec.h"
#include "render/integrator.h"
#include "render/render_scene.h"

namespace dtraced::render {

// Squared distances below this are subnormal floats: they have lost bits, and 1 / dist2 overflows.
inline constexpr float kMinNormal = std::numeric_limits<float>::min();

// v / |v|, given dist2 = dot(v, v) computed in float (v != 0). A subnormal dist2 (|v| below about
// 1e-19) has lost bits, and its square root more, so there the direction is taken in double.
Vec3f unit_towards(const Vec3f& v, float dist2);

// The radiance one light, or one area-light sample, reflects: f * emitted * g per channel, with g
// the geometric factor. `fast` is the caller's float evaluation of it, kept when it can be
// trusted: `fast_ok` (the float squared distance in g is a normal float) and every channel at
// most kMaxLightTerm, which NaN and Inf are not. So every ordinary scene keeps its bits, and pays
// four comparisons. Otherwise, a light within ~1e-19 of the point, dist2 underflowed, g
// overflowed and Inf * 0 in a black channel made NaN; `exact_factor()` then gives g in double,
// where neither can happen for float inputs, and the term is clamped to kMaxLightTerm. An
// emission beyond float (+Inf) stays Inf, as it was.
template <typename ExactFactor>
Vec3f light_term(const Vec3f& fast, bool fast_ok, const Vec3f& f, const Vec3f& emitted, ExactFactor exact_factor) {
  if (fast_ok && fast.x <= kMaxLightTerm && fast.y <= kMaxLightTerm && fast.z <= kMaxLightTerm) return fast;
  const double g = exact_factor();
  Vec3f out;
  for (int c = 0; c < 3; ++c) {
    const double v = double(f[c]) * double(emitted[c]) * g;
    out[c] = std::isfinite(v) ? float(std::min(v, double(kMaxLightTerm))) : float(v);
  }
  return out;
}

// |v|^2 in double: exact squares of floats, never 0 for v != 0.
inline double length_squared_d(const Vec3f& v) { return math::length_squared(Vec3d(v)); }

// One sample of an area light seen from a shading point: the direction and distance to a point
// on the emitting surface and the Monte Carlo weight cos_l / pdf (pdf in solid angle).
struct AreaSample {
  Vec3f l;              // unit direction towards the sampled point
  Vec3f point;          // the sampled point on the light
  float cos_l = 0.0f;   // dot(nf, l), > 0
  float weight = 0.0f;  // cos_l / pdf_solid_angle, > 0
  // Disk and rect: weight = cos_l * area * cos_light / dist2, dist2 = |to_point|^2. A sphere's
  // weight has no distance in it: dist2 stays 1.
  Vec3f to_point;
  float cos_light = 0.0f;
  float dist2 = 1.0f;
};

// AreaSample::weight in double (see light_term).
double exact_weight(const AreaLightF& a, const AreaSample& s);

// Draws a point of light `a` seen from p (shading normal nf) from the uniforms (u1, u2). False
// when the sample cannot contribute: p inside or on a sphere light, the point below p's horizon,
// or p behind a one-sided disk or rect.
bool sample_area_light(const AreaLightF& a, const Vec3f& p, const Vec3f& nf, float u1, float u2, AreaSample& out);

// Where `ray` meets the emitting surface of area light `a` at t in (ray.t_min, ray.t_max): a
// sphere from outside, a disk or rect from the normal's side. Lights are few and not in the BVH.
bool hit_emitter(const AreaLightF& a, const math::Ray& ray, float& t);

}  // namespace dtraced::render
