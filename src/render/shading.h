// dtraced::render shading helpers: exact dielectric Fresnel, refraction and reflection
// directions. Pure functions of their arguments: thread-safe.
#pragma once

#include <algorithm>
#include <cmath>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "accel/geometry.h"
#include "math/float_util.h"
#include "math/vec.h"

namespace dtraced::render {

using math::Vec3f;

// Mirror direction of incoming direction d about unit normal n.
inline Vec3f reflect(const Vec3f& d, const Vec3f& n) { return d - n * (2.0f * math::dot(d, n)); }

// Result of meeting a dielectric interface, computed from one sin²θt so the Fresnel term and the
// refracted direction can never disagree about total internal reflection.
struct Interface {
  float fresnel = 1.0f;   // reflected fraction, in [0, 1]; exactly 1 under total internal reflection
  bool refracts = false;  // false under total internal reflection
  Vec3f wt;               // refracted direction (unit), valid when refracts
};

// dielectric_interface without the refracted direction: the same fresnel and refracts, and the
// cosines refracted_direction takes. For callers that may not need the direction: a lane's
// tracer whose refracted ray the packet path spawned already, a shadow ray crossing glass.
struct Fresnel {
  float fresnel = 1.0f;
  bool refracts = false;
  float cos_i = 0.0f;  // valid when refracts
  float cos_t = 0.0f;  // valid when refracts
};

// wo: unit direction towards the viewer; n: unit normal on wo's side (dot(wo, n) >= 0 expected,
// clamped otherwise); eta: n_transmitted / n_incident, > 0.
inline Fresnel dielectric_fresnel(const Vec3f& wo, const Vec3f& n, float eta) {
  Fresnel out;
  const float cos_i = std::clamp(math::dot(wo, n), 0.0f, 1.0f);
  const float sin2_i = std::max(0.0f, 1.0f - cos_i * cos_i);
  const float sin2_t = sin2_i / (eta * eta);
  if (!(sin2_t < 1.0f)) return out;  // total internal reflection (also catches NaN)
  const float cos_t = std::sqrt(1.0f - sin2_t);
  const float r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const float r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  out.fresnel = std::clamp(0.5f * (r_parl * r_parl + r_perp * r_perp), 0.0f, 1.0f);
  out.refracts = true;
  out.cos_i = cos_i;
  out.cos_t = cos_t;
  return out;
}

// The refracted direction of dielectric_fresnel(wo, n, eta) = f, when f.refracts.
inline Vec3f refracted_direction(const Vec3f& wo, const Vec3f& n, float eta, const Fresnel& f) {
  const Vec3f wt = (-wo) / eta + n * (f.cos_i / eta - f.cos_t);
  // |wt| is 1 up to rounding; traversal requires unit directions, so renormalise.
  return math::normalize(wt);
}

// Both at once.
inline Interface dielectric_interface(const Vec3f& wo, const Vec3f& n, float eta) {
  Interface out;
  const Fresnel f = dielectric_fresnel(wo, n, eta);
  out.fresnel = f.fresnel;
  if (!f.refracts) return out;
  out.refracts = true;
  out.wt = refracted_direction(wo, n, eta, f);
  return out;
}

// accel::offset_ray_origin for entries [0, n) of arrays, a component to an array: the origin
// o[c][j] of a ray leaving the point p[c][j] (error bound e, geometric normal g) in direction w.
// With SSE2 four entries at a time, without branches, reading and writing up to n rounded up to a
// multiple of 4 (the caller gives those entries values: zeros leave o = p); every entry gets
// offset_ray_origin's bits (the same float operations in the same order, then next_float_up or
// next_float_down's integer step chosen by masks). For the packet path's shadow-ray origins:
// called per lane, offset_ray_origin had 4.9 % of whitted10's samples; this took whitted10's
// process CPU down by 1.1 %.
inline void offset_ray_origins(int n, const float* const p[3], const float* const e[3], const float* const g[3],
                               const float* const w[3], float* const o[3]) {
#if defined(__SSE2__)
  const __m128 zero = _mm_setzero_ps(), sign = _mm_set1_ps(-0.0f);
  for (int j = 0; j < n; j += 4) {
    const __m128 gx = _mm_loadu_ps(g[0] + j), gy = _mm_loadu_ps(g[1] + j), gz = _mm_loadu_ps(g[2] + j);
    // d = dot(abs(g), e); the offset d * g, negated where dot(w, g) < 0.
    const __m128 d = _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_andnot_ps(sign, gx), _mm_loadu_ps(e[0] + j)),
                                           _mm_mul_ps(_mm_andnot_ps(sign, gy), _mm_loadu_ps(e[1] + j))),
                                _mm_mul_ps(_mm_andnot_ps(sign, gz), _mm_loadu_ps(e[2] + j)));
    const __m128 wg =
        _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_loadu_ps(w[0] + j), gx), _mm_mul_ps(_mm_loadu_ps(w[1] + j), gy)),
                   _mm_mul_ps(_mm_loadu_ps(w[2] + j), gz));
    const __m128 flip = _mm_and_ps(_mm_cmplt_ps(wg, zero), sign);
    const __m128 gc[3] = {gx, gy, gz};
    for (int c = 0; c < 3; ++c) {
      const __m128 off = _mm_xor_ps(_mm_mul_ps(gc[c], d), flip);
      const __m128 v = _mm_add_ps(_mm_loadu_ps(p[c] + j), off);
      _mm_storeu_ps(o[c] + j, math::step_away4(v, off));
    }
  }
#else
  for (int j = 0; j < n; ++j) {
    Vec3f origin;
    accel::offset_ray_origin_to(Vec3f{p[0][j], p[1][j], p[2][j]}, Vec3f{e[0][j], e[1][j], e[2][j]},
                                Vec3f{g[0][j], g[1][j], g[2][j]}, Vec3f{w[0][j], w[1][j], w[2][j]}, origin);
    o[0][j] = origin.x;
    o[1][j] = origin.y;
    o[2][j] = origin.z;
  }
#endif
}

}  // namespace dtraced::render
