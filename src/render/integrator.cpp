#include "render/integrator.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>

#include "render/shading.h"

namespace dtraced::render {

namespace {

constexpr float kInvPi = std::numbers::inv_pi_v<float>;
// A branch whose weight on the pixel falls below this is not traced: it cannot change an 8- or
// 16-bit output and, with glass, would otherwise double the ray count at every bounce.
constexpr float kMinBranchWeight = 1e-6f;
// Continuations through index-matched (eta == 1) surfaces do not consume depth, so they get
// their own bound.
constexpr int kMaxPassThroughs = 64;
// Transparent surfaces a shadow ray may cross before the light counts as blocked.
constexpr int kMaxShadowCrossings = 64;

// The transparent objects a path is currently inside, innermost last. Bounded; an overflow only
// loses the outermost entries' indices of refraction, never memory safety.
struct MediumStack {
  static constexpr int kCapacity = 16;
  std::array<std::uint32_t, kCapacity> ids{};
  int size = 0;

  float current_ior(const RenderScene& s) const { return size == 0 ? 1.0f : s.material(ids[size - 1]).ior; }
  bool contains(std::uint32_t id) const {
    for (int i = 0; i < size; ++i)
      if (ids[i] == id) return true;
    return false;
  }
  void push(std::uint32_t id) {
    if (size == kCapacity) {
      std::copy(ids.begin() + 1, ids.end(), ids.begin());
      --size;
    }
    ids[size++] = id;
  }
  void remove(std::uint32_t id) {
    for (int i = size - 1; i >= 0; --i) {
      if (ids[i] == id) {
        std::copy(ids.begin() + i + 1, ids.begin() + size, ids.begin() + i);
        --size;
        return;
      }
    }
  }
};

struct Tracer {
  const RenderScene& scene;
  const TraceLimits& limits;
  TraceStats& stats;

  bool intersect(const math::Ray& ray, accel::Hit& hit) {
    ++stats.rays;
    return scene.geometry().intersect(ray, hit);
  }

  // Fraction of a point light's intensity that reaches the shadow ray's end. Opaque surfaces
  // block. A transparent one passes transparency * (1 - F) at each crossing, the shadow ray going
  // straight on (the usual Whitted approximation: no caustics). The indices on both sides come
  // from the same media stack as camera paths use, so an index-matched interface (eta == 1)
  // passes exactly `transparency`, and F is taken from the less dense side: for a straight ray
  // the exit angle is not the refracted one, and evaluating it from the dense side would report
  // total internal reflection where, by reciprocity, the true path transmits 1 - F(entry).
  float transmittance(math::Ray ray, MediumStack media) {
    if (!scene.has_transparency()) {
      // Only opaque surfaces: any hit blocks, so the traversal may stop at the first one.
      ++stats.rays;
      return scene.geometry().occluded(ray) ? 0.0f : 1.0f;
    }
    float t = 1.0f;
    for (int crossing = 0; crossing < kMaxShadowCrossings; ++crossing) {
      accel::Hit hit;
      if (!intersect(ray, hit)) return t;
      const MaterialF& m = scene.material(hit.shape);
      if (m.transparency <= 0.0f) return 0.0f;
      const float eta = cross_interface(media, hit.shape);
      if (eta != 1.0f) {
        const Vec3f wo = -ray.d;
        const Vec3f nf = math::dot(wo, hit.n) >= 0.0f ? hit.n : -hit.n;
        const Interface it = dielectric_interface(wo, nf, eta >= 1.0f ? eta : 1.0f / eta);
        t *= m.transparency * (1.0f - it.fresnel);
      } else {
        t *= m.transparency;
      }
      if (t <= 0.0f) return 0.0f;
      // Same origin and direction, only past this surface: no new rounding enters.
      ray.t_min = hit.t;
    }
    return 0.0f;
  }

  // Updates `media` for a path crossing transparent shape `id` and returns the relative index of
  // refraction n_after / n_before of that crossing.
  float cross_interface(MediumStack& media, std::uint32_t id) const {
    const float n_from = media.current_ior(scene);
    if (media.contains(id)) {
      media.remove(id);
    } else {
      media.push(id);
    }
    return media.current_ior(scene) / n_from;
  }

  Vec3f direct(const accel::Hit& hit, const MaterialF& m, const Vec3f& wo, const Vec3f& nf, const MediumStack& media) {
    Vec3f sum{0, 0, 0};
    for (const PointLightF& light : scene.lights()) {
      const Vec3f to_light = light.position - hit.p;
      const float dist2 = math::dot(to_light, to_light);
      if (!(dist2 > 0.0f)) continue;
      const float dist = std::sqrt(dist2);
      const Vec3f l = to_light / dist;
      const float cos_l = math::dot(nf, l);
      if (!(cos_l > 0.0f)) continue;
      math::Ray shadow;
      shadow.o = accel::offset_ray_origin(hit.p, hit.p_error, hit.n, l);
      const Vec3f seg = light.position - shadow.o;
      const float seg_len = math::length(seg);
      shadow.d = seg / seg_len;
      shadow.t_max = seg_len;  // a point light is not a surface: nothing to stop short of
      const float vis = transmittance(shadow, media);
      if (vis <= 0.0f) continue;
      const float e = vis * cos_l / dist2;  // irradiance per unit intensity
      Vec3f f = m.color * (m.diffuse * kInvPi);
      if (m.specular > 0.0f) {
        const Vec3f h = math::normalize(l + wo);
        const float cos_h = std::max(0.0f, math::dot(nf, h));
        const float spec =
            m.specular * (m.shininess + 8.0f) / (8.0f * std::numbers::pi_v<float>)*std::pow(cos_h, m.shininess);
        f += Vec3f{spec, spec, spec};
      }
      sum += math::mul(f, light.intensity) * e;
    }
    return sum;
  }

  math::Ray spawn(const accel::Hit& hit, const Vec3f& dir) {
    math::Ray r;
    r.o = accel::offset_ray_origin(hit.p, hit.p_error, hit.n, dir);
    r.d = dir;
    return r;
  }

  Vec3f trace(math::Ray ray, std::uint32_t depth, float weight, MediumStack media) {
    for (int pass = 0; pass <= kMaxPassThroughs; ++pass) {
      accel::Hit hit;
      if (!intersect(ray, hit)) return limits.background;
      const MaterialF& m = scene.material(hit.shape);
      const Vec3f wo = -ray.d;
      const bool front = math::dot(wo, hit.n) >= 0.0f;
      const Vec3f nf = front ? hit.n : -hit.n;

      // Relative index of refraction across this surface and the media beyond it.
      MediumStack inside = media;
      const float eta = m.transparency > 0.0f ? cross_interface(inside, hit.shape) : 1.0f;

      Vec3f radiance{0, 0, 0};
      if (m.local_weight > 0.0f && (m.diffuse > 0.0f || m.specular > 0.0f)) {
        radiance += direct(hit, m, wo, nf, media) * m.local_weight;
      }
      const bool deeper = depth < limits.max_depth;
      if (m.reflectivity > 0.0f && deeper && weight * m.reflectivity >= kMinBranchWeight) {
        const Vec3f r = math::normalize(reflect(ray.d, nf));
        radiance +=
            math::mul(m.color, trace(spawn(hit, r), depth + 1, weight * m.reflectivity, media)) * m.reflectivity;
      }
      if (m.transparency <= 0.0f) return radiance;

      if (eta == 1.0f) {
        // Index-matched: the surface does not bend or reflect light. Continue the very same ray
        // past it (no re-origin, no depth used), so a clear ior-1 object is exactly invisible.
        if (m.transparency == 1.0f && radiance == Vec3f{0, 0, 0}) {
          ray.t_min = hit.t;
          media = inside;
          continue;
        }
        // Partly transparent: recurse along the same ray. The branch weight shrinks by the
        // transparency at each such surface, so the cut-off bounds this recursion.
        if (weight * m.transparency < kMinBranchWeight) return radiance;
        math::Ray cont = ray;
        cont.t_min = hit.t;
        return radiance + trace(cont, depth, weight * m.transparency, inside) * m.transparency;
      }
      if (!deeper) return radiance;
      const Interface it = dielectric_interface(wo, nf, eta);
      const float w_reflect = weight * m.transparency * it.fresnel;
      if (w_reflect >= kMinBranchWeight) {
        const Vec3f r = math::normalize(reflect(ray.d, nf));
        radiance += trace(spawn(hit, r), depth + 1, w_reflect, media) * (m.transparency * it.fresnel);
      }
      const float w_refract = weight * m.transparency * (1.0f - it.fresnel);
      if (it.refracts && w_refract >= kMinBranchWeight) {
        radiance += trace(spawn(hit, it.wt), depth + 1, w_refract, inside) * (m.transparency * (1.0f - it.fresnel));
      }
      return radiance;
    }
    return Vec3f{0, 0, 0};
  }
};

}  // namespace

Vec3f trace_radiance(const RenderScene& scene, const math::Ray& ray, const TraceLimits& limits, TraceStats& stats) {
  Tracer tracer{scene, limits, stats};
  return tracer.trace(ray, 0, 1.0f, MediumStack{});
}

}  // namespace dtraced::render
