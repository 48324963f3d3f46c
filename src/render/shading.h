// dtraced::render shading helpers: exact dielectric Fresnel, refraction and reflection
// directions. Pure functions of their arguments: thread-safe.
#pragma once

#include <algorithm>
#include <cmath>

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

}  // namespace dtraced::render
