#include "render/light_sampling.h"

#include <numbers>

#include "math/det_math.h"
namespace dtraced::render {

namespace {

// An orthonormal pair perpendicular to unit w (Duff et al. 2017: branch-free, continuous except
// across w.z = 0).
void tangent_frame(const Vec3f& w, Vec3f& t, Vec3f& b) {
  const float sign = std::copysign(1.0f, w.z);
  const float a = -1.0f / (sign + w.z);
  const float c = w.x * w.y * a;
  t = Vec3f{1.0f + sign * w.x * w.x * a, sign * c, -sign * w.x};
  b = Vec3f{c, sign + w.y * w.y * a, -w.y};
}

}  // namespace

// v / |v|, given dist2 = dot(v, v) computed in float (v != 0). A subnormal dist2 (|v| below about
// 1e-19) has lost bits, and its square root more, so there the direction is taken in double.
Vec3f unit_towards(const Vec3f& v, float dist2) {
  if (dist2 >= kMinNormal) {
    const float dist = std::sqrt(dist2);
    return v / dist;
  }
  return Vec3f(math::normalize(Vec3d(v)));
}

// AreaSample::weight in double (see light_term).
double exact_weight(const AreaLightF& a, const AreaSample& s) {
  if (a.shape == AreaShape::kSphere) return s.weight;
  return double(s.cos_l) * double(a.area) * double(s.cos_light) / length_squared_d(s.to_point);
}

// Draws a point of light `a` seen from p (shading normal nf) from the uniforms (u1, u2). False
// when the sample cannot contribute: p inside or on a sphere light, the point below p's horizon,
// or p behind a one-sided disk or rect.
bool sample_area_light(const AreaLightF& a, const Vec3f& p, const Vec3f& nf, float u1, float u2, AreaSample& out) {
  constexpr float kTwoPi = 2.0f * std::numbers::pi_v<float>;
  const float phi = kTwoPi * u2;
  if (a.shape == AreaShape::kSphere) {
    // Uniform over the cone of directions the sphere subtends: pdf 1 / (2 pi (1 - cos_max)).
    const Vec3f to_c = a.center - p;
    const float d2 = math::dot(to_c, to_c);
    const float r2 = a.radius * a.radius;
    if (!(d2 > r2)) return false;
    const float d = std::sqrt(d2);
    const Vec3f w = to_c / d;
    const float sin2_max = r2 / d2;
    // 1 - cos_max without the cancellation of 1 - sqrt(1 - s^2) for small lights.
    const float one_minus_cos_max = sin2_max / (1.0f + std::sqrt(std::max(0.0f, 1.0f - sin2_max)));
    const float one_minus_cos = u1 * one_minus_cos_max;
    const float cos_t = 1.0f - one_minus_cos;
    const float sin2_t = std::max(0.0f, one_minus_cos * (2.0f - one_minus_cos));
    const float sin_t = std::sqrt(sin2_t);
    Vec3f t, b;
    tangent_frame(w, t, b);
    const math::det::SinCos sc = math::det::sincos(phi);
    out.l = math::normalize(t * (sin_t * float(sc.cos)) + b * (sin_t * float(sc.sin)) + w * cos_t);
    out.cos_l = math::dot(nf, out.l);
    if (!(out.cos_l > 0.0f)) return false;
    // The near intersection of the sampled direction with the sphere.
    const float dist = d * cos_t - std::sqrt(std::max(0.0f, r2 - d2 * sin2_t));
    out.point = p + out.l * dist;
    out.weight = out.cos_l * (kTwoPi * one_minus_cos_max);
    return true;
  }
  // Disk and rect: uniform over the area (pdf 1 / A), turned into solid angle by dist^2 / cos.
  Vec3f q;
  if (a.shape == AreaShape::kDisk) {
    const float r = a.radius * std::sqrt(u1);
    const math::det::SinCos sc = math::det::sincos(phi);
    q = a.center + a.edge_u * (r * float(sc.cos)) + a.edge_v * (r * float(sc.sin));
  } else {
    q = a.corner + a.edge_u * u1 + a.edge_v * u2;
  }
  const Vec3f to_q = q - p;
  const float dist2 = math::dot(to_q, to_q);
  if (to_q == Vec3f{0, 0, 0} || std::isnan(dist2)) return false;
  out.l = unit_towards(to_q, dist2);
  const float cos_light = -math::dot(out.l, a.normal);  // one-sided: emits on the normal's side
  if (!(cos_light > 0.0f)) return false;
  out.cos_l = math::dot(nf, out.l);
  if (!(out.cos_l > 0.0f)) return false;
  out.point = q;
  out.weight = out.cos_l * a.area * cos_light / dist2;
  out.to_point = to_q;
  out.cos_light = cos_light;
  out.dist2 = dist2;
  return true;
}

// Where `ray` meets the emitting surface of area light `a` at t in (ray.t_min, ray.t_max): a
// sphere from outside, a disk or rect from the normal's side. Lights are few and not in the BVH.
bool hit_emitter(const AreaLightF& a, const math::Ray& ray, float& t) {
  if (a.shape == AreaShape::kSphere) {
    const Vec3f oc = ray.o - a.center;
    const float c = math::dot(oc, oc) - a.radius * a.radius;
    if (!(c > 0.0f)) return false;  // origin inside or on the sphere: its outside is not seen
    const float b = math::dot(oc, ray.d);
    if (!(b < 0.0f)) return false;  // moving away from the centre
    // The squared distance of the centre from the ray's line, formed without the cancellation
    // of b^2 - c for distant lights.
    const Vec3f perp = oc - ray.d * b;
    const float disc = a.radius * a.radius - math::dot(perp, perp);
    if (!(disc >= 0.0f)) return false;
    t = -b - std::sqrt(disc);
  } else {
    const float denom = math::dot(ray.d, a.normal);
    if (!(denom < 0.0f)) return false;  // parallel, or reaching the back
    t = math::dot(a.center - ray.o, a.normal) / denom;
    if (!(t > ray.t_min && t < ray.t_max)) return false;
    const Vec3f q = ray.o + ray.d * t;
    if (a.shape == AreaShape::kDisk) {
      const Vec3f rel = q - a.center;
      if (!(math::dot(rel, rel) <= a.radius * a.radius)) return false;
    } else {
      // Coordinates of q in the (edge_u, edge_v) basis; a parallelogram in general.
      const Vec3f rel = q - a.corner;
      const float uu = math::dot(a.edge_u, a.edge_u), vv = math::dot(a.edge_v, a.edge_v);
      const float uv = math::dot(a.edge_u, a.edge_v);
      const float ru = math::dot(rel, a.edge_u), rv = math::dot(rel, a.edge_v);
      const float det = uu * vv - uv * uv;
      const float s = (ru * vv - rv * uv) / det, w = (rv * uu - ru * uv) / det;
      if (!(s >= 0.0f && s <= 1.0f && w >= 0.0f && w <= 1.0f)) return false;
    }
  }
  return t > ray.t_min && t < ray.t_max;
}

}  // namespace dtraced::render
