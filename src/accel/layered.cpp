#include "accel/layered.h"

#include <algorithm>
#include <bit>
#include <cassert>
#include <cmath>
#include <limits>
#include <utility>

#if defined(__SSE2__)
#include <xmmintrin.h>
#endif

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

LayeredGeometry::LayeredGeometry(Geometry opaque, std::shared_ptr<const Layer> transparent)
    : transparent_(std::move(transparent)), shape_count_(opaque.shapes().size()), isa_(opaque.isa()) {
  assert(transparent_ && !transparent_->ids.empty() && transparent_->geometry.isa() == opaque.isa());
  assert(transparent_->ids.back() < shape_count_);
  auto layer = std::make_shared<Layer>();
  layer->geometry = std::move(opaque);
  fixed_ = std::move(layer);
  first_ = fixed_.get();
  second_ = transparent_.get();
  // A sphere around the bounds the transparent layer's hits lie in (shape_bounds is conservative,
  // rounded outward): the box's centre and half diagonal, rounded up.
  math::Bounds3f b;
  for (const Shape& s : transparent_->geometry.shapes()) b.extend(shape_bounds(s));
  // Unbounded (a plane) or empty (no valid shape): no culling, every ray is queried.
  cull_ = !b.empty();
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(b.lo[a]) || !std::isfinite(b.hi[a])) cull_ = false;
  }
  if (cull_) {
    // The centre in float (what the test subtracts from), and the squared distance from it to the
    // farthest corner, in double rounded up.
    double r2 = 0.0;
    for (int a = 0; a < 3; ++a) {
      center_[a] = float(0.5 * (double(b.lo[a]) + double(b.hi[a])));
      const double h = std::max(double(b.hi[a]) - double(center_[a]), double(center_[a]) - double(b.lo[a]));
      r2 += h * h;
    }
    radius2_ = float(r2 * 1.01);
    if (!std::isfinite(radius2_)) cull_ = false;
  }
}

namespace {
// The range of dd and ww dd the bounding-sphere test trusts (reach()): products of normal floats
// this large keep their relative rounding, and limit * dd (>= ww dd 2^-14) stays normal too; below
// 2^100, wd^2 (at most ww dd) and ww dd cannot overflow.
constexpr float kMinProduct = 0x1p-100f;
constexpr float kMaxProduct = 0x1p100f;
}  // namespace

bool LayeredGeometry::may_reach_second(const Ray& ray) const {
  if (!cull_) return true;
  return reach(ray.o.x, ray.o.y, ray.o.z, ray.d.x, ray.d.y, ray.d.z, ray.t_min);
}

// The test of may_reach_second, in float: w = centre - o, and the line misses the sphere when its
// squared distance from the centre, (ww dd - wd^2) / dd, is above the limit; a ray with t_min >= 0
// whose origin is outside and that points away (wd < 0) misses it too. The limit, r^2 * 1.01 (in
// radius2_) + ww * 2^-14, covers by far the roundings of this test (each w relative 2^-24, the
// difference ww dd - wd^2 within 2^-20 ww dd) and a box kernel's conservative slab test, which
// lets through rays missing a box by a few ulps of their t. That bound needs dd and ww dd well
// inside the normal floats (kMinProduct, kMaxProduct: a direction of length 1e-21 made dd
// subnormal, and one of 2^50 from 16,383 away made ww dd overflow to infinity while wd^2 did not,
// each culling rays aimed at the layer): outside them the line test keeps the ray. A NaN compares
// false: kept.
bool LayeredGeometry::reach(float ox, float oy, float oz, float dx, float dy, float dz, float t_min) const {
  const float wx = center_[0] - ox, wy = center_[1] - oy, wz = center_[2] - oz;
  const float ww = wx * wx + wy * wy + wz * wz;
  const float dd = dx * dx + dy * dy + dz * dz;
  const float wd = wx * dx + wy * dy + wz * dz;
  const float limit = radius2_ + ww * 0x1p-14f;
  const float wwdd = ww * dd;
  if (dd >= kMinProduct && wwdd >= kMinProduct && wwdd <= kMaxProduct && wwdd - wd * wd > limit * dd) return false;
  if (t_min >= 0.0f && wd < 0.0f && ww > limit) return false;
  return true;
}

template <int N>
std::uint32_t LayeredGeometry::reach_second(const Ray* rays, std::uint32_t valid) const {
  if (!cull_) return valid;
#if defined(__SSE2__)
  // Four rays at a time (the same operations as reach(), lane by lane): the rays' first and second
  // halves, o.x o.y o.z d.x and d.y d.z t_min t_max, transposed to one vector per field. Scalar,
  // the test of every shadow packet's lanes took about 3 % of scenes/mesh.json's render.
  static_assert(sizeof(Ray) == 32 && N % 4 == 0);
  const __m128 cx = _mm_set1_ps(center_[0]), cy = _mm_set1_ps(center_[1]), cz = _mm_set1_ps(center_[2]);
  const __m128 r2 = _mm_set1_ps(radius2_), k = _mm_set1_ps(0x1p-14f), zero = _mm_setzero_ps();
  const __m128 floor = _mm_set1_ps(kMinProduct), ceiling = _mm_set1_ps(kMaxProduct);
  std::uint32_t miss = 0;
  for (int g = 0; g < N; g += 4) {
    if ((valid >> g & 0xfu) == 0) continue;
    const float* f = reinterpret_cast<const float*>(rays + g);
    __m128 ox = _mm_loadu_ps(f), oy = _mm_loadu_ps(f + 8), oz = _mm_loadu_ps(f + 16), dx = _mm_loadu_ps(f + 24);
    __m128 dy = _mm_loadu_ps(f + 4), dz = _mm_loadu_ps(f + 12), tmin = _mm_loadu_ps(f + 20),
           tmax = _mm_loadu_ps(f + 28);
    _MM_TRANSPOSE4_PS(ox, oy, oz, dx);
    _MM_TRANSPOSE4_PS(dy, dz, tmin, tmax);
    const __m128 wx = _mm_sub_ps(cx, ox), wy = _mm_sub_ps(cy, oy), wz = _mm_sub_ps(cz, oz);
    const __m128 ww = _mm_add_ps(_mm_add_ps(_mm_mul_ps(wx, wx), _mm_mul_ps(wy, wy)), _mm_mul_ps(wz, wz));
    const __m128 dd = _mm_add_ps(_mm_add_ps(_mm_mul_ps(dx, dx), _mm_mul_ps(dy, dy)), _mm_mul_ps(dz, dz));
    const __m128 wd = _mm_add_ps(_mm_add_ps(_mm_mul_ps(wx, dx), _mm_mul_ps(wy, dy)), _mm_mul_ps(wz, dz));
    const __m128 limit = _mm_add_ps(r2, _mm_mul_ps(ww, k));
    const __m128 wwdd = _mm_mul_ps(ww, dd);
    const __m128 normal =
        _mm_and_ps(_mm_and_ps(_mm_cmpge_ps(dd, floor), _mm_cmpge_ps(wwdd, floor)), _mm_cmple_ps(wwdd, ceiling));
    const __m128 off_line =
        _mm_and_ps(normal, _mm_cmpgt_ps(_mm_sub_ps(wwdd, _mm_mul_ps(wd, wd)), _mm_mul_ps(limit, dd)));
    const __m128 away =
        _mm_and_ps(_mm_and_ps(_mm_cmpge_ps(tmin, zero), _mm_cmplt_ps(wd, zero)), _mm_cmpgt_ps(ww, limit));
    miss |= std::uint32_t(_mm_movemask_ps(_mm_or_ps(off_line, away))) << g;
  }
  return valid & ~miss;
#else
  std::uint32_t reached = 0;
  for (std::uint32_t s = valid; s != 0; s &= s - 1) {
    const int i = std::countr_zero(s);
    if (may_reach_second(rays[i])) reached |= 1u << i;
  }
  return reached;
#endif
}

bool LayeredGeometry::intersect_transparent(const Ray& ray, Hit& hit) const {
  assert(transparent_);
  if (!may_reach_second(ray) || !second_->geometry.intersect(ray, hit)) return false;
  hit.shape = second_->scene_id(hit.shape);
  return true;
}

template <int N>
std::uint32_t LayeredGeometry::second_hits(const Ray* rays, std::uint32_t reach, Hit* hits) const {
  if (reach == 0) return 0;
  const std::uint32_t found = detail::intersect_n<N>(second_->geometry, rays, reach, hits) & reach;
  for (std::uint32_t s = found; s != 0; s &= s - 1) {
    const int i = std::countr_zero(s);
    hits[i].shape = second_->scene_id(hits[i].shape);
  }
  return found;
}

template <int N>
std::uint32_t LayeredGeometry::intersect_transparent(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  assert(transparent_);
  return second_hits<N>(rays, reach_second<N>(rays, valid), hits);
}

template std::uint32_t LayeredGeometry::intersect_transparent<kPacketSize>(const Ray*, std::uint32_t, Hit*) const;
template std::uint32_t LayeredGeometry::intersect_transparent<kPacketSize16>(const Ray*, std::uint32_t, Hit*) const;

Shape LayeredGeometry::hole() {
  Shape s;
  s.type = ShapeType::kSphere;
  s.sphere = SphereShape{Vec3f{0, 0, 0}, 0.0f};
  return s;
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
  if (!may_reach_second(ray) || !second_->geometry.intersect(rest, other)) return found;
  other.shape = second_->scene_id(other.shape);
  if (!found || better(other, hit)) hit = other;
  return true;
}

bool LayeredGeometry::occluded_layers(const Ray& ray) const {
  return first_->geometry.occluded(ray) || (may_reach_second(ray) && second_->geometry.occluded(ray));
}

template <int N>
std::uint32_t LayeredGeometry::intersect_n_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  const std::uint32_t found = detail::intersect_n<N>(first_->geometry, rays, valid, hits) & valid;
  if (!first_->ids.empty()) {
    for (std::uint32_t s = found; s != 0; s &= s - 1) {
      const int i = std::countr_zero(s);
      hits[i].shape = first_->scene_id(hits[i].shape);
    }
  }
  const std::uint32_t reach = reach_second<N>(rays, valid);
  if (reach == 0) return found;
  Ray rest[N];
  for (int i = 0; i < N; ++i) {
    rest[i] = rays[i];
    // One float past the hit: the open interval then still holds a hit at exactly hit.t, which
    // wins if its id is smaller.
    if (found >> i & 1u) rest[i].t_max = math::next_float_up(hits[i].t);
  }
  Hit other[N];
  const std::uint32_t more = second_hits<N>(rest, reach, other);
  for (std::uint32_t s = more; s != 0; s &= s - 1) {
    const int i = std::countr_zero(s);
    if (!(found >> i & 1u) || better(other[i], hits[i])) hits[i] = other[i];
  }
  return found | more;
}

template <int N>
std::uint32_t LayeredGeometry::occluded_n_layers(const Ray* rays, std::uint32_t valid) const {
  std::uint32_t blocked = detail::occluded_n<N>(first_->geometry, rays, valid) & valid;
  const std::uint32_t rest = reach_second<N>(rays, valid & ~blocked);
  if (rest != 0) blocked |= detail::occluded_n<N>(second_->geometry, rays, rest) & rest;
  return blocked;
}

std::uint32_t LayeredGeometry::intersect8_layers(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  return intersect_n_layers<kPacketSize>(rays, valid, hits);
}

std::uint32_t LayeredGeometry::occluded8_layers(const Ray* rays, std::uint32_t valid) const {
  return occluded_n_layers<kPacketSize>(rays, valid);
}

template std::uint32_t LayeredGeometry::intersect_n_layers<kPacketSize16>(const Ray*, std::uint32_t, Hit*) const;
template std::uint32_t LayeredGeometry::occluded_n_layers<kPacketSize16>(const Ray*, std::uint32_t) const;

const Shape& LayeredGeometry::shape(std::uint32_t id) const {
  assert(id < shape_count_);
  if (!second_) return first_->geometry.shapes()[id];
  // The second layer first: a split scene's opaque layer (empty ids) holds a hole at a
  // transparent shape's id.
  for (const Layer* layer : {second_, first_}) {
    if (layer->ids.empty()) return layer->geometry.shapes()[id];
    const auto it = std::lower_bound(layer->ids.begin(), layer->ids.end(), id);
    if (it != layer->ids.end() && *it == id) return layer->geometry.shapes()[std::size_t(it - layer->ids.begin())];
  }
  assert(false && "every scene-wide id is in one layer");
  return first_->geometry.shapes()[0];
}

}  // namespace dtraced::accel
