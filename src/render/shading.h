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

// wo: unit direction towards the viewer; n: unit normal on wo's side (dot(wo, n) >= 0 expected,
// clamped otherwise); eta: n_transmitted / n_incident, > 0.
inline Interface dielectric_interface(const Vec3f& wo, const Vec3f& n, float eta) {
  Interface out;
  const float cos_i = std::clamp(math::dot(wo, n), 0.0f, 1.0f);
  const float sin2_i = std::max(0.0f, 1.0f - cos_i * cos_i);
  const float sin2_t = sin2_i / (eta * eta);
  if (!(sin2_t < 1.0f)) return out;  // total internal reflection (also catches NaN)
  const float cos_t = std::sqrt(1.0f - sin2_t);
  const float r_parl = (eta * cos_i - cos_t) / (eta * cos_i + cos_t);
  const float r_perp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t);
  out.fresnel = std::clamp(0.5f * (r_parl * r_parl + r_perp * r_perp), 0.0f, 1.0f);
  out.refracts = true;
  const Vec3f wt = (-wo) / eta + n * (cos_i / eta - cos_t);
  // |wt| is 1 up to rounding; traversal requires unit directions, so renormalise.
  out.wt = math::normalize(wt);
  return out;
}

}  // namespace dtraced::render
