// dtraced::accel geometry: float shapes, robust ray/shape intersection, and the acceleration
// structure over them.
//
// Owns: render-ready shapes (spheres, axis-aligned boxes, triangles, infinite planes), a binned-SAH
// BVH over the bounded ones (planes and a few huge shapes stay outside the tree), nearest-hit
// queries with conservative hit-point error bounds, and the pbrt-v4 style origin offset for
// secondary rays.
//
// Two traversal paths answer every query with the same bits (see accel/isa.h):
// - Isa::kScalar, the reference: one ray at a time through the binary BVH, scalar kernels.
// - a SIMD instruction set (SSE4, AVX2, AVX-512, picked at run time through Google Highway): the
//   binary BVH collapsed to an 8-wide one; single rays test 8 child boxes at once, 8-ray packets
//   (intersect8 / occluded8) test one box against 8 rays at once. The leaf kernels do the very
//   same IEEE operations as the scalar ones (no FMA), so hit/miss, t and shape agree bit for bit.
// Thread-safety: a built Geometry is immutable; any number of threads may query it at once.
//
// Robustness contract (after pbrt-v4's conservative error bounds and origin offsets, Ray Tracing
// Gems ch. 7 for spheres, Woop, Benthin and Wald 2013 for watertight triangles and Ize 2013 for the
// slab test):
// - A hit has t in the open interval (ray.t_min, ray.t_max); NaN never counts as a hit. Rays are
//   expected to have t_min >= 0 and a (float-)normalised direction.
// - Spheres are intersected in double (Ray Tracing Gems ch. 7 form), boxes with the conservative
//   slab test (Ize 2013 / pbrt-v4), planes in float. Hit.p comes with a per-axis bound p_error,
//   made of the roundings of the arithmetic that computed it (double for spheres, float for the
//   rest), such that offset_ray_origin() yields an origin from which the same surface is not
//   re-hit.
// - Geometry::intersect returns exactly what intersect_shape() over all shapes returns (same
//   shape, same t bits); among shapes hit at the same t the smallest index wins.
// - Shapes with non-finite parameters, spheres with radius <= 0, boxes with lo > hi on some axis
//   and planes with a zero normal are never hit.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include "accel/isa.h"
#include "accel/wide_bvh.h"
#include "math/float_util.h"
#include "math/ray.h"
#include "math/vec.h"

namespace dtraced::accel {

using math::Bounds3f;
using math::Ray;
using math::Vec3f;

struct SphereShape {
  Vec3f center;
  float radius = 1.0f;
};
struct BoxShape {
  Vec3f lo, hi;
};
struct TriangleShape {
  Vec3f v0, v1, v2;  // the normal is cross(v1 - v0, v2 - v0), normalised
};
struct PlaneShape {
  Vec3f point;
  Vec3f normal{0, 1, 0};  // unit length
};

enum class ShapeType : std::uint8_t { kSphere, kBox, kPlane, kTriangle };

// One shape: `type` says which member holds it. The members share their storage (40 bytes where
// one field per type took 104: at 10M spheres that is 640 MB), so set `type` and assign the
// member whole (`s.type = ShapeType::kBox; s.box = {lo, hi};`) and read only that member.
// Every byte of a Shape is set, padding included: shapes are written to files as they are (the
// worker's scene cache) and checksummed, which must not depend on what the memory held before.
// The constructor zeroes the whole union, then makes the sphere (radius 1) its member; a member
// assigned later leaves the bytes past its end as they were.
struct Shape {
  Shape() : bytes_{} { sphere = SphereShape{}; }
  ShapeType type = ShapeType::kSphere;
  std::uint8_t padding_[3] = {};
  union {
    SphereShape sphere;
    BoxShape box;
    PlaneShape plane;
    TriangleShape triangle;
    std::uint8_t bytes_[sizeof(TriangleShape)];
  };
};
static_assert(sizeof(Shape) == 40);

// Rays traced together by intersect8 / occluded8, and by intersect16 / occluded16.
inline constexpr int kPacketSize = 8;
inline constexpr int kPacketSize16 = 16;

// The nearest surface a ray meets.
struct Hit {
  float t = 0.0f;           // ray parameter of the hit, t_min < t < t_max
  std::uint32_t shape = 0;  // index into the shapes given to Geometry::build
  Vec3f p;                  // hit point (computed in the shape's own frame, not as o + t d)
  Vec3f p_error;            // per-axis absolute bound on the rounding error of p
  Vec3f n;                  // unit geometric normal, pointing out of the shape (not flipped)
};

struct BuildStats {
  std::uint32_t nodes = 0;
  std::uint32_t leaves = 0;
  std::uint32_t max_depth = 0;   // depth of the deepest node; the root has depth 0
  double seconds = 0.0;          // binary BVH build
  std::uint32_t wide_nodes = 0;  // 8-wide nodes after collapsing (SIMD isa only)
  double wide_seconds = 0.0;     // collapsing and packing the leaves (SIMD isa only)
  std::uint32_t outside = 0;     // shapes tested beside the tree: planes and huge shapes
  // A hash of the binary tree's node array (as 32-bit words) and leaf order, in fixed pieces of independent FNV-1a
  // chains folded in order (bvh.cpp): equal hashes, same tree (what the tests compare between thread counts).
  std::uint64_t tree_hash = 0;
};

namespace detail {

// A set-aside shape's sphere (the build, bvh.cpp). The constructor writes nothing (SphereShape has
// default values, hence the union), so that sizing the array writes no memory: the threads that
// copy the spheres in touch its pages first.
struct AsideSphere {
  AsideSphere() {}
  union {
    SphereShape sphere;
  };
};

// A set-aside scene's prims as the collapse reads them (collapse_to_wide), in place of Geometry's
// prims, which such a build does not make: prim i is the sphere spheres[order[i]].sphere with id
// order[i], i < count. Both arrays belong to the build and outlive the collapse.
struct AsideSpheres {
  const AsideSphere* spheres = nullptr;
  const std::uint32_t* order = nullptr;
  std::size_t count = 0;
};

}  // namespace detail

class Geometry {
 public:
  // Deepest node level (root = 0) is kMaxDepth - 1; a range reaching it becomes a leaf whatever its
  // size. Traversal uses a fixed stack of kMaxDepth entries.
  static constexpr std::uint32_t kMaxDepth = 64;

  // Builds the BVH (binned SAH) over the bounded shapes; planes and a few huge shapes (bounds of
  // more than a quarter of the scene's surface area) are kept in a separate list. With
  // a SIMD `isa` (which must be in supported_isas()) the tree is also collapsed to the 8-wide
  // layout that isa's kernels walk. A scene of fewer than 64 bounded shapes gets no wide tree:
  // packets test every shape directly (one flat leaf, stats().wide_nodes is then 1), single rays
  // keep the scalar walk, which is faster there.
  // Large trees are built on up to `threads` threads (0: util::usable_cpus(), the affinity mask),
  // started and joined inside the call. The tree, and so every answer, is the same whatever the
  // thread count.
  static Geometry build(std::vector<Shape> shapes, Isa isa = best_isa(), unsigned threads = 0);

  // Nearest hit with t in the open interval (ray.t_min, ray.t_max). Returns false on a miss.
  bool intersect(const Ray& ray, Hit& hit) const;

  // True if any shape is hit with t in (ray.t_min, ray.t_max) (shadow rays); stops at the first.
  bool occluded(const Ray& ray) const;

  // Packets of kPacketSize rays: lane i is traced when bit i of `valid` is set. `rays` must point
  // at kPacketSize readable rays (kPacketSize16 for the 16-ray calls) whatever `valid` says: the
  // kernels load the packet whole and ignore the dead lanes' values. intersect8 fills
  // hits[i] for each lane that hits and returns the mask of those lanes; occluded8 returns the
  // mask of valid lanes that are occluded. Each lane's answer is exactly intersect / occluded of
  // that ray alone. Coherent rays (camera rays of a pixel block, shadow rays towards one point)
  // are what packets are for; incoherent rays are faster one at a time.
  std::uint32_t intersect8(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  std::uint32_t occluded8(const Ray* rays, std::uint32_t valid) const;
  // The same for packets of kPacketSize16 rays (e.g. 4x4 camera pixels): one vector of 16 floats
  // per box test on AVX-512.
  std::uint32_t intersect16(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  std::uint32_t occluded16(const Ray* rays, std::uint32_t valid) const;

  const std::vector<Shape>& shapes() const { return shapes_; }
  const BuildStats& stats() const { return stats_; }
  Isa isa() const { return isa_; }

 private:
  // One BVH node, 32 bytes. Nodes are stored depth first: an interior node's first child is the
  // next node in the array, `offset` holds the second child. Like Prim, no member has a default
  // value and the constructor writes nothing, so that sizing nodes_ writes no memory: the build
  // writes every field of every node (a parallel build's threads each touch their subtrees' pages
  // first).
  struct Node {
    Node() {}
    float bounds[6];           // lo.x, lo.y, lo.z, hi.x, hi.y, hi.z
    std::uint32_t offset;      // leaf: first index into prims_; interior: second child's index
    std::uint32_t count : 30;  // number of shapes in a leaf; 0 for an interior node
    std::uint32_t axis : 2;    // split axis of an interior node (children ordered along it)
  };
  // A bounded shape packed for traversal (32 bytes), in BVH leaf order. No member has a default
  // value and the constructor writes nothing (`= default` would have vector::resize zero them),
  // so that sizing prims_ writes no memory: the build's threads write every field, each touching
  // its own chunk's pages first.
  struct Prim {
    Prim() {}
    float data[6];  // sphere: centre x, y, z, radius; box: lo x, y, z, hi x, y, z
    std::uint32_t id;
    ShapeType type;
  };

  friend detail::WideBvh detail::collapse_to_wide(const Geometry& g, bool prims_read_once, bool spheres_only,
                                                  util::ThreadPool& pool, unsigned threads,
                                                  const detail::AsideSpheres* aside);

  // Nearest hit below best_t among the shapes outside the tree (planes and huge shapes), ties to
  // the smaller id; updates best_t / best_id.
  bool outside_hit(const detail::RayPre& r, float t_min, float& best_t, std::uint32_t& best_id) const;
  // outside_hit for the lanes in `live` of a packet of N rays when the shapes it tests are all
  // planes: the same answers (best_t, best_id and the mask of lanes it returns true for), lane by
  // lane without the per-ray set-up (RayPre) that outside_hit takes.
  template <int N>
  std::uint32_t outside_planes(const Ray* rays, std::uint32_t live, float* best_t, std::uint32_t* best_id) const;
  const detail::Kernels& wide_kernels() const;
  template <int N>
  std::uint32_t intersect_n(const Ray* rays, std::uint32_t valid, Hit* hits) const;
  template <int N>
  std::uint32_t occluded_n(const Ray* rays, std::uint32_t valid) const;

  std::vector<Shape> shapes_;
  std::vector<Prim> prims_;             // bounded shapes in BVH leaf order
  std::vector<std::uint32_t> outside_;  // shape ids tested beside the tree: planes and huge shapes
  std::vector<Node> nodes_;
  BuildStats stats_;
  Isa isa_ = Isa::kScalar;
  bool has_triangles_ = false;  // rays then need the triangle test's shear constants
  detail::WideBvh wide_;        // empty for Isa::kScalar
};

// Nearest hit of one shape with t in (ray.t_min, ray.t_max); fills every field of `hit` (with
// hit.shape = id) and returns true, or returns false and leaves `hit` alone. The same arithmetic
// as Geometry::intersect, which makes it the brute-force reference.
bool intersect_shape(const Shape& shape, std::uint32_t id, const Ray& ray, Hit& hit);

// Conservative float bounds of a shape (a sphere's are rounded outward); planes are unbounded and
// invalid shapes (see above) get an empty box.
Bounds3f shape_bounds(const Shape& shape);

// What detail::shape_is_valid says of a sphere: a finite centre, a finite radius above 0, and
// finite bounds (or the SAH costs turn into inf - inf). Inline for the build, which asks it of
// every sphere of a scene (the call was 2 % of a 1M-sphere benchmark's CPU).
inline bool sphere_is_valid(const SphereShape& s) {
  if (!math::is_finite(s.center) || !std::isfinite(s.radius) || !(s.radius > 0.0f)) return false;
  for (int i = 0; i < 3; ++i) {
    if (!std::isfinite(float(std::abs(double(s.center[i])) + double(s.radius)))) return false;
  }
  return true;
}

// shape_bounds of a valid sphere: rounded outward, with a pad far above the double rounding of the
// sphere test, so every point the double kernel reports lies inside the float box the BVH node
// tests see. Inline for the build, which takes the bounds of every sphere of a scene (instead of
// a whole Shape made for shape_bounds' call: with the prims written in place, making them took
// 0.67-0.77 of the time, 1M spheres).
inline Bounds3f sphere_bounds(const SphereShape& s) {
  Bounds3f b;
  for (int i = 0; i < 3; ++i) {
    const double c = s.center[i];
    const double r = s.radius;
    const double pad = (std::abs(c) + r) * 0x1p-40;
    b.lo[i] = math::next_float_down(float(c - r - pad));
    b.hi[i] = math::next_float_up(float(c + r + pad));
  }
  return b;
}

// Origin for a ray leaving a surface point p (error bound p_error, geometric normal n) in
// direction w: pushed along +-n past the error bound and rounded one more ulp away (pbrt-v4's
// OffsetRayOrigin), so the new ray cannot re-hit the surface it leaves.
Vec3f offset_ray_origin(const Vec3f& p, const Vec3f& p_error, const Vec3f& n, const Vec3f& w);
// The same, written to `out` component by component (a returned Vec3f is packed into registers
// through the stack: two 4-byte stores reloaded as one 8-byte load, which waits for them).
void offset_ray_origin_to(const Vec3f& p, const Vec3f& p_error, const Vec3f& n, const Vec3f& w, Vec3f& out);

}  // namespace dtraced::accel
