// dtraced::render Whitted integrator.
//
// Direct light from point lights with hard shadows and from sphere, disk and rect area lights
// with soft shadows (Monte Carlo: `samples` shadow rays per light and shading point, uniform over
// a sphere's cone of directions or a disk's or rect's area), Lambert diffuse plus normalised
// Blinn-Phong specular, mirror reflection, and dielectric refraction with exact Fresnel and total
// internal reflection. A hit casts at most one mirror ray, carrying the summed weight of every lobe
// that reflects in that direction (the material's `reflectivity` and, on glass, the Fresnel
// reflection), and no branch lighter than TraceLimits::min_branch_weight. Area-light samples are
// stratified across a pixel's samples (render/sampler.h). Nested and touching transparent objects
// are handled with a small per-path stack of the media the path is inside; camera paths start
// inside the media that contain the camera (RenderScene::camera_media). Camera, mirror and
// refracted rays that reach an area light's emitting side before any surface return its radiance
// Le. Pure function of (scene, ray, sample key, settings): thread-safe.
//
// Each call runs a path specialised to the scene's features (RenderScene::features: code for a
// feature the scene lacks is compiled out), or with TraceLimits::specialise false the generic
// path; both give the same bits.
//
// trace_radiance follows one camera ray; trace_radiance8 and trace_radiance16 follow up to 8 or 16
// together, tracing their first hits (and the point lights' shadow rays there) as packets, then
// level by level the mirror and refracted rays those hits cast (and their point-light shadow
// rays) as packets while enough of them go together, and everything after per ray. All give
// every ray the same bits and count the same rays.
#pragma once

#include <cstdint>

#include "math/ray.h"
#include "math/rng.h"
#include "render/render_scene.h"

namespace dtraced::render {

struct TraceStats {
  std::uint64_t rays = 0;         // every ray cast for the pixels: camera, secondary, shadow segments
  std::uint64_t nan_samples = 0;  // samples whose radiance had a NaN (zeroed at the film)
  std::uint64_t inf_samples = 0;  // samples whose radiance had an Inf (zeroed at the film)
  // Rays cast for the one-pixel border around a tile that adaptive sampling's first checkpoint
  // reads (render/tile.h); not in `rays`, which stays the same whatever the tiling.
  std::uint64_t border_rays = 0;
  // Of `rays`: mirror and refracted rays, and their point-light shadow rays, that the packet path
  // traced as packets (trace_radiance8/16); 0 on the per-ray path. What the packets reach, for
  // tests and profiles; not part of a render's result.
  std::uint64_t secondary_packet_rays = 0;
  // Of `rays`: the shadow rays of a scene split by transparency (accel::LayeredGeometry) that
  // first asked the opaque layer for any hit. Each counts as one ray with its first query of the
  // transparent layer, and one more for each crossing after which it goes on, as the walk over
  // every shape counts its segments; a blocked ray is one. The same on both paths.
  std::uint64_t opaque_first_rays = 0;
  std::uint64_t all_rays() const { return rays + border_rays; }
  void add(const TraceStats& o) {
    rays += o.rays;
    secondary_packet_rays += o.secondary_packet_rays;
    opaque_first_rays += o.opaque_first_rays;
    nan_samples += o.nan_samples;
    inf_samples += o.inf_samples;
    border_rays += o.border_rays;
  }
};

struct TraceLimits {
  Vec3f background;
  std::uint32_t max_depth = 8;
  // A reflected, refracted or see-through branch whose weight on the pixel (the product of the
  // reflectances and transmittances along its path, at most 1) falls below this is not traced
  // (RenderSettings::branch_cutoff). It only loses light: at most this fraction of the radiance
  // arriving along the branch.
  float min_branch_weight = 1e-6f;
  // Run the path specialised to the scene's features (RenderScene::features); false runs the
  // generic path, which renders the same bits (the tests and the benchmark compare them).
  bool specialise = true;
};

// The most one light (or one area-light sample) adds to a shading point's radiance per channel.
// A point light a hair's breadth from a surface gives I / d^2 beyond float's range; the term is
// clamped here instead, far above anything a display or an image format tells apart, and far
// enough below FLT_MAX (2^128) that a path's sum over every light (scene::kMaxLights, 10^4 <
// 2^14) stays finite. A light whose own intensity is beyond float (+Inf) is not clamped: its
// samples are Inf, dropped and counted at the film as before.
inline constexpr float kMaxLightTerm = 0x1p100f;

// Random-number dimensions of a camera sample: the film position takes the first two; the
// integrator draws from kFirstIntegratorDim on, in a fixed order along the path.
inline constexpr std::uint32_t kFirstIntegratorDim = 2;

// Radiance arriving along `ray` (a camera ray) of the pixel sample `key`, whose random numbers
// (area-light samples) it draws.
Vec3f trace_radiance(const RenderScene& scene, const math::Ray& ray, const math::SampleKey& key,
                     const TraceLimits& limits, TraceStats& stats);

// Radiance along the camera rays rays[i] (pixel samples keys[i]) for each bit i set in `valid` (bits >= kPacketSize are
// ignored), written to out[i]; other entries of `out` are left alone. out[i] is bitwise equal to
// trace_radiance(rays[i], keys[i]) and `stats` counts the same rays. Coherent rays (one pixel block) are
// what it is for.
void trace_radiance8(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* keys, std::uint32_t valid,
                     const TraceLimits& limits, TraceStats& stats, Vec3f* out);

// The same for up to 16 rays (bits >= kPacketSize16 ignored), e.g. a 4x4 pixel block: one
// accel::Geometry::intersect16 / occluded16 query per packet and layer on a static scene (one
// layer, or an opaque and a transparent one; AVX-512 tests a node against 16 rays in one
// vector), two 8-ray halves on a frame with moving objects.
void trace_radiance16(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* keys, std::uint32_t valid,
                      const TraceLimits& limits, TraceStats& stats, Vec3f* out);

}  // namespace dtraced::render
