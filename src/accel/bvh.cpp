// dtraced::accel BVH: binned-SAH build into a depth-first node array, and iterative nearest-hit /
// any-hit traversal with a fixed stack. Planes are infinite and tested linearly beside the tree.
#include <algorithm>
#include <array>
#include <cassert>
#include <chrono>
#include <limits>
#include <utility>

#include "accel/geometry.h"
#include "accel/kernels.h"

namespace dtraced::accel {

namespace {

constexpr int kBins = 32;
constexpr std::uint32_t kMaxLeafSize = 4;
// Cost of visiting an interior node relative to testing one shape (SAH units).
constexpr double kTraversalCost = 0.5;
// Marginal cost of one more prim in a SIMD leaf block (SAH units; see the leaf cost in build).
constexpr double kSimdLeafSlope = 0.3;
// Bounded prims below which the SIMD kernels get no tree but one flat leaf (see Geometry::build).
constexpr std::size_t kMinWidePrims = 64;
// Shapes whose bounds have more than this fraction of the scene bounds' surface area are kept
// out of the tree (at most kMaxOutside of them, besides the planes).
constexpr double kHugeFraction = 0.25;
constexpr std::size_t kMaxOutside = 16;
constexpr std::uint32_t kNoParent = std::numeric_limits<std::uint32_t>::max();

struct BuildPrim {
  Bounds3f bounds;
  Vec3f centroid;
  std::uint32_t id = 0;
};

// A range of build prims still to become a node. `parent` is set for second children, whose index
// must be written into their parent's `offset` when they are created; first children need no
// patch because they directly follow their parent.
struct Task {
  std::uint32_t begin = 0;
  std::uint32_t end = 0;
  std::uint32_t depth = 0;
  std::uint32_t parent = kNoParent;
};

// Surface area in double: float extents up to 3e38 would overflow a float product.
double area(const Bounds3f& b) {
  if (b.empty()) return 0.0;
  const double ex = double(b.hi.x) - b.lo.x, ey = double(b.hi.y) - b.lo.y, ez = double(b.hi.z) - b.lo.z;
  return 2.0 * (ex * ey + ey * ez + ez * ex);
}

// Bin of a centroid coordinate, in double so a tiny extent cannot overflow the scale or hand a
// NaN to the int conversion.
int bin_of(float c, double lo, double scale) {
  const double x = (double(c) - lo) * scale;
  return std::clamp(int(x), 0, kBins - 1);
}

}  // namespace

Geometry Geometry::build(std::vector<Shape> shapes, Isa isa) {
  static_assert(sizeof(Node) == 32 && sizeof(Prim) == 32, "two nodes / prims per 64-byte cache line");
  const auto start = std::chrono::steady_clock::now();
  Geometry g;
  g.shapes_ = std::move(shapes);

  std::vector<BuildPrim> refs;
  refs.reserve(g.shapes_.size());
  for (std::uint32_t id = 0; id < g.shapes_.size(); ++id) {
    const Shape& s = g.shapes_[id];
    if (!detail::shape_is_valid(s)) continue;
    g.has_triangles_ = g.has_triangles_ || s.type == ShapeType::kTriangle;
    if (s.type == ShapeType::kPlane) {
      g.outside_.push_back(id);
      continue;
    }
    const Bounds3f b = shape_bounds(s);
    refs.push_back({b, b.centroid(), id});
  }

  // Huge shapes (a floor or the walls of a room as boxes or big triangles) overlap every SAH
  // split and make the tree worse for everything else; like planes, they are tested one by one
  // beside it. Huge: bounds with more than a quarter of the surface area of all shapes' bounds.
  // At most kMaxOutside are taken out, the largest first, so the linear part stays short.
  if (refs.size() > 1) {
    Bounds3f all;
    for (const BuildPrim& ref : refs) all.extend(ref.bounds);
    const double limit = kHugeFraction * area(all);
    std::vector<std::pair<double, std::uint32_t>> huge;  // (area, index into refs)
    for (std::uint32_t i = 0; i < refs.size(); ++i) {
      const double a = area(refs[i].bounds);
      if (a > limit) huge.push_back({a, i});
    }
    std::sort(huge.begin(), huge.end(), [](const auto& x, const auto& y) { return x.first > y.first; });
    if (huge.size() > kMaxOutside) huge.resize(kMaxOutside);
    if (!huge.empty() && huge.size() < refs.size()) {
      std::vector<bool> out(refs.size(), false);
      for (const auto& h : huge) {
        out[h.second] = true;
        g.outside_.push_back(refs[h.second].id);
      }
      std::size_t k = 0;
      for (std::size_t i = 0; i < refs.size(); ++i) {
        if (!out[i]) refs[k++] = refs[i];
      }
      refs.resize(k);
    }
  }
  // Tested in id order, which the tie rule does not need but keeps the loop deterministic.
  std::sort(g.outside_.begin(), g.outside_.end());

  std::uint32_t leaves = 0;
  std::uint32_t max_depth = 0;
  if (!refs.empty()) {
    g.nodes_.reserve(2 * refs.size());
    std::vector<Task> stack;
    stack.push_back({0, std::uint32_t(refs.size()), 0, kNoParent});
    while (!stack.empty()) {
      const Task task = stack.back();
      stack.pop_back();
      const auto index = std::uint32_t(g.nodes_.size());
      if (task.parent != kNoParent) g.nodes_[task.parent].offset = index;
      g.nodes_.emplace_back();
      max_depth = std::max(max_depth, task.depth);

      Bounds3f bounds, centroids;
      for (std::uint32_t i = task.begin; i < task.end; ++i) {
        bounds.extend(refs[i].bounds);
        centroids.extend(refs[i].centroid);
      }
      Node& node = g.nodes_.back();
      for (int i = 0; i < 3; ++i) {
        node.bounds[i] = bounds.lo[i];
        node.bounds[3 + i] = bounds.hi[i];
      }
      node.count = 0;
      node.axis = 0;

      const std::uint32_t n = task.end - task.begin;
      auto make_leaf = [&] {
        node.offset = task.begin;
        node.count = n;
        ++leaves;
      };
      if (n == 1 || task.depth + 1 >= kMaxDepth) {
        make_leaf();
        continue;
      }

      const auto axis = std::uint32_t(math::max_dimension(centroids.extent()));
      const double c_lo = centroids.lo[axis];
      const double c_extent = double(centroids.hi[axis]) - c_lo;
      std::uint32_t mid = 0;
      if (!(c_extent > 0.0)) {
        // All centroids coincide: SAH cannot separate them, split the range in half.
        if (n <= kMaxLeafSize) {
          make_leaf();
          continue;
        }
        mid = task.begin + n / 2;
      } else {
        const double scale = kBins / c_extent;
        std::array<Bounds3f, kBins> bin_bounds;
        std::array<std::uint32_t, kBins> bin_count{};
        for (std::uint32_t i = task.begin; i < task.end; ++i) {
          const int b = bin_of(refs[i].centroid[axis], c_lo, scale);
          ++bin_count[b];
          bin_bounds[b].extend(refs[i].bounds);
        }
        // SAH cost of splitting after bin k, scaled by the node's area to avoid a division (flat or
        // point-like nodes have zero area): kTraversalCost A + A_left n_left + A_right n_right.
        std::array<double, kBins - 1> left_cost{};
        Bounds3f acc;
        std::uint32_t acc_n = 0;
        for (int k = 0; k < kBins - 1; ++k) {
          acc.extend(bin_bounds[k]);
          acc_n += bin_count[k];
          left_cost[k] = acc_n == 0 ? -1.0 : area(acc) * acc_n;  // -1: empty side, not a split
        }
        const double node_area = area(bounds);
        double best_cost = std::numeric_limits<double>::infinity();
        int best_k = -1;
        acc = Bounds3f{};
        acc_n = 0;
        for (int k = kBins - 2; k >= 0; --k) {
          acc.extend(bin_bounds[k + 1]);
          acc_n += bin_count[k + 1];
          if (acc_n == 0 || left_cost[k] < 0.0) continue;
          const double cost = kTraversalCost * node_area + left_cost[k] + area(acc) * acc_n;
          if (cost <= best_cost) {
            best_cost = cost;
            best_k = k;
          }
        }
        // The SIMD kernels test a leaf's prims 4 at a time, so for them a fuller leaf costs little
        // more than a single prim: favour leaves of up to kMaxLeafSize (fewer, fuller blocks).
        const double leaf_cost = (isa == Isa::kScalar ? double(n) : 1.0 + kSimdLeafSlope * (n - 1)) * node_area;
        if (n <= kMaxLeafSize && leaf_cost <= best_cost) {
          make_leaf();
          continue;
        }
        if (best_k < 0) {
          mid = task.begin + n / 2;  // NaN costs (cannot happen for valid shapes): split in half
        } else {
          auto* first = refs.data() + task.begin;
          auto* last = refs.data() + task.end;
          mid = std::uint32_t(
              std::partition(first, last,
                             [&](const BuildPrim& p) { return bin_of(p.centroid[axis], c_lo, scale) <= best_k; }) -
              refs.data());
        }
      }
      assert(mid > task.begin && mid < task.end);
      node.axis = axis;
      // LIFO: the first child is popped next and so lands at index + 1.
      stack.push_back({mid, task.end, task.depth + 1, index});
      stack.push_back({task.begin, mid, task.depth + 1, kNoParent});
    }
  }

  g.prims_.reserve(refs.size());
  for (const BuildPrim& ref : refs) {
    const Shape& s = g.shapes_[ref.id];
    Prim p;
    p.id = ref.id;
    p.type = s.type;
    if (s.type == ShapeType::kTriangle) {
      // The scalar path reads the vertices from shapes_ (9 floats do not fit a 32-byte prim).
      for (float& x : p.data) x = 0.0f;
    } else if (s.type == ShapeType::kSphere) {
      p.data[0] = s.sphere.center.x;
      p.data[1] = s.sphere.center.y;
      p.data[2] = s.sphere.center.z;
      p.data[3] = s.sphere.radius;
      p.data[4] = p.data[5] = 0.0f;
    } else {
      p.data[0] = s.box.lo.x;
      p.data[1] = s.box.lo.y;
      p.data[2] = s.box.lo.z;
      p.data[3] = s.box.hi.x;
      p.data[4] = s.box.hi.y;
      p.data[5] = s.box.hi.z;
    }
    g.prims_.push_back(p);
  }

  g.stats_.nodes = std::uint32_t(g.nodes_.size());
  g.stats_.leaves = leaves;
  g.stats_.outside = std::uint32_t(g.outside_.size());
  g.stats_.max_depth = max_depth;
  g.stats_.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  g.isa_ = isa;
  // A tree of a few dozen prims is two or three wide levels whose fixed costs exceed what they
  // save (the showcase scene rendered ~20% slower with it than with the scalar walk). Such scenes
  // get no tree at all for packets: every bounded shape in a flat leaf that the SIMD kernels test
  // against 8 rays at once (detail::flat_wide), with the same bits as the scalar walk. Single
  // rays are faster on the scalar walk there (measured: 19 vs 12 Mrays/s for secondary rays of
  // 10 spheres), which answers with the same bits.
  if (isa != Isa::kScalar && !g.prims_.empty()) {
    const auto wide_start = std::chrono::steady_clock::now();
    if (g.prims_.size() >= kMinWidePrims) {
      g.wide_ = detail::collapse_to_wide(g);
    } else {
      // Packets test the huge shapes in a second flat leaf (only planes stay beside it); single
      // rays keep the scalar walk, with the huge shapes beside the binary tree.
      std::vector<std::vector<std::uint32_t>> groups(2);
      for (const Prim& p : g.prims_) groups[0].push_back(p.id);
      for (const std::uint32_t id : g.outside_) {
        if (g.shapes_[id].type != ShapeType::kPlane) groups[1].push_back(id);
      }
      g.wide_ = detail::flat_wide(g.shapes_, groups);
    }
    g.stats_.wide_nodes = std::uint32_t(g.wide_.nodes.size());
    g.stats_.wide_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - wide_start).count();
  }
  return g;
}

namespace {

inline float triangle_prim_t(const TriangleShape& tr, const detail::RayPre& r, float t_min) {
  const float v[9] = {tr.v0.x, tr.v0.y, tr.v0.z, tr.v1.x, tr.v1.y, tr.v1.z, tr.v2.x, tr.v2.y, tr.v2.z};
  return detail::triangle_t(v, r, t_min);
}

inline float prim_t(const float* data, ShapeType type, const std::vector<Shape>& shapes, std::uint32_t id,
                    const detail::RayPre& r, float t_min) {
  switch (type) {
    case ShapeType::kSphere:
      return detail::sphere_t(data, r, t_min);
    case ShapeType::kTriangle:
      return triangle_prim_t(shapes[id].triangle, r, t_min);
    default:
      return detail::box_t(data, r, t_min);
  }
}

// A shape tested outside the tree: a plane or a huge shape.
inline float outside_t(const Shape& s, const detail::RayPre& r, float t_min) {
  switch (s.type) {
    case ShapeType::kPlane:
      return detail::plane_t(s.plane, r, t_min);
    case ShapeType::kSphere: {
      const float d[4] = {s.sphere.center.x, s.sphere.center.y, s.sphere.center.z, s.sphere.radius};
      return detail::sphere_t(d, r, t_min);
    }
    case ShapeType::kBox: {
      const float d[6] = {s.box.lo.x, s.box.lo.y, s.box.lo.z, s.box.hi.x, s.box.hi.y, s.box.hi.z};
      return detail::box_t(d, r, t_min);
    }
    case ShapeType::kTriangle:
      return triangle_prim_t(s.triangle, r, t_min);
  }
  return detail::kNaN;
}

// The one traversal loop, nearest child first. `cull_t` is read at every node, so a caller that
// shrinks it from `leaf` prunes the rest of the walk; `leaf(prim)` returns true to end the walk.
template <typename Nodes, typename Prims, typename Leaf>
void walk(const Nodes& nodes, const Prims& prims, const detail::RayPre& r, float t_min, const float& cull_t,
          Leaf&& leaf) {
  constexpr std::uint32_t kStack = Geometry::kMaxDepth;
  std::uint32_t stack[kStack];
  std::uint32_t sp = 0;
  std::uint32_t index = 0;
  while (true) {
    const auto& node = nodes[index];
    if (detail::node_hit(node.bounds, r, t_min, cull_t)) {
      if (node.count > 0) {
        const auto* prim = prims.data() + node.offset;
        for (std::uint32_t i = 0; i < node.count; ++i, ++prim) {
          if (leaf(*prim)) return;
        }
      } else {
        std::uint32_t first = index + 1;
        std::uint32_t second = node.offset;
        if (r.neg[node.axis]) std::swap(first, second);
        assert(sp < kStack);
        stack[sp++] = second;
        index = first;
        continue;
      }
    }
    if (sp == 0) return;
    index = stack[--sp];
  }
}

}  // namespace

bool Geometry::intersect(const Ray& ray, Hit& hit) const {
  if (!(ray.t_min < ray.t_max) || !math::is_finite(ray.o) || !math::is_finite(ray.d)) return false;
  const detail::RayPre r = detail::precompute(ray, has_triangles_);
  if (!wide_.empty() && !detail::is_flat(wide_)) {
    float best_t = ray.t_max;
    std::uint32_t best_id = 0;
    const bool found = outside_hit(r, ray.t_min, best_t, best_id);
    const bool tree = wide_kernels().intersect1(wide_, r, ray.t_min, best_t, best_id);
    if (!found && !tree) return false;
    detail::finish_hit(shapes_[best_id], best_id, ray, r, best_t, hit);
    return true;
  }

  // Nearest so far; ties in t go to the smaller shape id, so the answer does not depend on the
  // order shapes are visited in (best_id starts at 0: `id < 0` never holds before a first hit).
  float best_t = ray.t_max;
  std::uint32_t best_id = 0;
  bool found = false;
  auto consider = [&](float t, std::uint32_t id) {
    if (!(t < best_t || (t == best_t && id < best_id))) return false;
    best_t = t;
    best_id = id;
    found = true;
    return true;
  };

  for (const std::uint32_t id : outside_) consider(outside_t(shapes_[id], r, ray.t_min), id);

  if (!nodes_.empty()) {
    // Nodes are culled against best_t enlarged like a far slab distance: the sphere kernel runs in
    // double, and its float t may sit an ulp or two before the float entry distance of its box.
    float cull_t = best_t * detail::kFarScale;
    walk(nodes_, prims_, r, ray.t_min, cull_t, [&](const Prim& prim) {
      if (consider(prim_t(prim.data, prim.type, shapes_, prim.id, r, ray.t_min), prim.id))
        cull_t = best_t * detail::kFarScale;
      return false;
    });
  }

  if (!found) return false;
  detail::finish_hit(shapes_[best_id], best_id, ray, r, best_t, hit);
  return true;
}

bool Geometry::occluded(const Ray& ray) const {
  if (!(ray.t_min < ray.t_max) || !math::is_finite(ray.o) || !math::is_finite(ray.d)) return false;
  const detail::RayPre r = detail::precompute(ray, has_triangles_);
  if (!wide_.empty() && !detail::is_flat(wide_)) {
    float best_t = ray.t_max;
    std::uint32_t best_id = 0;
    if (outside_hit(r, ray.t_min, best_t, best_id)) return true;
    return wide_kernels().occluded1(wide_, r, ray.t_min, ray.t_max);
  }
  for (const std::uint32_t id : outside_) {
    if (outside_t(shapes_[id], r, ray.t_min) < ray.t_max) return true;
  }
  if (nodes_.empty()) return false;
  const float cull_t = ray.t_max * detail::kFarScale;
  bool hit = false;
  walk(nodes_, prims_, r, ray.t_min, cull_t, [&](const Prim& prim) {
    hit = prim_t(prim.data, prim.type, shapes_, prim.id, r, ray.t_min) < ray.t_max;
    return hit;
  });
  return hit;
}

bool Geometry::outside_hit(const detail::RayPre& r, float t_min, float& best_t, std::uint32_t& best_id) const {
  // With the flat layout the huge shapes are in it: only the planes are beside it.
  const bool flat = detail::is_flat(wide_);
  bool found = false;
  for (const std::uint32_t id : outside_) {
    if (flat && shapes_[id].type != ShapeType::kPlane) continue;
    const float t = outside_t(shapes_[id], r, t_min);
    if (t < best_t || (found && t == best_t && id < best_id)) {
      best_t = t;
      best_id = id;
      found = true;
    }
  }
  return found;
}

const detail::Kernels& Geometry::wide_kernels() const { return detail::kernels_for(isa_); }

namespace {
bool ray_ok(const Ray& ray) { return ray.t_min < ray.t_max && math::is_finite(ray.o) && math::is_finite(ray.d); }

// What outside_hit tests for a packet's lanes: kNone, kPlanes (which need no division of the
// ray's constants: precompute_od) or kAny. With the flat layout only the planes are outside it.
enum class Outside { kNone, kPlanes, kAny };
Outside outside_kind(const std::vector<Shape>& shapes, const std::vector<std::uint32_t>& outside,
                     const detail::WideBvh& wide) {
  const bool flat = detail::is_flat(wide);
  Outside kind = Outside::kNone;
  for (const std::uint32_t id : outside) {
    if (shapes[id].type != ShapeType::kPlane) {
      if (!flat) return Outside::kAny;
    } else {
      kind = Outside::kPlanes;
    }
  }
  return kind;
}
}  // namespace

std::uint32_t Geometry::intersect8(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  std::uint32_t live = 0;
  for (int i = 0; i < kPacketSize; ++i) {
    if ((valid >> i & 1u) && ray_ok(rays[i])) live |= 1u << i;
  }
  if (live == 0) return 0;
  if (wide_.empty()) {
    std::uint32_t found = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      if ((live >> i & 1u) && intersect(rays[i], hits[i])) found |= 1u << i;
    }
    return found;
  }
  float best_t[kPacketSize];
  std::uint32_t best_id[kPacketSize];
  std::uint32_t found = 0;
  const Outside outside = outside_kind(shapes_, outside_, wide_);
  for (int i = 0; i < kPacketSize; ++i) {
    best_t[i] = rays[i].t_max;
    best_id[i] = 0;
    if ((live >> i & 1u) && outside != Outside::kNone &&
        outside_hit(
            outside == Outside::kPlanes ? detail::precompute_od(rays[i]) : detail::precompute(rays[i], has_triangles_),
            rays[i].t_min, best_t[i], best_id[i])) {
      found |= 1u << i;
    }
  }
  found |= wide_kernels().intersect8(wide_, rays, live, best_t, best_id);
  // Sphere hits are finished together (their square roots and divisions overlap), the rest one
  // by one.
  const Shape* sph_shape[kPacketSize];
  std::uint32_t sph_id[kPacketSize];
  const Ray* sph_ray[kPacketSize];
  float sph_t[kPacketSize];
  Hit* sph_hit[kPacketSize];
  int spheres = 0;
  for (int i = 0; i < kPacketSize; ++i) {
    if (found >> i & 1u) {
      const Shape& s = shapes_[best_id[i]];
      if (s.type == ShapeType::kSphere) {
        sph_shape[spheres] = &s;
        sph_id[spheres] = best_id[i];
        sph_ray[spheres] = &rays[i];
        sph_t[spheres] = best_t[i];
        sph_hit[spheres] = &hits[i];
        ++spheres;
      } else {
        detail::finish_hit(s, best_id[i], rays[i], detail::precompute_for(rays[i], s.type), best_t[i], hits[i]);
      }
    }
  }
  if (spheres > 0) detail::finish_sphere_hits(sph_shape, sph_id, sph_ray, sph_t, sph_hit, spheres);
  return found;
}

std::uint32_t Geometry::occluded8(const Ray* rays, std::uint32_t valid) const {
  std::uint32_t live = 0;
  for (int i = 0; i < kPacketSize; ++i) {
    if ((valid >> i & 1u) && ray_ok(rays[i])) live |= 1u << i;
  }
  if (live == 0) return 0;
  if (wide_.empty()) {
    std::uint32_t blocked = 0;
    for (int i = 0; i < kPacketSize; ++i) {
      if ((live >> i & 1u) && occluded(rays[i])) blocked |= 1u << i;
    }
    return blocked;
  }
  std::uint32_t blocked = 0;
  const Outside outside = outside_kind(shapes_, outside_, wide_);
  for (int i = 0; i < kPacketSize; ++i) {
    float t = rays[i].t_max;
    std::uint32_t id = 0;
    if ((live >> i & 1u) && outside != Outside::kNone &&
        outside_hit(
            outside == Outside::kPlanes ? detail::precompute_od(rays[i]) : detail::precompute(rays[i], has_triangles_),
            rays[i].t_min, t, id)) {
      blocked |= 1u << i;
    }
  }
  const std::uint32_t rest = live & ~blocked;
  if (rest != 0) blocked |= wide_kernels().occluded8(wide_, rays, rest);
  return blocked;
}

}  // namespace dtraced::accel
