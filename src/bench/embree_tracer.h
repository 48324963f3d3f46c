// dtraced-bench-rays' Embree 3 backend: the reference library the ray benchmark compares our
// traversal with. Compiled only when CMake's DTRACED_BENCH_EMBREE is on; the product never links
// Embree.
//
// Owns one RTCDevice and one committed RTCScene holding the same primitives as an accel::Geometry:
// spheres as RTC_GEOMETRY_TYPE_SPHERE_POINT (x, y, z, r) and triangles as RTC_GEOMETRY_TYPE_TRIANGLE
// (three vertices of their own per triangle, as our Shape stores them). Boxes and planes have no
// Embree primitive: they are left out and counted in `skipped`, and the benchmark's scenes contain
// none of them.
//
// Every call traces up to 8 rays (one of the benchmark's packets; 16, two packets, for the *16
// calls) and writes, per valid lane, the
// index of the Shape that was hit (kMissId on a miss) or 1/0 for occluded/free. Invalid lanes are
// left alone.
// Thread-safety: immutable after build; any number of threads may trace at once (rtcIntersect* and
// rtcOccluded* are thread-safe on a committed scene).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "accel/geometry.h"
#include "math/ray.h"
#include "util/result.h"

namespace dtraced::bench {

inline constexpr std::uint32_t kMissId = 0xffffffffu;

enum class EmbreeQuality { kLow, kMedium, kHigh };

class EmbreeTracer {
 public:
  // Builds the scene with the given RTC_BUILD_QUALITY_*. `build_threads` = 0 lets Embree use every
  // hardware thread for the build (its default). Fails with Embree's message.
  static util::Result<std::unique_ptr<EmbreeTracer>> build(const std::vector<accel::Shape>& shapes,
                                                           EmbreeQuality quality, std::uint32_t build_threads);
  ~EmbreeTracer();
  EmbreeTracer(const EmbreeTracer&) = delete;
  EmbreeTracer& operator=(const EmbreeTracer&) = delete;

  // rtcIntersect1 per valid lane; `coherent` sets RTC_INTERSECT_CONTEXT_FLAG_COHERENT.
  void intersect1(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const;
  // One rtcIntersect8 call (valid lanes as the valid mask).
  void intersect8(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const;
  // rtcOccluded1 per valid lane / one rtcOccluded8 call; writes 1 (occluded) or 0.
  void occluded1(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const;
  void occluded8(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const;
  // One rtcIntersect16 / rtcOccluded16 call on 16 rays (two of the benchmark's packets).
  void intersect16(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const;
  void occluded16(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const;

  double build_seconds() const { return build_seconds_; }  // wall time of rtcCommitScene
  std::size_t skipped() const { return skipped_; }         // boxes and planes left out
  static std::string version();                            // "3.13.5"

 private:
  EmbreeTracer() = default;
  struct Impl;
  std::unique_ptr<Impl> impl_;
  double build_seconds_ = 0.0;
  std::size_t skipped_ = 0;
};

std::string_view embree_quality_name(EmbreeQuality q);

}  // namespace dtraced::bench
