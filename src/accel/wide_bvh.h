// dtraced::accel internal: the 8-wide BVH the SIMD kernels walk, in structure-of-arrays form.
// Not part of the public API (Geometry owns one); shared between the collapse (wide_build.cpp)
// and the per-instruction-set kernels (simd_kernels.cpp, compiled once per Highway target).
#pragma once

#include <cstdint>
#include <vector>

#include "accel/isa.h"
#include "math/ray.h"

namespace dtraced::util {
class ThreadPool;
}  // namespace dtraced::util

namespace dtraced::accel {
struct Hit;
class Geometry;
}  // namespace dtraced::accel

namespace dtraced::accel::detail {

struct RayPre;  // kernels.h

inline constexpr int kNodeWidth = 8;  // children per node (one AVX2/AVX-512 vector, two SSE4)
inline constexpr int kWidth = 4;      // prims per leaf block
inline constexpr std::uint32_t kEmptyChild = 0xffffffffu;
inline constexpr std::uint32_t kLeafBit = 0x80000000u;  // child refers to leaves[child & ~kLeafBit]

// A leaf of triangles only is described in its child reference itself, so that traversal reaches
// its blocks without first loading the WideLeaf record (a dependent load per leaf):
// kLeafBit | kTriLeaf | blocks << kTriLeafShift | triangle_begin. A leaf of one block of spheres
// (and nothing else: nearly every leaf of a sphere scene) likewise, with a block count of 0:
// kLeafBit | kTriLeaf | sphere_begin; traversal can then also prefetch its block as soon as a lane
// enters it. Other leaves' indices stay below kTriLeaf (2^30 leaves would need far more prims than
// memory holds; collapse_to_wide checks).
inline constexpr std::uint32_t kTriLeaf = 0x40000000u;
inline constexpr int kTriLeafShift = 26;
inline constexpr std::uint32_t kTriLeafMaxBlocks = 15;                         // 4 bits
inline constexpr std::uint32_t kTriLeafBeginMask = (1u << kTriLeafShift) - 1;  // first block < 2^26

// One node, four cache lines. Per axis a, lo[a][i] / hi[a][i] bound child i; an empty slot has
// lo = +inf, hi = -inf and child = kEmptyChild. Children are in the binary tree's depth-first
// order, so a slot's index says nothing about distance: traversal sorts by entry distance.
// The constructors of the node and the blocks write nothing, so that sizing an array of them writes
// no memory (the collapse's threads touch their own parts' pages first); every member is set by
// whoever makes one.
struct alignas(64) WideNode {
  WideNode() {}  // leaves every member unset
  float lo[3][kNodeWidth];
  float hi[3][kNodeWidth];
  std::uint32_t child[kNodeWidth];
  std::uint32_t pad[8];
};
static_assert(sizeof(WideNode) == 256);

// A leaf: the prims of one binary-tree leaf (normally at most kWidth), split by type. Spheres and
// triangles sit in kWidth-lane SoA blocks (unused lanes hold NaN and never hit); boxes are few and
// tested one by one.
struct WideLeaf {
  std::uint32_t sphere_begin = 0;  // blocks [sphere_begin, sphere_begin + sphere_blocks) of WideBvh::spheres
  std::uint32_t triangle_begin = 0;
  std::uint32_t box_begin = 0;  // boxes [box_begin, box_begin + box_count) of WideBvh::boxes
  std::uint16_t sphere_blocks = 0;
  std::uint16_t triangle_blocks = 0;
  std::uint32_t box_count = 0;
};

struct alignas(16) SphereBlock {
  SphereBlock() {}  // leaves every member unset
  float cx[kWidth], cy[kWidth], cz[kWidth], r[kWidth];
  std::uint32_t id[kWidth];
};

// Triangle vertices a, b, c as given (the watertight test needs the vertices themselves, relative
// to the ray origin, not precomputed edges).
struct alignas(16) TriangleBlock {
  TriangleBlock() {}      // leaves every member unset
  float v[3][3][kWidth];  // v[vertex][axis][lane]
  std::uint32_t id[kWidth];
};

struct BoxPrim {
  float b[6];  // lo x, y, z, hi x, y, z
  std::uint32_t id = 0;
};

// The child reference that describes `leaf` by itself (kTriLeaf: triangles only, or one block of
// spheres only), or 0 when it holds other prims or does not fit the encoding (then the reference
// is kLeafBit | its index in WideBvh::leaves).
inline std::uint32_t tri_leaf_ref(const WideLeaf& leaf) {
  if (leaf.box_count != 0) return 0;
  if (leaf.sphere_blocks != 0) {
    if (leaf.sphere_blocks != 1 || leaf.triangle_blocks != 0 || leaf.sphere_begin > kTriLeafBeginMask) return 0;
    return kLeafBit | kTriLeaf | leaf.sphere_begin;
  }
  if (leaf.triangle_blocks == 0) return 0;
  if (leaf.triangle_blocks > kTriLeafMaxBlocks || leaf.triangle_begin > kTriLeafBeginMask) return 0;
  return kLeafBit | kTriLeaf | std::uint32_t(leaf.triangle_blocks) << kTriLeafShift | leaf.triangle_begin;
}

// The number of triangle blocks of a kTriLeaf reference: 0 for a leaf of one sphere block.
inline std::uint32_t tri_leaf_blocks(std::uint32_t ref) { return (ref & ~(kLeafBit | kTriLeaf)) >> kTriLeafShift; }

// The WideLeaf that a kTriLeaf reference describes.
inline WideLeaf tri_leaf_of(std::uint32_t ref) {
  WideLeaf leaf;
  const std::uint32_t blocks = tri_leaf_blocks(ref);
  if (blocks == 0) {
    leaf.sphere_begin = ref & kTriLeafBeginMask;
    leaf.sphere_blocks = 1;
    return leaf;
  }
  leaf.triangle_begin = ref & kTriLeafBeginMask;
  leaf.triangle_blocks = std::uint16_t(blocks);
  return leaf;
}

struct WideBvh {
  std::vector<WideNode> nodes;  // nodes[0] is the root (when not empty)
  std::vector<WideLeaf> leaves;
  std::vector<SphereBlock> spheres;
  std::vector<TriangleBlock> triangles;
  std::vector<BoxPrim> boxes;
  bool has_triangles = false;  // rays need the triangle test's shear constants
  bool empty() const { return nodes.empty(); }
};

// What one instruction set provides. The planes and the final hit record are handled by Geometry
// around these calls; `best_t`/`best_id` carry in the planes' result and come back as the nearest
// hit over planes and tree (ties to the smaller id). When the tree's nearest hit is a triangle
// (or, for packets, a sphere a packet test found), the kernel writes the hit record itself
// (finish_hit's bits, from the edge functions of the winning test and the prim in the leaf block
// it just tested: no second test, and no load of the Shape, which at a million triangles was a
// cache miss per hit) and says so in `finished`; other hits are left to Geometry.
struct Kernels {
  // Single ray: updates best_t / best_id; returns true if the tree held a nearer hit. `r` is
  // precompute(ray, bvh.has_triangles). `finished`: `hit` holds the record.
  bool (*intersect1)(const WideBvh& bvh, const RayPre& r, float t_min, float& best_t, std::uint32_t& best_id, Hit& hit,
                     bool& finished);
  bool (*occluded1)(const WideBvh& bvh, const RayPre& r, float t_min, float t_max);
  // Packet of 8: lanes with bit set in `valid`; per lane best_t / best_id / hits[lane] as above.
  // Returns the mask of lanes whose best came from the tree; `finished` the mask of those whose
  // hits[lane] the kernel wrote.
  std::uint32_t (*intersect8)(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid, float* best_t,
                              std::uint32_t* best_id, Hit* hits, std::uint32_t& finished);
  std::uint32_t (*occluded8)(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid);
  // The same for packets of 16 (one AVX-512 vector of floats; two AVX2, four SSE4 vectors).
  std::uint32_t (*intersect16)(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid, float* best_t,
                               std::uint32_t* best_id, Hit* hits, std::uint32_t& finished);
  std::uint32_t (*occluded16)(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid);
};

// The kernels compiled for `isa` (a SIMD isa that supported_isas() lists).
const Kernels& kernels_for(Isa isa);

struct AsideSpheres;  // geometry.h

// The 8-wide tree of a built Geometry (collapsed from its binary BVH). `aside`, where given: the
// prims are those set-aside spheres by id (a set-aside scene makes no Geometry prims).
// `prims_read_once`: the caller frees what the collapse reads the prims from after it (a build
// with its shapes set aside, which reads its spheres back from the wide tree's blocks), so the
// collapse gives those pages back as it reads them (the prims', or with `aside` the ids'); it
// keeps them for a tree that may collapse to one node (is_flat). `spheres_only`: every prim is a
// sphere (the collapse then sizes its arrays without reading the prims' types; a wrong claim
// writes out of bounds). Runs on up to `threads` threads (the caller's among them) of `pool`, the
// build's threads; the tree is the same whatever their number.
WideBvh collapse_to_wide(const Geometry& g, bool prims_read_once, bool spheres_only, util::ThreadPool& pool,
                         unsigned threads, const AsideSpheres* aside = nullptr);

}  // namespace dtraced::accel::detail
