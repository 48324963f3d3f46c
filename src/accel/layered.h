// dtraced::accel two-level geometry: the shapes of a scene in one layer (a static scene) or in two,
// the shapes that do not move over an animation, built once and shared by every frame, and the
// few that move, built per frame.
//
// Owns: Layer (a Geometry and the scene-wide id of each of its shapes) and LayeredGeometry, which
// answers the queries of Geometry over its layers. No transforms: both layers are in scene space,
// so a query is the nearest hit (or any hit) over the two BVHs.
//
// Contract: every query answers exactly what Geometry::build over all the scene's shapes, in
// scene-wide id order, would answer (same shape, same t bits, same hit record): the nearest hit of
// either layer wins, and a tie in t goes to the smaller scene-wide id, as within one Geometry.
// With one layer (a static scene) the queries are that Geometry's own, through one branch.
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

  // The shape with scene-wide id `id` < shape_count().
  const Shape& shape(std::uint32_t id) const;
  std::size_t shape_count() const { return shape_count_; }
  // The kernels every layer walks with.
  Isa isa() const { return isa_; }
  // The layers: one (`fixed`, holding every shape) for a static scene; null where absent.
  const Layer* fixed() const { return fixed_.get(); }
  const Layer* moving() const { return moving_.get(); }

 private:
  // The queries over two layers.
  bool intersect_layers(const Ray& ray, Hit& hit) const;
  bool occluded_layers(const Ray& ray) const;
  std::uint32_t intersect8_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  std::uint32_t occluded8_layers(const Ray* rays, std::uint32_t valid) const;

  // With one layer, first_ holds it and second_ is null; otherwise both are set.
  const Layer* first_ = nullptr;
  const Layer* second_ = nullptr;
  std::shared_ptr<const Layer> fixed_;
  std::shared_ptr<const Layer> moving_;
  std::size_t shape_count_ = 0;
  Isa isa_ = Isa::kScalar;
};

}  // namespace dtraced::accel
