// dtraced::accel two-level geometry: the shapes of a scene in one layer (a static scene) or in two:
// for an animation, the shapes that do not move, built once and shared by every frame, and the
// few that move, built per frame; for a static scene with opaque and transparent shapes, the
// opaque ones and the transparent ones, so that a shadow ray asks the opaque layer for any hit
// and walks its crossings over the transparent layer only.
//
// Owns: Layer (a Geometry and the scene-wide id of each of its shapes) and LayeredGeometry, which
// answers the queries of Geometry over its layers. No transforms: both layers are in scene space,
// so a query is the nearest hit (or any hit) over the two BVHs.
//
// Contract: every query answers exactly what Geometry::build over all the scene's shapes, in
// scene-wide id order, would answer (same shape, same t bits, same hit record): the nearest hit of
// either layer wins, and a tie in t goes to the smaller scene-wide id, as within one Geometry.
// With one layer (a static scene) the queries are that Geometry's own, through one branch.
// A static scene split by transparency keeps its opaque layer's ids implicit: that layer holds
// every shape of the scene at its own id, the transparent ones replaced by shapes never hit (a
// sphere of radius 0, which the build leaves out of the tree), so its shapes() has the scene's
// count and no id array or id mapping is needed for the many opaque shapes.
//
// Thread-safety: immutable once built; any number of threads may query it at once. Layers are
// shared (shared_ptr<const Layer>) by the frames that use them.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "accel/geometry.h"

namespace dtraced::accel {

namespace detail {
// Geometry's nearest-hit and any-hit queries of N rays (kPacketSize or kPacketSize16) at once.
template <int N>
std::uint32_t intersect_n(const Geometry& g, const Ray* rays, std::uint32_t valid, Hit* hits) {
  static_assert(N == kPacketSize || N == kPacketSize16);
  if constexpr (N == kPacketSize16) {
    return g.intersect16(rays, valid, hits);
  } else {
    return g.intersect8(rays, valid, hits);
  }
}
template <int N>
std::uint32_t occluded_n(const Geometry& g, const Ray* rays, std::uint32_t valid) {
  static_assert(N == kPacketSize || N == kPacketSize16);
  if constexpr (N == kPacketSize16) {
    return g.occluded16(rays, valid);
  } else {
    return g.occluded8(rays, valid);
  }
}
}  // namespace detail

// Shapes of some of a scene's objects, with their BVH.
struct Layer {
  // `ids[i]` is the scene-wide id of shapes[i]; strictly increasing, so that a layer's own tie
  // break (smallest index) is the scene's. Empty `ids` means shapes[i] has id i (one layer).
  // The BVH on up to `threads` threads (Geometry::build; 0: the CPUs this process may use).
  static std::shared_ptr<const Layer> build(std::vector<Shape> shapes, std::vector<std::uint32_t> ids, Isa isa,
                                            unsigned threads = 0);

  Geometry geometry;
  std::vector<std::uint32_t> ids;

  std::uint32_t scene_id(std::uint32_t local) const { return ids.empty() ? local : ids[local]; }
};

class LayeredGeometry {
 public:
  // No shapes: every query misses.
  LayeredGeometry() : LayeredGeometry(Geometry{}) {}
  // A static scene: one Geometry over every shape, ids as given to it.
  explicit LayeredGeometry(Geometry whole);
  // A frame of an animated scene: the layer shared by every frame and the frame's own (either may
  // be null or empty; both non-null layers have non-empty ids). `shape_count` is the scene's.
  LayeredGeometry(std::shared_ptr<const Layer> fixed, std::shared_ptr<const Layer> moving, std::size_t shape_count);
  // A static scene split by transparency: `opaque` over every shape, the transparent ones replaced
  // by hole() (so its ids are the scene's), and `transparent` those shapes with their ids (non-empty).
  LayeredGeometry(Geometry opaque, std::shared_ptr<const Layer> transparent);
  // The shape that stands for a transparent one in the opaque layer: a sphere of radius 0, which
  // no ray hits and the build leaves out of the tree.
  static Shape hole();

  // Geometry's queries (see accel/geometry.h), over every layer; hit.shape is the scene-wide id.
  // Inline so that one layer costs a static scene one branch over calling its Geometry.
  bool intersect(const Ray& ray, Hit& hit) const {
    return second_ == nullptr ? first_->geometry.intersect(ray, hit) : intersect_layers(ray, hit);
  }
  bool occluded(const Ray& ray) const {
    return second_ == nullptr ? first_->geometry.occluded(ray) : occluded_layers(ray);
  }
  std::uint32_t intersect8(const Ray* rays, std::uint32_t valid, Hit* hits) const {
    return second_ == nullptr ? first_->geometry.intersect8(rays, valid, hits) : intersect8_layers(rays, valid, hits);
  }
  std::uint32_t occluded8(const Ray* rays, std::uint32_t valid) const {
    return second_ == nullptr ? first_->geometry.occluded8(rays, valid) : occluded8_layers(rays, valid);
  }
  // The 16-ray queries (SIMD isas): each layer's own 16-ray query, then the merge, so a packet
  // stays 16 wide over two layers.
  std::uint32_t intersect16(const Ray* rays, std::uint32_t valid, Hit* hits) const {
    return second_ == nullptr ? first_->geometry.intersect16(rays, valid, hits)
                              : intersect_n_layers<kPacketSize16>(rays, valid, hits);
  }
  std::uint32_t occluded16(const Ray* rays, std::uint32_t valid) const {
    return second_ == nullptr ? first_->geometry.occluded16(rays, valid)
                              : occluded_n_layers<kPacketSize16>(rays, valid);
  }

  // A static scene split by transparency (transparent() not null): any hit over the opaque layer
  // alone, and the nearest hit over the transparent layer alone (hit.shape scene-wide), 1, 8 or
  // 16 (kPacketSize16) rays; what a shadow ray asks (render/integrator_paths.h).
  bool occluded_opaque(const Ray& ray) const { return first_->geometry.occluded(ray); }
  template <int N>
  std::uint32_t occluded_opaque(const Ray* rays, std::uint32_t valid) const {
    return detail::occluded_n<N>(first_->geometry, rays, valid);
  }
  bool intersect_transparent(const Ray& ray, Hit& hit) const;
  template <int N>
  std::uint32_t intersect_transparent(const Ray* rays, std::uint32_t valid, Hit* hits) const;

  // The shape with scene-wide id `id` < shape_count().
  const Shape& shape(std::uint32_t id) const;
  std::size_t shape_count() const { return shape_count_; }
  // The kernels every layer walks with.
  Isa isa() const { return isa_; }
  // The layers: one (`fixed`, holding every shape) for a static scene; null where absent. A static
  // scene split by transparency has `fixed` the opaque layer (every id, the transparent shapes
  // holes) and `transparent` the other; a frame of an animation has `fixed` and `moving`.
  const Layer* fixed() const { return fixed_.get(); }
  const Layer* moving() const { return moving_.get(); }
  const Layer* transparent() const { return transparent_.get(); }

 private:
  // The queries over two layers.
  bool intersect_layers(const Ray& ray, Hit& hit) const;
  bool occluded_layers(const Ray& ray) const;
  std::uint32_t intersect8_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  std::uint32_t occluded8_layers(const Ray* rays, std::uint32_t valid) const;
  template <int N>
  std::uint32_t intersect_n_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  template <int N>
  std::uint32_t occluded_n_layers(const Ray* rays, std::uint32_t valid) const;
  // The second layer's nearest hits of the lanes `reach` (already past its cull), with scene-wide
  // ids: the transparent layer's query, and the second half of the queries over both layers.
  template <int N>
  std::uint32_t second_hits(const Ray* rays, std::uint32_t reach, Hit* hits) const;
  // Whether the ray may meet the second layer's bounding sphere (always true unless cull_): a
  // query of that layer for a ray that cannot is skipped.
  bool may_reach_second(const Ray& ray) const;
  template <int N>
  std::uint32_t reach_second(const Ray* rays, std::uint32_t valid) const;
  bool reach(float ox, float oy, float oz, float dx, float dy, float dz, float t_min) const;

  // With one layer, first_ holds it and second_ is null; otherwise both are set.
  const Layer* first_ = nullptr;
  const Layer* second_ = nullptr;
  std::shared_ptr<const Layer> fixed_;
  std::shared_ptr<const Layer> moving_;
  std::shared_ptr<const Layer> transparent_;
  // A sphere around a split scene's transparent layer (see may_reach_second); cull_ false where
  // that layer is unbounded (a plane), or the scene not split. Without it, a query of the
  // transparent layer for every ray cost about what the opaque layer's any-hit queries saved:
  // scenes/mesh.json's render phase 1.01x against one layer (AVX-512, 1 thread, 5 pairs); with a
  // slab test in double per ray 0.97x; with this sphere, four rays at a time, 1.05x (6 pairs).
  bool cull_ = false;
  float center_[3] = {0, 0, 0};
  float radius2_ = 0.0f;
  std::size_t shape_count_ = 0;
  Isa isa_ = Isa::kScalar;
};

}  // namespace dtraced::accel
