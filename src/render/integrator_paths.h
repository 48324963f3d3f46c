// The integrator's code paths (render/integrator.cpp's trace_radiance, trace_radiance8 and
// trace_radiance16), shared by the two files that instantiate them: integrator.cpp for the scene
// feature sets without point lights, integrator_lit.cpp for those with them. Each path is a
// template over the feature set and the packet width, 40 sets in all. In one file they were the
// render library's longest compile (28 s of CPU at -O3, 50-99 s in the sanitizer build), and the
// libraries that depend on render waited for it with a core idle; in two they take 15 and 16 s
// at -O3, on two cores at once. Not part of the render library's interface.
#pragma once

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <limits>
#include <memory>
#include <new>
#include <numbers>
#include <type_traits>
#include <utility>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "math/det_math.h"
#include "math/float_util.h"
#include "math/rng.h"
#include "render/integrator.h"
#include "render/light_sampling.h"
#include "render/sampler.h"
#include "render/shading.h"

namespace dtraced::render::paths {

inline constexpr float kInvPi = std::numbers::inv_pi_v<float>;
// An area light's sample index, key.sample * samples + s, stays below stratified_2d's 2^24.
static_assert(std::uint64_t(scene::kMaxSamples) * scene::kMaxLightSamples <= (std::uint64_t(1) << 24));
// Continuations through index-matched (eta == 1) surfaces do not consume depth, so they get
// their own bound.
inline constexpr int kMaxPassThroughs = 64;
// Transparent surfaces a shadow ray may cross before the light counts as blocked.
inline constexpr int kMaxShadowCrossings = 64;

// The transparent objects a path is currently inside (scene object indices, so a closed mesh is
// one medium whichever triangle the path crosses), innermost last. Bounded; an overflow only
// loses the outermost entries' indices of refraction, never memory safety.
struct MediumStack {
  static constexpr int kCapacity = 16;
  std::array<std::uint32_t, kCapacity> ids{};
  int size = 0;

  // Where every camera path starts: inside the objects that contain the camera.
  static MediumStack at_camera(const RenderScene& s) {
    MediumStack m;
    for (const std::uint32_t id : s.camera_media()) m.push(id);
    return m;
  }

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

// The scene features (SceneFeatures) as the bits of a template argument: Tracer<kF> models only
// the features in kF. A feature that is off is one the scene does not use, so skipping its code
// changes no bits: every such branch would have been false at run time.
enum FeatureBit : unsigned {
  kReflection = 1u << 0,
  kRefraction = 1u << 1,
  kSpecular = 1u << 2,
  kShadows = 1u << 3,
  kAreaLights = 1u << 4,
  kPointLights = 1u << 5,
};
inline constexpr unsigned kFeatureCount = 6;
inline constexpr unsigned kAllFeatures = (1u << kFeatureCount) - 1;

constexpr unsigned feature_bits(const SceneFeatures& f) {
  return (f.reflection ? kReflection : 0u) | (f.refraction ? kRefraction : 0u) | (f.specular ? kSpecular : 0u) |
         (f.shadows ? kShadows : 0u) | (f.area_lights ? kAreaLights : 0u) | (f.point_lights ? kPointLights : 0u);
}
static_assert(feature_bits(SceneFeatures::all()) == kAllFeatures);

// A point light as seen from one hit point (see Tracer::light_setup).
struct LightSample {
  Vec3f to_light;      // light position - hit point
  Vec3f l;             // unit direction towards the light
  float dist2 = 0.0f;  // squared distance to the light, in float
  float cos_l = 0.0f;  // dot(nf, l), > 0
};

// What the packet path already traced for one ray of a lane's path (the camera ray, or a mirror or
// refracted ray its tracer will cast): whether and where it hits, the point-light direct light
// there when the shadow rays went as packets, and the same for the mirror and refracted rays that
// hit spawns. A nullptr child (and has_direct false) leaves that part to the tracer.
// `hit` and `direct` are left unset until trace_ahead writes them (each is read only when its flag
// says so): zeroing them in every record was part of the records' construction, about 23 % of
// trace_packet_with's own time on whitted10.
struct Known {
  explicit Known(const math::Ray& r) : ray(r) {}
  // A secondary ray, its direction only (trace_ahead finds its origin), written component by
  // component where it stays: a ray built whole on the stack and then copied in made the copy's
  // wide loads wait for the narrow stores that built the direction (30 % of trace_packet_with's own
  // time on whitted10; with the records' construction trimmed, its process CPU went down 1.8 %).
  explicit Known(const Vec3f& d) {
    ray.d.x = d.x;
    ray.d.y = d.y;
    ray.d.z = d.z;
  }
  math::Ray ray;       // the ray itself, as trace() would spawn it (a secondary ray's tracer takes it)
  bool found = false;  // the ray hits; `hit` is its nearest hit
  bool has_direct = false;
  union {
    accel::Hit hit;  // set when found
  };
  union {
    Vec3f direct;  // the point lights' sum (Tracer::point_direct) at the hit, when has_direct
  };
  const Known* mirror = nullptr;
  const Known* refracted = nullptr;
};

template <unsigned kF>
struct Tracer {
  static constexpr bool kReflect = (kF & kReflection) != 0;
  static constexpr bool kRefract = (kF & kRefraction) != 0;
  static constexpr bool kSpec = (kF & kSpecular) != 0;
  static constexpr bool kShadow = (kF & kShadows) != 0;
  static constexpr bool kArea = (kF & kAreaLights) != 0;
  static constexpr bool kPoint = (kF & kPointLights) != 0;

  const RenderScene& scene;
  const TraceLimits& limits;
  TraceStats& stats;
  // The pixel sample whose random numbers area-light sampling draws, and the next dimension to
  // draw: advanced by 2 * samples per area light at every hit that gathers direct light, in the
  // order the path visits them, so a sample's radiance is a pure function of (scene, key).
  math::SampleKey key{};
  std::uint32_t dim = kFirstIntegratorDim;

  bool intersect(const math::Ray& ray, accel::Hit& hit) {
    ++stats.rays;
    return scene.geometry().intersect(ray, hit);
  }

  bool transparent_scene() const { return kRefract && scene.has_transparency(); }

  // The media a camera path starts in; without refraction there are none to look up.
  MediumStack camera_media() const { return kRefract ? MediumStack::at_camera(scene) : MediumStack{}; }

  // Fraction of a light's emission that reaches the shadow ray's end. Opaque surfaces
  // block. A transparent one passes transparency * (1 - F) at each crossing, the shadow ray going
  // straight on (the usual Whitted approximation: no caustics). The indices on both sides come
  // from the same media stack as camera paths use, so an index-matched interface (eta == 1)
  // passes exactly `transparency`, and F is taken from the less dense side: for a straight ray
  // the exit angle is not the refracted one, and evaluating it from the dense side would report
  // total internal reflection where, by reciprocity, the true path transmits 1 - F(entry).
  float transmittance(math::Ray ray, MediumStack media) {
    if (!transparent_scene()) {
      // Only opaque surfaces: any hit blocks, so the traversal may stop at the first one.
      ++stats.rays;
      return scene.geometry().occluded(ray) ? 0.0f : 1.0f;
    }
    if (scene.geometry().transparent() == nullptr) return transmittance_walk(ray, media, false);
    // A scene split by transparency: an opaque surface anywhere on the ray blocks the light
    // whatever the crossings before it let through, so one any-hit query over the opaque layer
    // answers the blocked rays, and the others walk the transparent layer only. The same value as
    // the walk over every shape, but where an opaque and a transparent surface meet the ray at the
    // same t and the transparent one has the smaller id (that walk crosses it and starts past both).
    // Counted as one ray with the walk's first query, which goes on where it found nothing: the
    // rays counted are the segments cast between crossings, as for the walk over every shape, but
    // a blocked ray is one segment however many crossings lie before its opaque surface.
    ++stats.rays;
    ++stats.opaque_first_rays;
    if (scene.geometry().occluded_opaque(ray)) return 0.0f;
    return transmittance_walk(ray, media, true);
  }

  // The crossings of a shadow ray through transparent surfaces, one scalar query at a time (the
  // packet path walks the same crossings as packets: trace_ahead): over every shape, or over the
  // transparent layer alone (`clear`: the opaque one found nothing).
  float transmittance_walk(math::Ray ray, MediumStack media, bool clear) {
    float t = 1.0f;
    for (int crossing = 0; crossing < kMaxShadowCrossings; ++crossing) {
      accel::Hit hit;
      if (!clear) {
        if (!intersect(ray, hit)) return t;
      } else {
        if (crossing > 0) ++stats.rays;  // the first query's ray is the opaque query's
        if (!scene.geometry().intersect_transparent(ray, hit)) return t;
      }
      if (!shadow_crossing(hit, ray, media, t)) return 0.0f;
    }
    return 0.0f;
  }

  // One crossing of a shadow ray at `hit` (the nearest hit of `ray`, which travels in `media`):
  // multiplies `t` by what passes, updates `media`, and moves ray.t_min past the surface. False
  // when nothing passes (an opaque surface, or a transmittance that rounds to 0). Shared by the
  // scalar walk and the packet path's, so both give the same bits.
  bool shadow_crossing(const accel::Hit& hit, math::Ray& ray, MediumStack& media, float& t) const {
    const MaterialF& m = scene.material(hit.shape);
    if (m.transparency <= 0.0f) return false;
    const float eta = cross_interface(media, hit.shape);
    if (eta != 1.0f) {
      const Vec3f wo = -ray.d;
      const Vec3f nf = math::dot(wo, hit.n) >= 0.0f ? hit.n : -hit.n;
      const Fresnel it = dielectric_fresnel(wo, nf, eta >= 1.0f ? eta : 1.0f / eta);
      t *= m.transparency * (1.0f - it.fresnel);
    } else {
      t *= m.transparency;
    }
    if (t <= 0.0f) return false;
    // Same origin and direction, only past this surface: no new rounding enters.
    ray.t_min = hit.t;
    return true;
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
    ls.to_light = light.position - hit.p;
    ls.dist2 = math::dot(ls.to_light, ls.to_light);
    if (ls.to_light == Vec3f{0, 0, 0} || std::isnan(ls.dist2)) return false;
    ls.l = unit_towards(ls.to_light, ls.dist2);
    ls.cos_l = math::dot(nf, ls.l);
    if (!(ls.cos_l > 0.0f)) return false;
    shadow = shadow_ray(hit, ls.l, light.position);
    return true;
  }

  // A shadow ray from hit towards `target`, leaving along about `l`, ending at `end` times the
  // distance to the target: lights are not surfaces the traversal could find. A point light ends
  // at 1. An area light's sample ends at kAreaShadowEnd short of it, because area lights are
  // usually mounted on a surface (a rect on a ceiling), and that surface's hit, computed in float
  // at about the same distance, would otherwise shadow the light at random.
  static constexpr float kAreaShadowEnd = 1.0f - 1e-4f;
  static math::Ray shadow_ray(const accel::Hit& hit, const Vec3f& l, const Vec3f& target, float end = 1.0f) {
    math::Ray shadow;
    shadow.o = accel::offset_ray_origin(hit.p, hit.p_error, hit.n, l);
    const Vec3f seg = target - shadow.o;
    const float seg_len = math::length(seg);
    shadow.d = seg / seg_len;
    shadow.t_max = seg_len * end;
    return shadow;
  }

  // Lambert plus normalised Blinn-Phong: the BRDF for light arriving from unit direction l.
  static Vec3f brdf(const MaterialF& m, const Vec3f& wo, const Vec3f& nf, const Vec3f& l) {
    Vec3f f = m.color * (m.diffuse * kInvPi);
    if (kSpec && m.specular > 0.0f) {
      const Vec3f h = math::normalize(l + wo);
      const float cos_h = std::max(0.0f, math::dot(nf, h));
      const float spec =
          m.specular * (m.shininess + 8.0f) / (8.0f * std::numbers::pi_v<float>)*math::det::powf(cos_h, m.shininess);
      f += Vec3f{spec, spec, spec};
    }
    return f;
  }

  // Light reflected towards wo from one light whose shadow ray let `vis` (> 0) of it through.
  static Vec3f light_contribution(const MaterialF& m, const Vec3f& wo, const Vec3f& nf, const PointLightF& light,
                                  const LightSample& ls, float vis) {
    const Vec3f f = brdf(m, wo, nf, ls.l);
    const float e = vis * ls.cos_l / ls.dist2;  // irradiance per unit intensity
    return light_term(math::mul(f, light.intensity) * e, ls.dist2 >= kMinNormal, f, light.intensity,
                      [&] { return double(vis) * double(ls.cos_l) / length_squared_d(ls.to_light); });
  }

  // Whether a hit on material m gathers direct light at all.
  static bool wants_direct(const MaterialF& m) {
    return m.local_weight > 0.0f && (m.diffuse > 0.0f || (kSpec && m.specular > 0.0f));
  }

  // Direct light from the point lights, summed in scene order.
  Vec3f point_direct(const accel::Hit& hit, const MaterialF& m, const Vec3f& wo, const Vec3f& nf,
                     const MediumStack& media) {
    Vec3f sum{0, 0, 0};
    if constexpr (kPoint) {
      for (const PointLightF& light : scene.lights()) {
        LightSample ls;
        math::Ray shadow;
        if (!light_setup(hit, nf, light, ls, shadow)) continue;
        const float vis = transmittance(shadow, media);
        if (vis <= 0.0f) continue;
        sum += light_contribution(m, wo, nf, light, ls, vis);
      }
    }
    return sum;
  }

  // Adds to `sum` the Monte Carlo estimate of each area light's direct light, in scene order,
  // each the mean of its `samples` samples.
  void add_area_direct(const accel::Hit& hit, const MaterialF& m, const Vec3f& wo, const Vec3f& nf,
                       const MediumStack& media, Vec3f& sum) {
    if constexpr (kArea) {
      for (const AreaLightF& a : scene.area_lights()) {
        const std::uint32_t base = dim;
        dim += 2 * a.samples;
        Vec3f acc{0, 0, 0};
        const PixelSampler2 light_points(key, base);  // stratified_2d(key, base, .), hashed once
        for (std::uint32_t s = 0; s < a.samples; ++s) {
          // Point key.sample * samples + s of one stratified sequence: the light's samples of
          // one pixel sample, and of the pixel's first 2^k samples, are stratified together.
          const Sample2 u = light_points.at(key.sample * a.samples + s);
          AreaSample as;
          if (!sample_area_light(a, hit.p, nf, u.u, u.v, as)) continue;
          float vis = 1.0f;
          if constexpr (kShadow) {
            if (a.cast_shadows) vis = transmittance(shadow_ray(hit, as.l, as.point, kAreaShadowEnd), media);
          }
          if (vis <= 0.0f) continue;
          const Vec3f f = brdf(m, wo, nf, as.l);
          acc += light_term(math::mul(f, a.radiance) * (as.weight * vis), as.dist2 >= kMinNormal, f, a.radiance,
                            [&] { return exact_weight(a, as) * double(vis); });
        }
        sum += acc / float(a.samples);
      }
    }
  }

  // Radiance of the nearest area light whose emitting surface `ray` reaches before t_limit.
  bool emitter_before(math::Ray ray, float t_limit, Vec3f& le) const {
    bool found = false;
    if constexpr (kArea) {
      ray.t_max = t_limit;
      for (const AreaLightF& a : scene.area_lights()) {
        float t;
        if (!hit_emitter(a, ray, t)) continue;
        ray.t_max = t;  // nearer lights only from now on
        le = a.radiance;
        found = true;
      }
    }
    return found;
  }

  // Where a ray leaving `hit` along `dir` starts: past the hit point's rounding error.
  static Vec3f spawn_origin(const accel::Hit& hit, const Vec3f& dir) {
    return accel::offset_ray_origin(hit.p, hit.p_error, hit.n, dir);
  }
  static math::Ray spawn(const accel::Hit& hit, const Vec3f& dir) {
    math::Ray r;
    r.o = spawn_origin(hit, dir);
    r.d = dir;
    return r;
  }

  // The direction of the mirror ray of `ray` at its hit (nf: the normal on the incoming side).
  static Vec3f mirror_direction(const math::Ray& ray, const Vec3f& nf) { return math::normalize(reflect(ray.d, nf)); }

  // The secondary rays a hit casts: at most one mirror ray and one refracted ray, and the weights
  // trace() sums them with. Decided here for trace() and for the packet path alike, so both cast
  // the very same rays.
  struct Branches {
    // `inside` is made (by branches()) only at a transparent surface, copied whole from the media
    // before it: a default MediumStack zeroed its ids first (a `rep stos` of the whole record, 11 %
    // of trace_packet_with's own time on whitted10) only for the copy to overwrite them, and most
    // hits (whitted10's floor) are opaque: copied only where needed, whitted10's process CPU went
    // down 1.7 %.
    Branches() {}
    bool transparent = false;
    union {
      MediumStack inside;  // the media past the surface (transparent only)
    };
    float eta = 1.0f;    // n_after / n_before across it
    bool bends = false;  // transparent, eta != 1 and depth left: Fresnel reflection and refraction
    // Valid when bends. Without the refracted direction (refracted_direction(wo, nf, eta, it)),
    // which only a ray not traced ahead needs: a lane's tracer computing it again for every glass
    // hit whose refracted ray the packet path spawned cost up to seven divisions and a square root.
    Fresnel it;
    float fresnel_w = 0.0f;
    bool reflective = false;  // the `reflectivity` lobe; its ray also carries the Fresnel reflection
    bool mirror = false;      // a mirror ray is cast, with branch weight mirror_weight
    float mirror_weight = 0.0f;
    bool refract = false;  // a refracted ray (it.wt) is cast, with branch weight refract_weight
    float refract_w = 0.0f;
    float refract_weight = 0.0f;
  };
  Branches branches(const accel::Hit& hit, const MaterialF& m, const Vec3f& wo, const Vec3f& nf, std::uint32_t depth,
                    float weight, const MediumStack& media) const {
    Branches b;
    const float cutoff = limits.min_branch_weight;
    const bool deeper = depth < limits.max_depth;
    b.transparent = kRefract && m.transparency > 0.0f;
    if (b.transparent) {
      std::construct_at(&b.inside, media);
      b.eta = cross_interface(b.inside, hit.shape);
    }
    b.bends = b.transparent && b.eta != 1.0f && deeper;
    if (b.bends) b.it = dielectric_fresnel(wo, nf, b.eta);
    b.fresnel_w = b.bends ? m.transparency * b.it.fresnel : 0.0f;
    b.reflective = kReflect && m.reflectivity > 0.0f && deeper;
    if (b.reflective) {
      // One ray for every lobe that reflects in the mirror direction: the `reflectivity` mirror
      // (tinted by the colour) and, on glass, the Fresnel reflection.
      const float mirror_w = b.bends ? m.reflectivity + b.fresnel_w : m.reflectivity;
      b.mirror_weight = weight * mirror_w;
      b.mirror = b.mirror_weight >= cutoff;
    } else if (b.bends) {
      b.mirror_weight = weight * b.fresnel_w;
      b.mirror = b.mirror_weight >= cutoff;
    }
    if (b.bends) {
      b.refract_w = m.transparency * (1.0f - b.it.fresnel);
      b.refract_weight = weight * b.refract_w;
      b.refract = b.it.refracts && b.refract_weight >= cutoff;
    }
    return b;
  }

  // `known`, given only for the rays of a packet, replaces this ray's intersection (and maybe the
  // point-light direct sum), and through its children those of the secondary rays it spawns, by
  // what the packet traversal found; all else is unchanged, so the result has the same bits
  // either way.
  Vec3f trace(const math::Ray& ray, std::uint32_t depth, float weight, const MediumStack& media,
              const Known* known = nullptr) {
    Vec3f out;
    trace_to(out, ray, depth, weight, media, known);
    return out;
  }

  // trace, written to `out`: a Vec3f returned from the recursion went through the stack, its
  // components stored one by one and loaded back two at a time, and each such load waited for
  // the stores to complete (whitted10's render phase went down by 2.3 %).
  // The ray and the media are taken by reference: copies of them, made with wide loads of the
  // narrow stores that had just written them, waited for those stores too (whitted10's render
  // phase went down by 2.4 %). `pass` counts the continuations past index-matched surfaces so far.
  void trace_to(Vec3f& out, const math::Ray& ray, std::uint32_t depth, float weight, const MediumStack& media,
                const Known* known = nullptr, int pass = 0) {
    if (pass > kMaxPassThroughs) {
      out = Vec3f{0, 0, 0};
      return;
    }
    accel::Hit hit;
    // Only the ray as given is known: a continuation past an index-matched surface is not
    // (continuations pass none).
    const Known* k = known;
    bool found;
    if (k != nullptr) {
      found = k->found;
      if (found) hit = k->hit;
    } else {
      found = intersect(ray, hit);
    }
    if constexpr (kArea) {
      Vec3f le;
      if (emitter_before(ray, found ? hit.t : ray.t_max, le)) {
        out = le;
        return;
      }
    }
    if (!found) {
      out = limits.background;
      return;
    }
    const MaterialF& m = scene.material(hit.shape);
    const Vec3f wo = -ray.d;
    const bool front = math::dot(wo, hit.n) >= 0.0f;
    const Vec3f nf = front ? hit.n : -hit.n;
    // The relative index of refraction across this surface, the media beyond it, and the rays
    // this hit casts.
    const Branches b = branches(hit, m, wo, nf, depth, weight, media);

    Vec3f radiance{0, 0, 0};
    if (wants_direct(m)) {
      // Point lights first (the packet path may have summed them already), then area lights.
      Vec3f direct = k != nullptr && k->has_direct ? k->direct : point_direct(hit, m, wo, nf, media);
      add_area_direct(hit, m, wo, nf, media, direct);
      radiance += direct * m.local_weight;
    }
    if (b.mirror) {
      const Known* kr = k != nullptr ? k->mirror : nullptr;
      Vec3f lr;
      trace_to(lr, kr != nullptr ? kr->ray : spawn(hit, mirror_direction(ray, nf)), depth + 1, b.mirror_weight, media,
               kr);
      if (b.reflective) {
        radiance += math::mul(m.color, lr) * m.reflectivity;
        if (b.bends) radiance += lr * b.fresnel_w;
      } else {
        radiance += lr * b.fresnel_w;
      }
    }
    if (!b.transparent) {
      out = radiance;
      return;
    }

    if (b.eta == 1.0f) {
      // Index-matched: the surface does not bend or reflect light. Continue the very same ray
      // past it (no re-origin, no depth used), so a clear ior-1 object is exactly invisible.
      if (m.transparency == 1.0f && radiance == Vec3f{0, 0, 0}) {
        math::Ray cont = ray;
        cont.t_min = hit.t;
        trace_to(out, cont, depth, weight, b.inside, nullptr, pass + 1);
        return;
      }
      // Partly transparent: recurse along the same ray. The branch weight shrinks by the
      // transparency at each such surface, so the cut-off bounds this recursion.
      if (weight * m.transparency < limits.min_branch_weight) {
        out = radiance;
        return;
      }
      math::Ray cont = ray;
      cont.t_min = hit.t;
      Vec3f lc;
      trace_to(lc, cont, depth, weight * m.transparency, b.inside);
      out = radiance + lc * m.transparency;
      return;
    }
    if (b.refract) {
      const Known* kt = k != nullptr ? k->refracted : nullptr;
      Vec3f lt;
      trace_to(lt, kt != nullptr ? kt->ray : spawn(hit, refracted_direction(wo, nf, b.eta, b.it)), depth + 1,
               b.refract_weight, b.inside, kt);
      radiance += lt * b.refract_w;
    }
    out = radiance;
  }
};

template <unsigned kF>
Vec3f trace_radiance_with(const RenderScene& scene, const math::Ray& ray, const math::SampleKey& key,
                          const TraceLimits& limits, TraceStats& stats) {
  Tracer<kF> tracer{scene, limits, stats, key};
  return tracer.trace(ray, 0, 1.0f, tracer.camera_media());
}

// A packet of kN (8 or 16) rays through the geometry. 16-ray packets go to the one layer of a
// static scene, or to both layers of a static scene split by transparency (each layer's 16-ray
// query, then the merge); an animated frame's two layers have 8-ray queries only, so their 16
// rays are traced as two 8-ray halves: the same answers either way.
template <int kN>
std::uint32_t intersect_packet(const accel::LayeredGeometry& geometry, const math::Ray* rays, std::uint32_t valid,
                               accel::Hit* hits) {
  if constexpr (kN == accel::kPacketSize) {
    return geometry.intersect8(rays, valid, hits);
  } else {
    static_assert(kN == 2 * accel::kPacketSize);
    // One layer, or a static scene split by transparency: 16 rays at once over each layer.
    if (geometry.moving() == nullptr) return geometry.intersect16(rays, valid, hits);
    constexpr int kH = accel::kPacketSize;
    constexpr std::uint32_t kHalf = (1u << kH) - 1;
    const std::uint32_t lo = (valid & kHalf) != 0 ? geometry.intersect8(rays, valid & kHalf, hits) : 0;
    const std::uint32_t hi = (valid >> kH) != 0 ? geometry.intersect8(rays + kH, valid >> kH, hits + kH) : 0;
    return (lo & kHalf) | (hi & kHalf) << kH;
  }
}

template <int kN>
std::uint32_t occluded_packet(const accel::LayeredGeometry& geometry, const math::Ray* rays, std::uint32_t valid) {
  if constexpr (kN == accel::kPacketSize) {
    return geometry.occluded8(rays, valid);
  } else {
    static_assert(kN == 2 * accel::kPacketSize);
    if (geometry.moving() == nullptr) return geometry.occluded16(rays, valid);
    constexpr int kH = accel::kPacketSize;
    constexpr std::uint32_t kHalf = (1u << kH) - 1;
    const std::uint32_t lo = (valid & kHalf) != 0 ? geometry.occluded8(rays, valid & kHalf) : 0;
    const std::uint32_t hi = (valid >> kH) != 0 ? geometry.occluded8(rays + kH, valid >> kH) : 0;
    return (lo & kHalf) | (hi & kHalf) << kH;
  }
}

// A ray of some lane's path traced ahead of the lane's tracer as part of a packet: its record, the
// arguments Tracer::trace will be called with for it, and the parent's pointer to the record
// (nullptr for a camera ray), cleared when the ray is left to the tracer after all.
// A secondary ray's origin is found (Tracer::spawn) only once the ray goes into a packet: until
// then `from` is the hit it leaves and known.ray.d its direction.
// The media are a pointer: the camera rays share the packet's camera media and a mirror ray those
// of its parent, so only a refracted ray, which goes into a medium, has its own copy (`inside`),
// left unset otherwise (copying the 68-byte stack into every record was the other part of their
// construction's cost).
struct Ahead {
  // `r`: the camera ray, or a secondary ray's direction (see Known).
  template <typename R>
  Ahead(const R& r, const accel::Hit* from_hit, const MediumStack* ray_media, std::uint32_t ray_depth, float ray_weight,
        const Known** parent_link)
      : known(r), from(from_hit), media(ray_media), depth(ray_depth), weight(ray_weight), link(parent_link) {}
  Ahead(const Vec3f& r, const accel::Hit* from_hit, const MediumStack& own_media, std::uint32_t ray_depth,
        float ray_weight, const Known** parent_link)
      : known(r),
        from(from_hit),
        media(&inside),
        depth(ray_depth),
        weight(ray_weight),
        link(parent_link),
        inside(own_media) {}
  Ahead(const Ahead&) = delete;
  Ahead& operator=(const Ahead&) = delete;
  Known known;
  const accel::Hit* from;
  const MediumStack* media;  // the media the ray travels in
  std::uint32_t depth;
  float weight;
  const Known** link;
  union {
    MediumStack inside;  // a refracted ray's media (then `media` points here)
  };
};

// Room for up to N objects of type T, constructed one by one as they are needed (a packet's
// records are many and mostly unused: zeroing them all costs more than tracing).
template <typename T, int N>
class Slots {
 public:
  Slots() {}
  template <typename... Args>
  T* emplace(Args&&... args) {
    assert(used_ < N);
    return std::construct_at(&slots_[used_++].value, std::forward<Args>(args)...);
  }
  bool full() const { return used_ == N; }

 private:
  union Slot {
    Slot() {}
    T value;
  };
  Slot slots_[N];
  int used_ = 0;
};

// Room for N objects of T left uninitialised, for a packet's scratch arrays, which the code fills
// before it reads them and which are too many to zero on every call. T must be an implicit-
// lifetime type (an aggregate such as accel::Hit), so that the bytes hold T objects as soon as
// they are written.
template <typename T, int N>
class Scratch {
 public:
  static_assert(std::is_trivially_copyable_v<T> && std::is_trivially_destructible_v<T>);
  Scratch() {}
  T* data() { return std::launder(reinterpret_cast<T*>(bytes_)); }
  T& operator[](int i) { return data()[i]; }

 private:
  alignas(T) std::byte bytes_[sizeof(T) * N];
};

// The point lights at a packet's shading points (trace_ahead), a light at a time over arrays of
// the lanes that gather direct light (m of them, packed: entry j is packet lane lane[j]), instead
// of Tracer::light_setup, shadow_ray and light_contribution lane by lane: no calls per lane, and
// loops over plain float arrays. Every entry goes through the float operations of those functions
// in their order (the build forbids contraction), so it gets their bits; the rare entries they
// treat specially (a squared distance below kMinNormal, a term that light_term would clamp) are
// handed to those functions themselves.
template <unsigned kF, int kN>
struct PacketLights {
  using T = Tracer<kF>;
  int m = 0;
  int lane[kN];
  const accel::Hit* hit[kN];
  const MaterialF* mat[kN];
  // The shading points: p, nf and wo, and the origin o of their shadow rays.
  float px[kN], py[kN], pz[kN], fx[kN], fy[kN], fz[kN], wx[kN], wy[kN], wz[kN], ox[kN], oy[kN], oz[kN];
  // The points' error bounds and geometric normals, for the origins.
  float ex[kN], ey[kN], ez[kN], gx[kN], gy[kN], gz[kN];
  // Their materials: Lambert's color * (diffuse / pi), and for the entries in spec_mask the
  // specular lobe's factor specular * (shininess + 8) / (8 pi) and its exponent.
  float lam_r[kN], lam_g[kN], lam_b[kN], spec_scale[kN], shininess[kN];
  std::uint32_t spec_mask = 0;
  // The sums (Tracer::point_direct's), in scene order of the lights.
  float sum_r[kN], sum_g[kN], sum_b[kN];
  // One light: light_setup's LightSample per entry, and the entries set up by light_setup itself.
  float tx[kN], ty[kN], tz[kN], d2[kN], lx[kN], ly[kN], lz[kN], cos_l[kN];
  std::uint32_t slow = 0;

  void add_lane(int i, const accel::Hit& h, const MaterialF& mt, const Vec3f& wo, const Vec3f& nf) {
    const int j = m++;
    lane[j] = i;
    hit[j] = &h;
    mat[j] = &mt;
    px[j] = h.p.x, py[j] = h.p.y, pz[j] = h.p.z;
    fx[j] = nf.x, fy[j] = nf.y, fz[j] = nf.z;
    // For shadow_ray's origin (pad() computes it).
    ex[j] = h.p_error.x, ey[j] = h.p_error.y, ez[j] = h.p_error.z;
    gx[j] = h.n.x, gy[j] = h.n.y, gz[j] = h.n.z;
    wx[j] = wo.x, wy[j] = wo.y, wz[j] = wo.z;
    const float kd = mt.diffuse * kInvPi;  // brdf's first line: color * (diffuse * kInvPi)
    lam_r[j] = mt.color.x * kd, lam_g[j] = mt.color.y * kd, lam_b[j] = mt.color.z * kd;
    if (T::kSpec && mt.specular > 0.0f) {
      spec_mask |= 1u << j;
      spec_scale[j] = mt.specular * (mt.shininess + 8.0f) / (8.0f * std::numbers::pi_v<float>);
      shininess[j] = mt.shininess;
    }
  }

  // Gives the entries from m up to the next multiple of 4 (add() reads them four at a time) a
  // direction, wo and nf of 0; their results are never used. Once, after the last add_lane.
  // Then every entry's shadow-ray origin.
  void pad() {
    for (int j = m; j < ((m + 3) & ~3); ++j) {
      lx[j] = ly[j] = lz[j] = wx[j] = wy[j] = wz[j] = fx[j] = fy[j] = fz[j] = 0.0f;
      px[j] = py[j] = pz[j] = ex[j] = ey[j] = ez[j] = gx[j] = gy[j] = gz[j] = 0.0f;
    }
    // shadow_ray's origin, the same for every light: offset_ray_origin flips the offset where
    // dot(l, n) < 0, and a light that casts has dot(nf, l) > 0 with nf = +-n (exact negation, the
    // same products summed in the same order), so dot(l, n) has the sign of dot(nf, n): the
    // origin leaving in direction nf.
    const float* const p[3] = {px, py, pz};
    const float* const e[3] = {ex, ey, ez};
    const float* const g[3] = {gx, gy, gz};
    const float* const w[3] = {fx, fy, fz};
    float* const o[3] = {ox, oy, oz};
    offset_ray_origins(m, p, e, g, w, o);
    // The sums start at 0, four entries to a store (add() loads them four at a time).
#if defined(__SSE2__)
    for (int j = 0; j < m; j += 4) {
      _mm_storeu_ps(sum_r + j, _mm_setzero_ps());
      _mm_storeu_ps(sum_g + j, _mm_setzero_ps());
      _mm_storeu_ps(sum_b + j, _mm_setzero_ps());
    }
#else
    for (int j = 0; j < m; ++j) sum_r[j] = sum_g[j] = sum_b[j] = 0.0f;
#endif
  }

  // An entry's wo and nf as vectors, for the functions that handle the rare entries (kept as
  // components only: copying whole vectors in add_lane waited on their components' stores).
  Vec3f wo_of(int j) const { return {wx[j], wy[j], wz[j]}; }
  Vec3f nf_of(int j) const { return {fx[j], fy[j], fz[j]}; }

  LightSample sample(int j) const {
    LightSample ls;
    ls.to_light = {tx[j], ty[j], tz[j]};
    ls.l = {lx[j], ly[j], lz[j]};
    ls.dist2 = d2[j];
    ls.cos_l = cos_l[j];
    return ls;
  }

  // light_setup for every entry: returns the entries that cast a shadow ray, written to shadow[j];
  // the other entries' shadow[j] get a default ray, so that the packet queries, which load every
  // lane, read initialised rays (the caller initialises the entries from m on).
  std::uint32_t setup(const PointLightF& light, math::Ray* shadow) {
    const float qx = light.position.x, qy = light.position.y, qz = light.position.z;
    std::uint32_t cast = 0;
    slow = 0;
    // The shadow rays' segments, for the entries that cast.
    float sdx[kN], sdy[kN], sdz[kN], slen[kN];
#if defined(__SSE2__)
    // Four entries at a time, every one from 0 to m (after pad(), all hold values): the entries'
    // square roots and divisions queue at the divider instead of each waiting for the previous
    // entry's (whitted10's render phase went down by 1.9 %, its CPU time by 2.4 %). SSE2's sqrt
    // and division round as the scalar ones do, and the sums go in the same order (no
    // contraction), so every entry gets light_setup's and shadow_ray's bits.
    const __m128 vqx = _mm_set1_ps(qx), vqy = _mm_set1_ps(qy), vqz = _mm_set1_ps(qz);
    const __m128 min_normal = _mm_set1_ps(kMinNormal), zero = _mm_setzero_ps();
    for (int j = 0; j < m; j += 4) {
      const __m128 vx = _mm_sub_ps(vqx, _mm_loadu_ps(px + j));
      const __m128 vy = _mm_sub_ps(vqy, _mm_loadu_ps(py + j));
      const __m128 vz = _mm_sub_ps(vqz, _mm_loadu_ps(pz + j));
      const __m128 dd = _mm_add_ps(_mm_add_ps(_mm_mul_ps(vx, vx), _mm_mul_ps(vy, vy)), _mm_mul_ps(vz, vz));
      _mm_storeu_ps(tx + j, vx), _mm_storeu_ps(ty + j, vy), _mm_storeu_ps(tz + j, vz), _mm_storeu_ps(d2 + j, dd);
      // !(dd >= kMinNormal): at the light, NaN, or unit_towards' double case.
      const __m128 fast = _mm_cmpge_ps(dd, min_normal);
      const __m128 dist = _mm_sqrt_ps(dd);
      // lx = 0 on the slow entries: read by add() (unused) unless light_setup sets it.
      const __m128 ux = _mm_and_ps(fast, _mm_div_ps(vx, dist));
      const __m128 uy = _mm_and_ps(fast, _mm_div_ps(vy, dist));
      const __m128 uz = _mm_and_ps(fast, _mm_div_ps(vz, dist));
      const __m128 c =
          _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_loadu_ps(fx + j), ux), _mm_mul_ps(_mm_loadu_ps(fy + j), uy)),
                     _mm_mul_ps(_mm_loadu_ps(fz + j), uz));
      _mm_storeu_ps(lx + j, ux), _mm_storeu_ps(ly + j, uy), _mm_storeu_ps(lz + j, uz), _mm_storeu_ps(cos_l + j, c);
      const __m128 sx = _mm_sub_ps(vqx, _mm_loadu_ps(ox + j));
      const __m128 sy = _mm_sub_ps(vqy, _mm_loadu_ps(oy + j));
      const __m128 sz = _mm_sub_ps(vqz, _mm_loadu_ps(oz + j));
      const __m128 len =
          _mm_sqrt_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(sx, sx), _mm_mul_ps(sy, sy)), _mm_mul_ps(sz, sz)));
      _mm_storeu_ps(sdx + j, _mm_div_ps(sx, len)), _mm_storeu_ps(sdy + j, _mm_div_ps(sy, len));
      _mm_storeu_ps(sdz + j, _mm_div_ps(sz, len)), _mm_storeu_ps(slen + j, len);
      const std::uint32_t four = std::uint32_t(_mm_movemask_ps(fast));
      slow |= (~four & 0xfu) << j;
      cast |= std::uint32_t(_mm_movemask_ps(_mm_and_ps(fast, _mm_cmpgt_ps(c, zero)))) << j;
    }
    static_assert(kN < 32);
    const std::uint32_t entries = (1u << m) - 1;
    slow &= entries;
    cast &= entries;
#else
    for (int j = 0; j < m; ++j) {
      const float vx = qx - px[j], vy = qy - py[j], vz = qz - pz[j];
      const float dd = vx * vx + vy * vy + vz * vz;
      tx[j] = vx, ty[j] = vy, tz[j] = vz, d2[j] = dd;
      if (!(dd >= kMinNormal)) {  // at the light, NaN, or unit_towards' double case
        slow |= 1u << j;
        lx[j] = ly[j] = lz[j] = 0.0f;  // read by add() (unused) unless light_setup sets it
        continue;
      }
      const float dist = std::sqrt(dd);
      const float ux = vx / dist, uy = vy / dist, uz = vz / dist;
      const float c = fx[j] * ux + fy[j] * uy + fz[j] * uz;
      lx[j] = ux, ly[j] = uy, lz[j] = uz, cos_l[j] = c;
      if (!(c > 0.0f)) continue;
      cast |= 1u << j;
      const float sx = qx - ox[j], sy = qy - oy[j], sz = qz - oz[j];
      const float len = std::sqrt(sx * sx + sy * sy + sz * sz);
      sdx[j] = sx / len, sdy[j] = sy / len, sdz[j] = sz / len, slen[j] = len;
    }
#endif
    for (int j = 0; j < m; ++j) {
      math::Ray& r = shadow[j];
      if (!(cast >> j & 1u)) {
        r = math::Ray{};
        continue;
      }
      // shadow_ray: the origin, then the segment to the light (end 1).
      r.o = {ox[j], oy[j], oz[j]};
      r.d = {sdx[j], sdy[j], sdz[j]};
      r.t_min = 0.0f;
      r.t_max = slen[j] * 1.0f;
    }
    for (std::uint32_t s = slow; s != 0; s &= s - 1) {
      const int j = std::countr_zero(s);
      LightSample ls;
      if (T::light_setup(*hit[j], nf_of(j), light, ls, shadow[j])) {
        cast |= 1u << j;
        tx[j] = ls.to_light.x, ty[j] = ls.to_light.y, tz[j] = ls.to_light.z, d2[j] = ls.dist2;
        lx[j] = ls.l.x, ly[j] = ls.l.y, lz[j] = ls.l.z, cos_l[j] = ls.cos_l;
      }
    }
    return cast;
  }

  // cos_h[j] = max(0, dot(nf, normalize(l + wo))) (brdf's) for the entries in `want` at least. With
  // SSE2 four entries at a time, every one from 0 to m (after pad() and setup(), all hold values):
  // one entry after another, each entry's square root and three divisions queued at the divider
  // (add's share of whitted10's samples went from 6.1 to 4.9 %). SSE2's sqrt and division round
  // as the scalar ones do, and the sums go in the same order (no contraction), so every entry gets
  // brdf's bits.
  void half_cosines(std::uint32_t want, float* cos_h) const {
    if (want == 0) return;
#if defined(__SSE2__)
    const __m128 zero = _mm_setzero_ps();
    const int end = 32 - std::countl_zero(want);  // past the last entry wanted
    for (int j = 0; j < end; j += 4) {
      const __m128 hx = _mm_add_ps(_mm_loadu_ps(lx + j), _mm_loadu_ps(wx + j));
      const __m128 hy = _mm_add_ps(_mm_loadu_ps(ly + j), _mm_loadu_ps(wy + j));
      const __m128 hz = _mm_add_ps(_mm_loadu_ps(lz + j), _mm_loadu_ps(wz + j));
      const __m128 hl = _mm_sqrt_ps(_mm_add_ps(_mm_add_ps(_mm_mul_ps(hx, hx), _mm_mul_ps(hy, hy)), _mm_mul_ps(hz, hz)));
      const __m128 c = _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_loadu_ps(fx + j), _mm_div_ps(hx, hl)),
                                             _mm_mul_ps(_mm_loadu_ps(fy + j), _mm_div_ps(hy, hl))),
                                  _mm_mul_ps(_mm_loadu_ps(fz + j), _mm_div_ps(hz, hl)));
      // std::max(0.0f, c): c where c > 0, else +0 (NaN and -0 too), as maxps(c, 0) has it.
      _mm_storeu_ps(cos_h + j, _mm_max_ps(c, zero));
    }
#else
    for (std::uint32_t s = want; s != 0; s &= s - 1) {
      const int j = std::countr_zero(s);
      const float hx = lx[j] + wx[j], hy = ly[j] + wy[j], hz = lz[j] + wz[j];
      const float hl = std::sqrt(hx * hx + hy * hy + hz * hz);
      const float c = fx[j] * (hx / hl) + fy[j] * (hy / hl) + fz[j] * (hz / hl);
      cos_h[j] = std::max(0.0f, c);
    }
#endif
  }

  // Adds light_contribution(vis[j]) to the sums of the entries in `lit` (set up by setup()).
  void add(const PointLightF& light, std::uint32_t lit, const float* vis) {
    // Zeroed: the four-at-a-time loop below loads the entries that are not lit too (and discards
    // their results), and a load of an unwritten float is undefined.
    float fr[kN] = {}, fg[kN] = {}, fb[kN] = {};
    Scratch<float, kN> pow_x, pow_y;  // the first np entries are written before powf reads them
    int pow_of[kN];
    int np = 0;
    // brdf's half vector: normalize(l + wo), and max(0, dot(nf, h)), for the entries that have a
    // specular lobe and this light.
    float cos_h[kN];
    half_cosines(lit & spec_mask, cos_h);
    for (std::uint32_t s = lit; s != 0; s &= s - 1) {
      const int j = std::countr_zero(s);
      fr[j] = lam_r[j], fg[j] = lam_g[j], fb[j] = lam_b[j];
      if (!(spec_mask >> j & 1u)) continue;
      pow_x[np] = cos_h[j];
      pow_y[np] = shininess[j];
      pow_of[np++] = j;
    }
    math::det::powf(pow_x.data(), pow_y.data(), pow_x.data(), np);
    for (int k = 0; k < np; ++k) {
      const int j = pow_of[k];
      const float spec = spec_scale[j] * pow_x[k];
      fr[j] += spec, fg[j] += spec, fb[j] += spec;
    }
    const float ir = light.intensity.x, ig = light.intensity.y, ib = light.intensity.z;
#if defined(__SSE2__)
    // The terms four entries at a time: one division for four, and no branch per entry (the
    // render phase of whitted10 went down by 2.2 %). The same operations in the same order as the
    // loop of the #else branch; the entries that light_term treats exactly go to it below.
    // fr, fg, fb and vis are loaded entry by entry (they were stored so), the rest four at once.
    const __m128 vir = _mm_set1_ps(ir), vig = _mm_set1_ps(ig), vib = _mm_set1_ps(ib);
    const __m128 min_normal = _mm_set1_ps(kMinNormal), max_term = _mm_set1_ps(kMaxLightTerm);
    const __m128i lane_bits = _mm_setr_epi32(1, 2, 4, 8);
    std::uint32_t exact = 0;
    for (int j = 0; j < m; j += 4) {
      const std::uint32_t four = lit >> j & 0xfu;
      if (four == 0) continue;
      const __m128 in =
          _mm_castsi128_ps(_mm_cmpeq_epi32(_mm_and_si128(_mm_set1_epi32(std::int32_t(four)), lane_bits), lane_bits));
      const __m128 d2j = _mm_loadu_ps(d2 + j);
      const __m128 e =
          _mm_div_ps(_mm_mul_ps(_mm_setr_ps(vis[j], vis[j + 1], vis[j + 2], vis[j + 3]), _mm_loadu_ps(cos_l + j)), d2j);
      const __m128 cr = _mm_mul_ps(_mm_mul_ps(_mm_setr_ps(fr[j], fr[j + 1], fr[j + 2], fr[j + 3]), vir), e);
      const __m128 cg = _mm_mul_ps(_mm_mul_ps(_mm_setr_ps(fg[j], fg[j + 1], fg[j + 2], fg[j + 3]), vig), e);
      const __m128 cb = _mm_mul_ps(_mm_mul_ps(_mm_setr_ps(fb[j], fb[j + 1], fb[j + 2], fb[j + 3]), vib), e);
      const __m128 fast = _mm_and_ps(_mm_and_ps(_mm_cmpge_ps(d2j, min_normal), _mm_cmple_ps(cr, max_term)),
                                     _mm_and_ps(_mm_cmple_ps(cg, max_term), _mm_cmple_ps(cb, max_term)));
      const __m128 add = _mm_and_ps(fast, in);
      const auto accumulate = [&](float* sum, __m128 c) {
        const __m128 old = _mm_loadu_ps(sum + j);
        _mm_storeu_ps(sum + j, _mm_or_ps(_mm_and_ps(add, _mm_add_ps(old, c)), _mm_andnot_ps(add, old)));
      };
      accumulate(sum_r, cr), accumulate(sum_g, cg), accumulate(sum_b, cb);
      exact |= (four & ~std::uint32_t(_mm_movemask_ps(fast))) << j;
    }
    for (std::uint32_t s = exact; s != 0; s &= s - 1) {  // light_term's exact case
      const int j = std::countr_zero(s);
      const Vec3f c = T::light_contribution(*mat[j], wo_of(j), nf_of(j), light, sample(j), vis[j]);
      sum_r[j] += c.x, sum_g[j] += c.y, sum_b[j] += c.z;
    }
#else
    for (std::uint32_t s = lit; s != 0; s &= s - 1) {
      const int j = std::countr_zero(s);
      const float e = vis[j] * cos_l[j] / d2[j];
      const float cr = fr[j] * ir * e, cg = fg[j] * ig * e, cb = fb[j] * ib * e;
      if (d2[j] >= kMinNormal && cr <= kMaxLightTerm && cg <= kMaxLightTerm && cb <= kMaxLightTerm) {
        sum_r[j] += cr, sum_g[j] += cg, sum_b[j] += cb;
      } else {  // light_term's exact case
        const Vec3f c = T::light_contribution(*mat[j], wo_of(j), nf_of(j), light, sample(j), vis[j]);
        sum_r[j] += c.x, sum_g[j] += c.y, sum_b[j] += c.z;
      }
    }
#endif
  }
};

// The packet path traces at most this many rays ahead per lane (camera, mirror and refracted rays
// together); further ones are left to the lanes' tracers. The records live on the stack: 16 lanes
// take 256 of 216 bytes. A glass path of depth 5 casts up to 63 rays, but a level whose
// rays no longer fill packets ends the lookahead anyway (measured on whitted10: 16 per lane
// traced 2.8 M rays ahead, 8 per lane 2.3 M, 4 per lane 1.9 M).
inline constexpr int kAheadPerLane = 16;
// Secondary rays go as a packet only this many or more at a time; fewer are left to the lanes'
// tracers (a packet costs about the same however few of its lanes are live).
inline constexpr int kMinAheadRays = 4;
// The same where the scene has a tree, whose packet walk pays only for fuller packets: half of a
// 16-ray packet (on scenes/mesh.json, AVX-512, 1 thread, render phase against camera rays only:
// 1.11x at 8, 1.10x at 6 and 12, 1.09x at 4; 10-12 pairs each; on AVX2, 4 against 8: 0.99x).
inline constexpr int kMinTreeAheadRays = 8;

// Whether every query tests each shape directly (a scene of under 64 shapes has no tree; see
// accel::Geometry::build): a packet then costs the same whichever way its rays go.
inline bool flat_geometry(const accel::LayeredGeometry& geometry) {
  for (const accel::Layer* layer : {geometry.fixed(), geometry.moving(), geometry.transparent()}) {
    if (layer != nullptr && layer->geometry.stats().wide_nodes > 1) return false;
  }
  return true;
}

// Traces n <= kN rays ahead as one packet, filling their Known records: the nearest hits, then the
// hits' shadow rays towards each point light as packets, one per light: occluded8 when the scene
// is opaque (a pure any-hit query); with transparent objects, Tracer::transmittance_walk crossing
// by crossing, each crossing's nearest hits as one packet query of the lanes still walking (on
// whitted10, shadow rays through its glass spheres cross 2-4 surfaces). With a tree too: walking
// the lanes that go on after the first crossing one by one instead was measured slower on
// scenes/mesh.json, whose glass sphere is a mesh (render phase, 1 thread, AVX-512: 1.036x, 1.051x
// and 1.039x in three runs of 8-10 pairs; 2 threads 1.073x and 0.975x; SSE4 0.99x-1.02x), and
// no faster on a 10,000-sphere field's glass (1.02x-1.05x AVX-512, 0.95x-1.03x SSE4). Over one
// layer of every shape, nearest-hit queries are kept for every shadow ray: an any-hit query over
// everything first (taking the walk only for the rays it found blocked) was measured slower on
// scenes/mesh.json (0.89x-0.92x, 8 pairs per isa and thread count), as 17 % of its shadow rays
// are blocked and pay both queries while a ray nothing blocks costs the same either way. A scene
// split by transparency (RenderScene::build, accel::LayeredGeometry) asks its opaque layer alone
// for any hit, and walks only the rays nothing opaque blocks, over its transparent layer alone.
// Area lights are left to the lanes' tracers, which add them after this sum as the scalar path
// does.
template <unsigned kF, int kN>
void trace_ahead(Tracer<kF>& tracer, Ahead* const* ahead, int n) {
  using T = Tracer<kF>;
  const RenderScene& scene = tracer.scene;
  const accel::LayeredGeometry& geometry = scene.geometry();
  // The packet's rays: the first n written below, the rest default rays (the packet query loads
  // every lane). Not a zeroed array: zeroing all kN rays (512 bytes with 16) on every call, and the
  // shadow rays' below, cost a `rep stos` each, most of them overwritten at once.
  Scratch<math::Ray, kN> rays;
  for (int i = n; i < kN; ++i) rays[i] = math::Ray{};
  Scratch<accel::Hit, kN> hits;
  for (int i = 0; i < n; ++i) {
    Ahead& a = *ahead[i];
    math::Ray& r = a.known.ray;
    if (a.from != nullptr) {
      // Tracer::spawn, written field by field into both copies: a ray built whole and then copied
      // made the copy's wide loads wait for the narrow stores that built it.
      Vec3f o;
      accel::offset_ray_origin_to(a.from->p, a.from->p_error, a.from->n, r.d, o);
      r.o = o;
      r.t_min = 0.0f;
      r.t_max = std::numeric_limits<float>::infinity();
      a.from = nullptr;
      rays[i].o = o;
      rays[i].d = r.d;
      rays[i].t_min = 0.0f;
      rays[i].t_max = std::numeric_limits<float>::infinity();
    } else {
      rays[i] = r;
    }
  }
  const std::uint32_t valid = (1u << n) - 1;
  const bool secondary = ahead[0]->depth > 0;
  tracer.stats.rays += std::uint32_t(n);
  if (secondary) tracer.stats.secondary_packet_rays += std::uint32_t(n);
  const std::uint32_t hit_mask = intersect_packet<kN>(geometry, rays.data(), valid, hits.data()) & valid;

  PacketLights<kF, kN> pl;
  for (int i = 0; i < n; ++i) {
    Known& k = ahead[i]->known;
    k.found = hit_mask >> i & 1u;
    if (!k.found) continue;
    k.hit = hits[i];
    const MaterialF& m = scene.material(hits[i].shape);
    if (!T::wants_direct(m)) continue;
    // A ray that meets an area light before its hit shows the light: Tracer::trace returns
    // there, casting no shadow ray, so none is cast for it here either.
    Vec3f le;
    if (tracer.emitter_before(rays[i], hits[i].t, le)) continue;
    // The same wo and nf as Tracer::trace computes for this hit.
    const Vec3f wo = -rays[i].d;
    const Vec3f nf = math::dot(wo, hits[i].n) >= 0.0f ? hits[i].n : -hits[i].n;
    pl.add_lane(i, k.hit, m, wo, nf);
  }
  if (pl.m == 0) return;
  pl.pad();
  // Entries below pl.m are written by every pl.setup (a default ray where none is cast), the rest
  // here: the packet queries load every lane.
  Scratch<math::Ray, kN> shadow_rays;
  math::Ray* const shadow = shadow_rays.data();
  for (int j = pl.m; j < kN; ++j) shadow[j] = math::Ray{};
  Scratch<accel::Hit, kN> hits_scratch;
  float vis[kN] = {};  // PacketLights::add loads the entries that are not lit too
  const std::size_t point_lights = T::kPoint ? scene.lights().size() : 0;
  for (std::size_t li = 0; li < point_lights; ++li) {
    const PointLightF& light = scene.lights()[li];
    // Entry j of the arrays is lane pl.lane[j]; the packet queries take the entries as lanes.
    const std::uint32_t cast = pl.setup(light, shadow);
    if (cast == 0) continue;
    tracer.stats.rays += std::popcount(cast);
    if (secondary) tracer.stats.secondary_packet_rays += std::popcount(cast);
    // Lights are summed in scene order per lane, as Tracer::point_direct does; a blocked light
    // (visibility 0) adds nothing.
    if (!tracer.transparent_scene()) {
      const std::uint32_t lit = cast & ~occluded_packet<kN>(geometry, shadow, cast);
      for (std::uint32_t s = lit; s != 0; s &= s - 1) vis[std::countr_zero(s)] = 1.0f;
      pl.add(light, lit, vis);
      continue;
    }
    // Tracer::transmittance_walk for the entries in `cast`, crossing by crossing: each crossing's
    // queries go as one packet of the entries still walking (the same queries, each entry's
    // crossings in its order, through the same Tracer::shadow_crossing). In a scene split by
    // transparency, as Tracer::transmittance: the opaque layer's any-hit query first, then the
    // walk of the entries it leaves over the transparent layer only.
    const bool clear = geometry.transparent() != nullptr;
    std::uint32_t open = cast;
    if (clear) {
      tracer.stats.opaque_first_rays += std::popcount(cast);
      open = cast & ~geometry.template occluded_opaque<kN>(shadow, cast);
      // The walk's first query of an entry is counted with its opaque query (Tracer::transmittance).
      if (open == 0) continue;  // every entry blocked: the light adds nothing
    }
    // The nearest hits of the entries in `on` (a query over every shape, or the transparent layer's
    // with its ids made the scene's).
    const auto nearest = [&](std::uint32_t on) {
      if (!clear) return intersect_packet<kN>(geometry, shadow, on, hits_scratch.data()) & on;
      return geometry.template intersect_transparent<kN>(shadow, on, hits_scratch.data()) & on;
    };
    std::uint32_t lit = 0;
    std::uint32_t walking = nearest(open);
    for (std::uint32_t s = open & ~walking; s != 0; s &= s - 1) vis[std::countr_zero(s)] = 1.0f;
    lit |= open & ~walking;
    Scratch<MediumStack, kN> media;  // written for the entries that walk before they are read
    for (std::uint32_t s = walking; s != 0; s &= s - 1) {
      const int j = std::countr_zero(s);
      // The hit is seen from the media its ray travels in, as Tracer::trace has it.
      media[j] = *ahead[pl.lane[j]]->media;
      vis[j] = 1.0f;
    }
    for (int crossing = 0; walking != 0; ++crossing) {
      std::uint32_t on = 0;  // the entries that pass this crossing
      for (std::uint32_t s = walking; s != 0; s &= s - 1) {
        const int j = std::countr_zero(s);
        if (tracer.shadow_crossing(hits_scratch[j], shadow[j], media[j], vis[j])) {
          on |= 1u << j;
        } else {
          vis[j] = 0.0f;
        }
      }
      if (on == 0) break;
      if (crossing + 1 >= kMaxShadowCrossings) {  // the walk's bound: counted as blocked
        for (std::uint32_t s = on; s != 0; s &= s - 1) vis[std::countr_zero(s)] = 0.0f;
        break;
      }
      tracer.stats.rays += std::popcount(on);
      if (secondary) tracer.stats.secondary_packet_rays += std::popcount(on);
      walking = nearest(on);
      lit |= on & ~walking;  // reached the light through every crossing: vis[j] = t > 0
    }
    pl.add(light, lit, vis);
  }
  for (int j = 0; j < pl.m; ++j) {
    Known& k = ahead[pl.lane[j]]->known;
    k.has_direct = true;
    k.direct = Vec3f{pl.sum_r[j], pl.sum_g[j], pl.sum_b[j]};
  }
}

// The packet path: the camera rays and their first hits' point-light shadow rays as packets, then
// level by level the mirror and refracted rays those hits cast (and their shadow rays), as long as
// enough of them remain for a packet; then each lane's tracer follows its path with what was found
// (Known), tracing the rest one ray at a time. The rays ahead are the ones Tracer::trace casts (the
// same Tracer::branches decides them), so every lane gets the scalar path's bits and ray count.
template <unsigned kF, int kN>
void trace_packet_with(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* keys,
                       std::uint32_t valid, const TraceLimits& limits, TraceStats& stats, Vec3f* out) {
  using T = Tracer<kF>;
  T tracer{scene, limits, stats};
  const MediumStack camera_media = tracer.camera_media();
  const bool flat = flat_geometry(scene.geometry());
  // Secondary levels go as packets where there is no tree, and in a scene with one on the 16-ray
  // path (AVX2 and AVX-512). Measured against camera rays only, render phase, 1 thread, median of
  // per-pair ratios: scenes/mesh.json 1.11x on AVX-512 (12 pairs), 1.03x on AVX2 (process CPU
  // 1.05x; 8 pairs); the 10,000-sphere field 1.02x at 1 spp (11 pairs) and 1.07x adaptive (-s 16,
  // 5 pairs). On a quiet machine, base and this alternated, 6 pairs: scenes/mesh.json 1.14x on 1
  // and 2 threads, with the shadow walk below. The 8-ray path (SSE4) lost 1.5-2.5 % on
  // scenes/mesh.json, so it leaves them to the lanes' tracers. Stopping after the first bounce
  // gave 1.06-1.08x; grouping a level's rays by direction octant first, against this: 1.00x on
  // scenes/mesh.json, 0.96x on the sphere field (-s 16 adaptive).
  const bool ahead_levels = flat || kN == accel::kPacketSize16;
  const int min_secondary = flat ? kMinAheadRays : kMinTreeAheadRays;
  constexpr int kCapacity = kN * kAheadPerLane;

  Slots<Ahead, kCapacity> pool;
  // The rays of one level, and the next level's mirror and refracted rays.
  Ahead* level[kCapacity];
  Ahead* mirrors[kCapacity];
  Ahead* refracts[kCapacity];
  const Known* lane_known[kN] = {};
  int count = 0;
  for (int i = 0; i < kN; ++i) {
    if (!(valid >> i & 1u)) continue;
    Ahead* a = pool.emplace(rays[i], nullptr, &camera_media, 0u, 1.0f, nullptr);
    lane_known[i] = &a->known;
    level[count++] = a;
  }
  while (count > 0) {
    // Packets of the level's rays: the camera rays always; secondary rays (see ahead_levels) only
    // when enough of them go together. The rest are left to the lanes' tracers.
    int kept = 0;
    for (int j = 0; j < count;) {
      const int end = std::min(count, j + kN);
      const int n = end - j;
      if (level[j]->depth > 0 && n < min_secondary) {
        for (int r = j; r < end; ++r) *level[r]->link = nullptr;
      } else {
        trace_ahead<kF, kN>(tracer, level + j, n);
        std::copy(level + j, level + end, level + kept);
        kept += n;
      }
      j = end;
    }
    count = kept;
    if (!ahead_levels) break;

    // The rays the hits cast, mirror rays first, then refracted ones: rays of one kind together.
    int nm = 0, nr = 0;
    for (int j = 0; j < count && !pool.full(); ++j) {
      Ahead& a = *level[j];
      Known& k = a.known;
      if (!k.found) continue;
      if constexpr (T::kArea) {
        Vec3f le;
        if (tracer.emitter_before(k.ray, k.hit.t, le)) continue;  // trace() returns the light
      }
      const MaterialF& m = scene.material(k.hit.shape);
      const Vec3f wo = -k.ray.d;
      const Vec3f nf = math::dot(wo, k.hit.n) >= 0.0f ? k.hit.n : -k.hit.n;
      const typename T::Branches b = tracer.branches(k.hit, m, wo, nf, a.depth, a.weight, *a.media);
      if (b.mirror && !pool.full()) {
        Ahead* c =
            pool.emplace(T::mirror_direction(k.ray, nf), &k.hit, a.media, a.depth + 1, b.mirror_weight, &k.mirror);
        k.mirror = &c->known;
        mirrors[nm++] = c;
      }
      if (b.refract && !pool.full()) {
        Ahead* c = pool.emplace(refracted_direction(wo, nf, b.eta, b.it), &k.hit, b.inside, a.depth + 1,
                                b.refract_weight, &k.refracted);
        k.refracted = &c->known;
        refracts[nr++] = c;
      }
    }
    std::copy(mirrors, mirrors + nm, level);
    std::copy(refracts, refracts + nr, level + nm);
    count = nm + nr;
  }

  for (int i = 0; i < kN; ++i) {
    if (!(valid >> i & 1u)) continue;
    // Each lane's own random numbers, from the first dimension on, as trace_radiance has them.
    T lane{scene, limits, stats, keys[i]};
    lane.trace_to(out[i], rays[i], 0, 1.0f, camera_media, lane_known[i]);
  }
}

// One feature set's three paths. A set no scene has (derivable() false) has none: the dispatch
// sends it to kAllFeatures, which models everything.
using RadianceFn = Vec3f (*)(const RenderScene&, const math::Ray&, const math::SampleKey&, const TraceLimits&,
                             TraceStats&);
using RadiancePacketFn = void (*)(const RenderScene&, const math::Ray*, const math::SampleKey*, std::uint32_t,
                                  const TraceLimits&, TraceStats&, Vec3f*);
struct PathFns {
  RadianceFn one = nullptr;
  RadiancePacketFn eight = nullptr;
  RadiancePacketFn sixteen = nullptr;
};

// Whether some scene has feature set kF: point lights always cast shadows, and shadows need a
// light. The 24 other sets of the 64 are never derived; they get no instantiation (compile time).
constexpr bool derivable(unsigned kF) {
  const bool point = (kF & kPointLights) != 0, area = (kF & kAreaLights) != 0, shadows = (kF & kShadows) != 0;
  return (!point || shadows) && (!shadows || point || area);
}
static_assert(derivable(kAllFeatures) && derivable(0));

template <unsigned kF>
constexpr PathFns path_fns() {
  if constexpr (derivable(kF)) {
    return {&trace_radiance_with<kF>, &trace_packet_with<kF, accel::kPacketSize>,
            &trace_packet_with<kF, accel::kPacketSize16>};
  } else {
    return {};
  }
}

// The paths of feature sets kBase to kBase + sizeof...(I) - 1.
template <unsigned kBase, std::size_t... I>
constexpr std::array<PathFns, sizeof...(I)> path_table(std::index_sequence<I...>) {
  return {path_fns<kBase + unsigned(I)>()...};
}

// The paths of a derivable feature set without point lights (integrator.cpp) and with them
// (integrator_lit.cpp).
PathFns unlit_paths(unsigned features);
PathFns lit_paths(unsigned features);

}  // namespace dtraced::render::paths
