#include "accel/layered.h"

#include <algorithm>
#include <cassert>
#include <utility>

#include "math/float_util.h"

namespace dtraced::accel {

namespace {

bool empty(const std::shared_ptr<const Layer>& layer) { return !layer || layer->geometry.shapes().empty(); }

// Whether hit `b` (of another layer) beats `a`: nearer, or as near with a smaller id. Both carry
// scene-wide ids.
bool better(const Hit& b, const Hit& a) { return b.t < a.t || (b.t == a.t && b.shape < a.shape); }

}  // namespace

std::shared_ptr<const Layer> Layer::build(std::vector<Shape> shapes, std::vector<std::uint32_t> ids, Isa isa,
                                          unsigned threads) {
  assert(ids.empty() || ids.size() == shapes.size());
  assert(std::is_sorted(ids.begin(), ids.end()) && std::adjacent_find(ids.begin(), ids.end()) == ids.end());
  auto layer = std::make_shared<Layer>();
  layer->geometry = Geometry::build(std::move(shapes), isa, threads);
  layer->ids = std::move(ids);
  return layer;
}

LayeredGeometry::LayeredGeometry(Geometry whole) : shape_count_(whole.shapes().size()), isa_(whole.isa()) {
  auto layer = std::make_shared<Layer>();
  layer->geometry = std::move(whole);
  fixed_ = std::move(layer);
  first_ = fixed_.get();
}

LayeredGeometry::LayeredGeometry(std::shared_ptr<const Layer> fixed, std::shared_ptr<const Layer> moving,
                                 std::size_t shape_count)
    : fixed_(std::move(fixed)), moving_(std::move(moving)), shape_count_(shape_count) {
  assert(!fixed_ || !moving_ || fixed_->geometry.isa() == moving_->geometry.isa());
  const std::size_t held =
      (fixed_ ? fixed_->geometry.shapes().size() : 0) + (moving_ ? moving_->geometry.shapes().size() : 0);
  assert(held == shape_count);
  (void)held;
  // An empty layer is skipped; the one left then holds every shape, so its ids are 0..n-1 and the
  // one-layer path (no id mapping) answers for it.
  if (!empty(fixed_) && !empty(moving_)) {
    first_ = fixed_.get();
    second_ = moving_.get();
  } else if (!empty(moving_)) {
    first_ = moving_.get();
  } else {
    if (!fixed_) fixed_ = Layer::build({}, {}, moving_ ? moving_->geometry.isa() : Isa::kScalar);
    first_ = fixed_.get();
  }
  isa_ = first_->geometry.isa();
}

bool LayeredGeometry::intersect_layers(const Ray& ray, Hit& hit) const {
  const bool found = first_->geometry.intersect(ray, hit);
  Ray rest = ray;
  if (found) {
    hit.shape = first_->scene_id(hit.shape);
    // One float past the hit: the open interval then still holds a hit at exactly hit.t, which
    // wins if its id is smaller.
    rest.t_max = math::next_float_up(hit.t);
  }
  Hit other;
  if (!second_->geometry.intersect(rest, other)) return found;
  other.shape = second_->scene_id(other.shape);
  if (!found || better(other, hit)) hit = other;
  return true;
}

bool LayeredGeometry::occluded_layers(const Ray& ray) const {
  return first_->geometry.occluded(ray) || second_->geometry.occluded(ray);
}

std::uint32_t LayeredGeometry::intersect8_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  const std::uint32_t found = first_->geometry.intersect8(rays, valid, hits) & valid;
  Ray rest[kPacketSize];
  for (int i = 0; i < kPacketSize; ++i) {
    rest[i] = rays[i];
    if (found >> i & 1u) {
      hits[i].shape = first_->scene_id(hits[i].shape);
      rest[i].t_max = math::next_float_up(hits[i].t);
    }
  }
  Hit other[kPacketSize];
  const std::uint32_t more = second_->geometry.intersect8(rest, valid, other) & valid;
  for (int i = 0; i < kPacketSize; ++i) {
    if (!(more >> i & 1u)) continue;
    other[i].shape = second_->scene_id(other[i].shape);
    if (!(found >> i & 1u) || better(other[i], hits[i])) hits[i] = other[i];
  }
  return found | more;
}

std::uint32_t LayeredGeometry::occluded8_layers(const Ray* rays, std::uint32_t valid) const {
  std::uint32_t blocked = first_->geometry.occluded8(rays, valid) & valid;
  if ((valid & ~blocked) != 0) blocked |= second_->geometry.occluded8(rays, valid & ~blocked);
  return blocked;
}

const Shape& LayeredGeometry::shape(std::uint32_t id) const {
  assert(id < shape_count_);
  if (!second_) return first_->geometry.shapes()[id];
  for (const Layer* layer : {first_, second_}) {
    const auto it = std::lower_bound(layer->ids.begin(), layer->ids.end(), id);
    if (it != layer->ids.end() && *it == id) return layer->geometry.shapes()[std::size_t(it - layer->ids.begin())];
  }
  assert(false && "every scene-wide id is in one layer");
  return first_->geometry.shapes()[0];
}

}  // namespace dtraced::accel
