// dtraced::render Whitted integrator (scalar reference path).
//
// Direct light from point lights with hard shadows, Lambert diffuse plus normalised Blinn-Phong
// specular, mirror reflection, and dielectric refraction with exact Fresnel and total internal
// reflection. Nested and touching transparent objects are handled with a small per-path stack
// of the media the path is inside. Pure function of (scene, ray, settings): thread-safe.
#pragma once

#include <cstdint>

#include "math/ray.h"
#include "render/render_scene.h"

namespace dtraced::render {

struct TraceStats {
  std::uint64_t rays = 0;         // every ray cast: camera, secondary, shadow segments
  std::uint64_t nan_samples = 0;  // samples whose radiance had a NaN (zeroed at the film)
  std::uint64_t inf_samples = 0;  // samples whose radiance had an Inf (zeroed at the film)
  void add(const TraceStats& o) {
    rays += o.rays;
    nan_samples += o.nan_samples;
    inf_samples += o.inf_samples;
  }
};

struct TraceLimits {
  Vec3f background;
  std::uint32_t max_depth = 8;
};

// Radiance arriving along `ray` (a camera ray).
Vec3f trace_radiance(const RenderScene& scene, const math::Ray& ray, const TraceLimits& limits, TraceStats& stats);

}  // namespace dtraced::render
