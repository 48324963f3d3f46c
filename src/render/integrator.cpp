#include "render/integrator.h"

#include <cassert>
#include <utility>

#include "render/integrator_paths.h"

namespace dtraced::render {

namespace paths {

PathFns unlit_paths(unsigned features) {
  static constexpr auto kTable = path_table<0>(std::make_index_sequence<kPointLights>{});
  assert(features < kPointLights);
  return kTable[features];
}

}  // namespace paths

namespace {

// The paths for this scene: its own feature set's with `specialise`, else the ones that model
// every feature.
paths::PathFns scene_paths(const RenderScene& scene, const TraceLimits& limits) {
  unsigned features = limits.specialise ? paths::feature_bits(scene.features()) : paths::kAllFeatures;
  if (!paths::derivable(features)) features = paths::kAllFeatures;
  return (features & paths::kPointLights) != 0 ? paths::lit_paths(features) : paths::unlit_paths(features);
}

}  // namespace

Vec3f trace_radiance(const RenderScene& scene, const math::Ray& ray, const math::SampleKey& key,
                     const TraceLimits& limits, TraceStats& stats) {
  return scene_paths(scene, limits).one(scene, ray, key, limits, stats);
}

void trace_radiance8(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* keys, std::uint32_t valid,
                     const TraceLimits& limits, TraceStats& stats, Vec3f* out) {
  valid &= (1u << accel::kPacketSize) - 1;
  if (valid == 0) return;
  scene_paths(scene, limits).eight(scene, rays, keys, valid, limits, stats, out);
}

void trace_radiance16(const RenderScene& scene, const math::Ray* rays, const math::SampleKey* keys, std::uint32_t valid,
                      const TraceLimits& limits, TraceStats& stats, Vec3f* out) {
  valid &= (1u << accel::kPacketSize16) - 1;
  if (valid == 0) return;
  scene_paths(scene, limits).sixteen(scene, rays, keys, valid, limits, stats, out);
}

}  // namespace dtraced::render
