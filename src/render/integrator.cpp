#include "render/integrator.h"

#include <algorithm>
#include <array>
#include <bit>
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

// The transparent objects a path is currently inside (scene object indices, so a closed mesh is
// one medium whichever triangle the path crosses), innermost last. Bounded; an overflow only
// loses the outermost entries' indices of refraction, never memory safety.
struct MediumStack {
  static constexpr int kCapacity = 16;
  std::array<std::uint32_t, kCapacity> ids{};
  int size = 0;

  float current_ior(const RenderScene& s) const { return size == 0 ? 1.0f : s.object_material(ids[size - 1]).ior; }
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

// A point light as seen from one hit point (see Tracer::light_setup).
struct LightSample {
  Vec3f l;             // unit direction towards the light
  float dist2 = 0.0f;  // squared distance to the light
  float cos_l = 0.0f;  // dot(nf, l), > 0
};

// What the packet path already knows about the first surface of a camera ray: its hit (nullptr on
// a miss) and, when the shadow rays were traced as packets, the direct light there (nullptr: the
// tracer computes it itself).
struct FirstHit {
  const accel::Hit* hit = nullptr;
  const Vec3f* direct = nullptr;
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
    return transmittance_walk(ray, media, nullptr);
  }

  // The crossings of a shadow ray through transparent surfaces. `first`, when given, is the
  // outcome of the first intersection, already traced (and counted) by a packet: its `found`
  // says whether it hit; the rest of the walk is the same code either way.
  struct KnownHit {
    bool found;
    accel::Hit hit;
  };
  float transmittance_walk(math::Ray ray, MediumStack media, const KnownHit* first) {
    float t = 1.0f;
    for (int crossing = 0; crossing < kMaxShadowCrossings; ++crossing) {
      accel::Hit hit;
      if (crossing == 0 && first != nullptr) {
        if (!first->found) return t;
        hit = first->hit;
      } else if (!intersect(ray, hit)) {
        return t;
      }
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

  // Updates `media` for a path crossing transparent shape `shape` and returns the relative index
  // of refraction n_after / n_before of that crossing.
  float cross_interface(MediumStack& media, std::uint32_t shape) const {
    const std::uint32_t id = scene.object(shape);
    const float n_from = media.current_ior(scene);
    if (media.contains(id)) {
      media.remove(id);
    } else {
      media.push(id);
    }
    return media.current_ior(scene) / n_from;
  }

  // The geometry of one point light seen from a hit point, and the shadow ray towards it. False
  // when the light cannot contribute (at the point itself, or below the shading normal), in which
  // case no shadow ray is cast. Shared by the scalar and the packet path so both cast the very
  // same shadow rays.
  static bool light_setup(const accel::Hit& hit, const Vec3f& nf, const PointLightF& light, LightSample& ls,
                          math::Ray& shadow) {
    const Vec3f to_light = light.position - hit.p;
    ls.dist2 = math::dot(to_light, to_light);
    if (!(ls.dist2 > 0.0f)) return false;
    const float dist = std::sqrt(ls.dist2);
    ls.l = to_light / dist;
    ls.cos_l = math::dot(nf, ls.l);
    if (!(ls.cos_l > 0.0f)) return false;
    shadow = math::Ray{};
    shadow.o = accel::offset_ray_origin(hit.p, hit.p_error, hit.n, ls.l);
    const Vec3f seg = light.position - shadow.o;
    const float seg_len = math::length(seg);
    shadow.d = seg / seg_len;
    shadow.t_max = seg_len;  // a point light is not a surface: nothing to stop short of
    return true;
  }

  // Light reflected towards wo from one light whose shadow ray let `vis` (> 0) of it through.
  static Vec3f light_contribution(const MaterialF& m, const Vec3f& wo, const Vec3f& nf, const PointLightF& light,
                                  const LightSample& ls, float vis) {
    const float e = vis * ls.cos_l / ls.dist2;  // irradiance per unit intensity
    Vec3f f = m.color * (m.diffuse * kInvPi);
    if (m.specular > 0.0f) {
      const Vec3f h = math::normalize(ls.l + wo);
      const float cos_h = std::max(0.0f, math::dot(nf, h));
      const float spec =
          m.specular * (m.shininess + 8.0f) / (8.0f * std::numbers::pi_v<float>)*std::pow(cos_h, m.shininess);
      f += Vec3f{spec, spec, spec};
    }
    return math::mul(f, light.intensity) * e;
  }

  // Whether a hit on material m gathers direct light at all.
  static bool wants_direct(const MaterialF& m) {
    return m.local_weight > 0.0f && (m.diffuse > 0.0f || m.specular > 0.0f);
  }

  Vec3f direct(const accel::Hit& hit, const MaterialF& m, const Vec3f& wo, const Vec3f& nf, const MediumStack& media) {
    Vec3f sum{0, 0, 0};
    for (const PointLightF& light : scene.lights()) {
      LightSample ls;
      math::Ray shadow;
      if (!light_setup(hit, nf, light, ls, shadow)) continue;
      const float vis = transmittance(shadow, media);
      if (vis <= 0.0f) continue;
      sum += light_contribution(m, wo, nf, light, ls, vis);
    }
    return sum;
  }

  math::Ray spawn(const accel::Hit& hit, const Vec3f& dir) {
    math::Ray r;
    r.o = accel::offset_ray_origin(hit.p, hit.p_error, hit.n, dir);
    r.d = dir;
    return r;
  }

  // `first`, given only for camera rays of a packet, replaces the first intersection (and maybe
  // the first direct-light sum) by what the packet traversal found; all else is unchanged, so the
  // result has the same bits either way.
  Vec3f trace(math::Ray ray, std::uint32_t depth, float weight, MediumStack media, const FirstHit* first = nullptr) {
    for (int pass = 0; pass <= kMaxPassThroughs; ++pass) {
      accel::Hit hit;
      const Vec3f* known_direct = nullptr;
      if (pass == 0 && first != nullptr) {
        if (first->hit == nullptr) return limits.background;
        hit = *first->hit;
        known_direct = first->direct;
      } else if (!intersect(ray, hit)) {
        return limits.background;
      }
      const MaterialF& m = scene.material(hit.shape);
      const Vec3f wo = -ray.d;
      const bool front = math::dot(wo, hit.n) >= 0.0f;
      const Vec3f nf = front ? hit.n : -hit.n;

      // Relative index of refraction across this surface and the media beyond it.
      MediumStack inside = media;
      const float eta = m.transparency > 0.0f ? cross_interface(inside, hit.shape) : 1.0f;

      Vec3f radiance{0, 0, 0};
      if (wants_direct(m)) {
        radiance += (known_direct != nullptr ? *known_direct : direct(hit, m, wo, nf, media)) * m.local_weight;
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

Vec3f trace_radiance(const RenderScene& scene, const math::Ray& ray, const math::SampleKey& /*key*/,
                     const TraceLimits& limits, TraceStats& stats) {
  Tracer tracer{scene, limits, stats};
  return tracer.trace(ray, 0, 1.0f, MediumStack{});
}

void trace_radiance8(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* /*keys*/,
                     std::uint32_t valid, const TraceLimits& limits, TraceStats& stats, Vec3f* out) {
  constexpr int kN = accel::kPacketSize;
  valid &= (1u << kN) - 1;
  if (valid == 0) return;
  Tracer tracer{scene, limits, stats};
  const accel::Geometry& geometry = scene.geometry();

  accel::Hit hits[kN];
  stats.rays += std::popcount(valid);
  const std::uint32_t hit_mask = geometry.intersect8(rays, valid, hits) & valid;

  // Shadow rays of the first hits as packets, one per light: occluded8 when the scene is opaque
  // (a pure any-hit query); with transparent objects, intersect8 finds every lane's first
  // crossing and Tracer::transmittance_walk continues from it one lane at a time (most shadow
  // rays end there: they reach the light or meet an opaque surface).
  Vec3f direct[kN];
  std::uint32_t direct_mask = 0;  // lanes whose direct[] is final
  if (hit_mask != 0) {
    Vec3f wo[kN], nf[kN];
    for (int i = 0; i < kN; ++i) {
      if (!(hit_mask >> i & 1u) || !Tracer::wants_direct(scene.material(hits[i].shape))) continue;
      // The same wo and nf as Tracer::trace computes for this hit.
      wo[i] = -rays[i].d;
      nf[i] = math::dot(wo[i], hits[i].n) >= 0.0f ? hits[i].n : -hits[i].n;
      direct[i] = Vec3f{0, 0, 0};
      direct_mask |= 1u << i;
    }
    LightSample ls[kN];
    math::Ray shadow[kN];
    accel::Hit hits_scratch[kN];
    for (const PointLightF& light : scene.lights()) {
      std::uint32_t cast = 0;
      for (int i = 0; i < kN; ++i) {
        if ((direct_mask >> i & 1u) && Tracer::light_setup(hits[i], nf[i], light, ls[i], shadow[i])) cast |= 1u << i;
      }
      if (cast == 0) continue;
      stats.rays += std::popcount(cast);
      // Lights are summed in scene order per lane, as Tracer::direct does; a blocked light
      // (visibility 0) adds nothing.
      if (!scene.has_transparency()) {
        const std::uint32_t blocked = geometry.occluded8(shadow, cast);
        for (int i = 0; i < kN; ++i) {
          if ((cast & ~blocked) >> i & 1u) {
            direct[i] += Tracer::light_contribution(scene.material(hits[i].shape), wo[i], nf[i], light, ls[i], 1.0f);
          }
        }
        continue;
      }
      Tracer::KnownHit first[kN];
      const std::uint32_t crossed = geometry.intersect8(shadow, cast, hits_scratch);
      for (int i = 0; i < kN; ++i) {
        if (!(cast >> i & 1u)) continue;
        first[i].found = crossed >> i & 1u;
        if (first[i].found) first[i].hit = hits_scratch[i];
        // A camera ray's first hit is seen from outside every medium, as Tracer::trace has it.
        const float vis = tracer.transmittance_walk(shadow[i], MediumStack{}, &first[i]);
        if (vis <= 0.0f) continue;
        direct[i] += Tracer::light_contribution(scene.material(hits[i].shape), wo[i], nf[i], light, ls[i], vis);
      }
    }
  }

  for (int i = 0; i < kN; ++i) {
    if (!(valid >> i & 1u)) continue;
    const FirstHit first{(hit_mask >> i & 1u) ? &hits[i] : nullptr, (direct_mask >> i & 1u) ? &direct[i] : nullptr};
    out[i] = tracer.trace(rays[i], 0, 1.0f, MediumStack{}, &first);
  }
}

}  // namespace dtraced::render
