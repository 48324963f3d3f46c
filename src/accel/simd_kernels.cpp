// dtraced::accel SIMD traversal kernels, compiled once per instruction set by Google Highway.
//
// This file includes itself once per target (foreach_target.h); everything between
// HWY_BEFORE_NAMESPACE and HWY_AFTER_NAMESPACE is compiled for SSE4, AVX2 and AVX-512 (and
// Highway's one-lane fallback), each in its own namespace, and kernels_for() at the end picks one
// by the Isa value Geometry was built with. Nothing here is global state: the tables are constant.
//
// Exactness: every leaf test repeats the scalar kernel of kernels.h operation for operation (the
// sphere in double, the triangle in float; separate Mul/Add/Sub/Div, never MulAdd, and the build
// passes -ffp-contract=off), so a lane's t has the same bits as the scalar path's, and the nearest
// hit is chosen by the same rule: smaller t, ties to the smaller shape id. Node tests only decide
// what is visited; they are the scalar node_hit arithmetic too, and conservative, so they cannot
// change an answer.
//
// Layouts: single rays test the 8 child boxes of a node in one 8-lane float vector (two on SSE4)
// and a leaf's 4 spheres (double) or 4 triangles (float) at once. Packets hold 8 or 16 rays in SoA
// arrays (the code is templated on the width kP) and test one box, sphere or triangle against all
// of them (8: one AVX2/AVX-512 vector, two SSE4 vectors; 16: one AVX-512 vector of floats), with a
// per-stack-entry lane mask, children visited nearest first (nearest-hit queries); when at most kSwitch lanes remain
// active at a node (2 for both widths: 4 of 16 measured slower), those lanes finish that subtree
// as single rays. A 16-ray packet shares a node's fixed costs (its planes, ordering the children,
// the stack) between twice the rays: on 4x4-pixel camera blocks (dtraced-bench-rays, avx512) it
// traces about 1.3x the rays per second of two 8-ray packets on the mesh, 1.2x on the spheres. A packet's per-lane
// constants are computed a vector at a time (make_packet); its lanes as single rays only when a fallback needs them. A
// nearest-hit query keeps the edge functions of its best triangle test (LaneUvw) and the slot of its best prim in the
// leaf blocks, and writes the hit record itself (finish_triangles, finish_spheres; Intersect1 for a triangle): the
// vertices or the sphere come from a block the packet has just tested, not from the Shape (a cache miss per hit at 1M
// triangles), and a packet's lanes are finished a double vector at a time, their divisions and square roots
// overlapping. Against Geometry finishing them lane by lane from the Shape (dtraced-bench-rays, avx512, 1 thread,
// the two binaries alternated, 5 pairs, medians of per-pair ratios, load 6-8): mesh camera 8 / 16 rays 1.11x / 1.11x,
// secondary rays 1.08x; sphere field camera 1.04x / 1.14x. A leaf of triangles only, or of one sphere block, is
// described by its child reference itself (kTriLeaf), not only by its WideLeaf record: one dependent load less per
// leaf, and its blocks prefetched as a lane enters it. Tiny scenes come as a flat layout (detail::flat_wide: one node
// over one or two leaves), which these same loops walk.
//
// Packets whose lanes share their direction signs (camera and shadow packets nearly always do) are traversed
// as a whole instead (traverse_coherent, the scheme of Embree's coherent packets): one frustum test of a node's 8
// boxes, lane tests of only the children it passes, hit children ordered and pushed by the frustum's entry distance
// with their lane mask (no per-lane distance stack), lanes culled lazily on pop. Against the per-lane traversal
// (dtraced-bench-rays, 1 thread, both alternated in one process, 7 rounds, medians), mesh camera / shadow: avx512
// 1.09x / 1.12x, avx2 1.13x / 1.27x, sse4 1.26x / 1.35x; sphere field 1.09x / 1.18x, 1.12x / 1.26x, 1.26x / 1.98x.
// The same for 8-ray packets (alternated likewise, 6-8 rounds), camera / shadow: mesh avx512 1.26x / 1.29x, avx2
// 1.09x / 1.10x, sse4 1.26x / 1.38x; sphere field avx512 1.12x / 1.21x, sse4 1.14x / 1.33x. Packets with mixed
// direction signs keep the per-lane traversal (traverse8).
//
// Tried and dropped (issue 16, round 5): the same frustum test ahead of the per-lane traversal (its child sort, its
// per-lane distance stack): on 4x4 camera packets of the 1M-triangle mesh it cut the children tested lane by lane
// from 7.2 to 1.65 per node, yet made 16-ray camera packets 7 % and 8-ray ones 15 % slower. In the first version of
// the coherent traversal, a scalar loop over the lanes for the largest cull distance at every node (now kept up to
// date only when a lane's hit improves) and a scalar frustum set-up made it 4 % (camera) and 6 % (shadow) slower than
// the per-lane one. Prefetching the children a node pushes in the per-lane traversal (no prefetch was emitted then: see
// prefetch_child), and leaving 16-ray packets at 1 or 3 live lanes (or, in the coherent traversal, 0 or 1) instead of
// 2: within noise (the coherent traversal now leaves at 1: kSwitchCoherent).
//
// Tried and dropped (Dec 4, sphere field, avx512, 16-ray camera packets against the same code without the change,
// processes alternated, 8-10 rounds each, medians of per-round ratios, load average 4-7): in the coherent traversal
// of a packet that shares its origin, taking the lane tests' plane-minus-origin differences from the frustum test
// (exact there, since the origin bounds are the origin) instead of subtracting per lane: 0.99x; an inner frustum test
// (the largest entry and smallest exit distance of any lane, from the corner products) that lets the children every
// lane enters skip their lane tests, with the smallest cull distance kept beside the largest: 0.95x; copying a lane's
// edge functions out only when its best is a triangle (a separate mask for the single-ray ones): 0.98x; prefetching
// every child the frustum test passes, before the lane tests: 1.00x. For single rays (mesh secondary rays, 16
// rounds), prefetching every child a node test passes: 1.00-1.02x. (These prefetches went through a plain inline
// helper, which GCC 12 drops in this file: likely not emitted. See prefetch_child, and the emitted ones below.)
//
// Tried and dropped (issue 16, round 13): quantised nodes (wide_bvh.h's WideNode) of two cache lines (Embree's
// compressed node: per axis a float origin and a power-of-two step, 8-bit child planes origin + float(q) * step, each q
// stepped outward at build time until that float expression contains the true plane, so the hits keep their bits; every
// isa's tests passed, tree unchanged). On the 1M-triangle mesh (dtraced-bench-rays, avx512, 1 thread, alternated with
// the float node, 5 pairs, load 7-8): secondary rays 0.84x (every pair below 0.96), 16-ray camera and shadow packets
// 0.975x and 0.94x, 8-ray ones 0.94x and 0.95x; in 2 more pairs with Embree, secondary / rtcIntersect1 0.66 ->
// 0.55-0.58, camera x16 / rtcIntersect16 0.75-0.81 -> 0.69-0.70, shadow x16 / rtcOccluded16 0.87 -> 0.77-0.79. Float
// nodes holding the dequantised (looser) boxes, 4 pairs: secondary 0.97x (the unchanged scalar path 0.98x in the same
// pairs), 16-ray camera and shadow 0.955x and 0.97x. So the single-ray loss is the dequantisation's latency (convert,
// multiply, add before the slab arithmetic, on every node's path to its child), which the halved node memory did not
// win back (a node's first load was 10 % of the walk); the packets' is mostly the looser boxes. Forcing triangles1
// inline into leaf1 (it is called out of line, with a vzeroupper): secondary 0.99x (8 pairs).
//
// Issue 16, round 14 (single rays, after Embree's BVH8 walk, bvh_traverser1.h): traverse1 chooses each axis's near
// and far planes once per ray (byte offsets into the node, NodeRay1) instead of per node, keeps the ray's constants in
// vectors, and enters a lone hit child without a push or a sort, orders two with one comparison, and sorts only three
// or more. Same visits, same bits. 1M-triangle mesh, avx512, 1 thread, old and new binaries alternated at load 8-13
// (other builds): secondary rays 1.075x (4 pairs, --no-embree, medians of per-pair ratios; the unchanged scalar path
// 1.01x), and against rtcIntersect1 in the same process 0.59 / 0.66 / 0.65 -> 0.77 / 0.72 / 0.78 (3 pairs). The sphere
// field's secondary rays against rtcIntersect1: 0.84 / 0.82 -> 0.97 / 0.98 (2 pairs). Tried and dropped: the same
// offsets in the coherent walk's frustum and lane tests (Frustum): 16-ray shadow packets against rtcOccluded16 0.79 (3
// pairs) where the single-ray change alone gave 0.89, camera within noise. Leaf blocks on that mesh: a leaf of up to 4
// prims (bvh.cpp's kMaxLeafSize) is one 4-lane block, and 1,040,000 triangles over 337,571 leaves (Geometry::stats)
// is 3.08 a block, 77 % of the lanes (derived from the counts, not counted lane by lane); packets test one triangle
// broadcast against their lanes (triangle8), as Embree's coherent packets do.
//
// Issue 16, round 15 (single rays; nothing kept). Measured in one process: the 1M-triangle mesh's secondary rays
// through Geometry::intersect on avx512, two to four variants of traverse1 switched every 512 packets, 30-60 rounds,
// medians of per-round ratios, load 5-9 on the 2-core AMD EPYC VM (separate processes drifted by 3-5 % between
// pairs there). The node test without the Min chain after the Max chain (t0 compared with each axis's far distance
// times kFarScale and with the cull distance; !(t0 > far) keeps the NaN rule, so the same children): 0.995x, and
// 0.996x / 1.008x in coarser runs. Prefetching a node's child-reference line (the one its plane loads do not touch)
// as it is entered: 1.00x. Prefetching the stack top's lines when a leaf is entered: 0.988x; with the node test
// above: 0.994x. (Neither prefetch was emitted: see prefetch_child; redone with emitted prefetches below.) triangles1
// skipping the error bound when no lane's t lies in (t_min, best_t] (the same answers: such lanes could not
// win): 1.008x / 1.000x (both orders). For 16-ray camera packets, a shared origin's vertex differences taken once per
// triangle in scalar (same bits): 1.000x / 0.986x (200 rounds each order). Not built: a leaf without the edge functions
// (stored only when a lane passes the edge test; those stores hold 0.01 % of triangles1's samples) and a smaller stack
// entry (already 8 bytes). Where a secondary ray's time goes (perf, 2999 Hz): traverse1 54 % (10 % on a node's first
// load, 5 % on the branch taken when no child is hit), triangles1 19 % (22 % of it on the block's first load),
// Geometry::intersect's ray set-up 6 %: waiting on memory and branches, not the node test's arithmetic.
//
// Issue 16, round 16 (the tree the mesh walks; nothing kept). Counted with temporary counters in these kernels, the
// 1M-triangle mesh (dtraced-bench-rays, avx512, tree of bvh.cpp's constants: kBins 32, kTraversalCost 0.5,
// kSimdLeafSlope 0.3, kMaxLeafSize 4): per secondary ray 9.06 wide nodes, 2.04 leaves, 7.1 triangles; per 16-ray camera
// packet 8.2 nodes (the coherent walk's and its single-ray lanes'), 0.35 leaves, 1.1 triangles; per 16-ray shadow
// packet 9.9 nodes, 0.70 leaves, 2.3 triangles (leaves and triangles tested by the packet's vector code only; counting
// every leaf any lane enters, a later count of the same tree found 7.3 nodes, 2.64 leaves and 8.9 triangle tests per
// camera packet, 8.6 / 3.3 / 11.3 per shadow packet: docs/figures.md, Kernels). The wide tree then held 4.1 children a
// node (108,163 nodes, 337,571 leaves; the SAH collapse has since made it 67,543 nodes); its SAH (root area 1, per node
// / block / triangle) 31.9 / 16.0 / 52.9. Packets pay for nodes, not leaves. Tree variants against it (same bits:
// nearest by t, ties by id): kTraversalCost 0.25 or 1 alone moves the counts by under 1 % (leaves of up to 4 prims are
// what the SAH takes anyway). kMaxLeafSize 8 (two blocks a leaf, which the collapse and kernels handle) cuts nodes per
// secondary ray to 8.4 and per camera packet to 7.3, but triangles per secondary ray rise to 12.7 (3.64 blocks);
// Embree's weights (traversal 1, leaves and children costed by blocks of 4, up to 16 prims a leaf; needs the split
// sweeps' counts in blocks) give packets the same counts as kMaxLeafSize 8. Measured, old and new trees alternated in
// separate processes (6 pairs, --runs 5, load average 11-13): kTraversalCost 1.5 with kMaxLeafSize 8 gave 16-ray camera
// 1.007x, 16-ray shadow 1.010x, 8-ray camera 0.978x, secondary 0.963x (ratios to Embree in the same runs: camera x16
// 0.761 -> 0.762, shadow x16 0.852 -> 0.848, secondary 0.744 -> 0.715), the mesh build 0.81 -> 0.66 s; kTraversalCost 1
// with kMaxLeafSize 8 (4 pairs, load 11-12) 16-ray 1.05x, secondary 0.96x. Fewer nodes at the price of more triangles
// is a wash for packets and a loss for single rays: the tree is not the gap to Embree.
//
// Issue 16, round 17 (single rays). Single points at the caller's RayPre instead of copying it: the copy was a 64-byte
// load over the scalar stores precompute() had just made (not forwardable: it waits for them to reach the cache)
// and a wide store the walk then read with scalar loads; perf put about a third of Intersect1's samples there.
// Measured in one process (the old copy and the pointer switched every 512 packets, 60 rounds, medians of per-round
// ratios, avx512, load 7-9): 1M-triangle mesh secondary rays 1.020x, single shadow rays 1.019x, the mesh at 104k
// triangles 1.033x, sphere field secondary rays 1.049x (40 rounds). Tried and dropped, the same way (1M mesh, 20-60
// rounds): a leaf block's four nearest-hit comparisons skipped when no lane's t is <= best_t, two children ordered
// without a branch (xor-select of reference and distance), and set_shear without a branch on the axis and the swap:
// 0.983-1.003x each, 0.987-1.011x together, within the noise of a null A/B (0.995-1.003). Counted on the mesh: of a
// secondary ray's node tests 11.4 % hit no child, 65.9 % one, 17.4 % two and 5.4 % three or more, so the order of
// hit children is rarely worth more than one comparison. Embree's own statistics (device config verbose=2) for the
// same 1M triangles: 60,646 wide nodes 65 % full and 255,262 leaves, against our 108,163 nodes then (4.1 children,
// about half full; 67,543 since the SAH collapse) and 337,571 leaves at 3.08 triangles a block; at 104k triangles 6,426
// against 9,111 nodes, and the ratio to rtcIntersect1 is the same there (0.72) as at 1M, so the gap is the number of
// nodes and leaves a ray visits, not cache misses. Then the single-ray stack as two arrays of words instead of 8-byte
// entries (the pop's 8-byte load could not be forwarded from the push's two 4-byte stores; see traverse1): mesh
// secondary rays 1.012x / 1.046x, the 104k-triangle mesh 1.028x, sphere field 1.023x, single shadow rays 1.008x.
//
// Any-hit packets take their blocked lanes from the triangle test itself (blocked_lanes, figures there). Tried and
// dropped beside it (1M-triangle mesh, dtraced-bench-rays, avx512, 1 thread, binaries alternated, 5 pairs, medians of
// per-pair ratios, load 4-6; paths whose code did not change moved by up to 1-2 % in the same pairs): nearest-hit
// packets skipping the error bound when no wanted lane inside the triangle has t in (t_min, best]: camera x16 0.993x,
// x8 1.013x; blocked_lanes' all-outside exit over the mask's lanes only: shadow x16 1.002x, x8 0.992x; prefetch_child
// also asking for a triangle block's last line (a 160-byte block spans four lines unless it starts within 32 bytes
// of one): camera x16 1.014x, shadow x16 1.004x, secondary rays (unchanged) 1.011x. A leaf holds at most one
// triangle block (bvh.cpp's kMaxLeafSize 4), so a single ray's leaf test has no second block to take in the same
// vector. Where a secondary ray's time goes on the Intel host (perf, cpu-clock, --rays secondary): traverse1 75 % of
// the kernel's samples, triangles1 25 %; in traverse1 the first load of a node's planes about 14 %, the load of the
// child reference after the test 5 %, in triangles1 the block's first load 14 % and the error bound's division 13 %.
//
// Issue 16 (single rays, prefetches that are emitted; nothing kept). The single-ray prefetches above redone with
// prefetch_child (forced inline; objdump of this object: 72 prefetch instructions before, 252 with the first variant).
// dtraced-bench-rays --rays secondary, avx512, 1 thread, --no-embree, base and variant binaries alternated, medians of
// per-pair ratios, load average 3-4, 0 disagreements on every path. prefetch_child on every child traverse1 pushes (a
// node's 4 lines, a leaf's block; so the stack top when a leaf is entered, and earlier), in all its callers:
// 1M-triangle mesh 1.010x and 1.017x (6 + 6 pairs), sphere field 0.999x (6 pairs); mesh 16-ray camera packets, whose
// lanes may finish as single rays, 0.994x, 8-ray 0.988x, 16-ray shadow 0.997x. The same for Intersect1 and Occluded1
// only: mesh 1.014x (12 pairs, 8 above 1), sphere field 0.992x (6 pairs). A pushed node's 4 lines only (no leaf block):
// mesh 1.009x, then 1.000x (6 + 8 pairs), sphere field 1.004x, then 0.992x. Adding a prefetch of the entered node's
// child-reference line to the push prefetch: 0.985x against it (6 pairs). All within the pairs' noise. Our reading (not
// counted): a pushed child has rarely left the cache by the time it is popped, and the misses perf sees lie on the
// dependent chain node planes -> test -> child reference -> next node (66 % of node tests hit one child, entered at
// once), which a prefetch cannot start any earlier.
//
// Issue 16 (single rays walked several at once; nothing kept). traverse1's loop cut into steps (a node test with its
// choice of child, or a leaf test and a pop) over a state per ray (NodeRay1, stack, cull distance), and K lanes of a
// packet stepped round-robin from the root, each with traverse1's visits and answer (0 disagreements). In one process
// on the 1M-triangle mesh's secondary rays in their packets (dtraced-bench-rays, avx512, 1 thread, variants
// alternated, 20 rounds, medians of per-round ratios, load 1-2), against the same lanes walked by traverse1 one after
// another behind the same packet set-up: K = 16 1.048x and 1.032x, K = 8 1.024x, K = 4 1.008x, K = 2 0.99x; two or
// four steps per ray per turn (K = 16) 0.987x / 0.944x; a prefetch of the node or leaf a step moves to (used K - 1
// steps later) 0.95-0.99x. Sphere field, K = 16: 1.09x. Setting a packet's lanes up as single rays costs 12 % over
// Geometry::intersect's own set-up, so the walk would not even beat single rays. The per-lane packet walk (traverse8)
// on the same packets beats all of it: per ray against traverse1 one ray at a time, mesh 1.19x (8-ray packets) and
// 1.37x (16), sphere field 1.38x / 1.68x (the bench's secondary rays leave neighbouring pixels' hits and share the
// upper part of their walks). Our reading (not counted): every step ends in data-dependent branches (children hit,
// node or leaf, pop), and a mispredicted one discards the other rays' steps issued after it, so little of one ray's
// latency overlaps another's; the tree's 17 MB of nodes stay in this host's caches.
//
// Issue 16 (packets; nothing kept). 1M-triangle mesh, dtraced-bench-rays, avx512, 1 thread, --no-embree, base and
// variant binaries alternated, 6 pairs (4 for kSwitch), medians of per-pair ratios, load 1.2-1.7; a null pair (two
// builds of the same kernel) gave 0.965-1.028 per pair, median 1.011. Coherent any-hit walk, shadow x16: the frustum
// made again over the lanes still unblocked whenever a leaf blocks some (and the cull bound with it) 0.995x; hit
// children visited nearest first 0.984x, farthest first 0.985x, in node order (first slot first) 0.989x;
// kSwitchCoherent 2 for any-hit 0.983x; no lane test for inner children (the frustum alone; leaves keep theirs) 0.63x,
// none at all 0.32x. The per-lane walk (traverse8) on the secondary rays in packets, x16 / x8: kSwitch 1 1.013x /
// 1.017x, 3 0.961x / 0.981x, 4 0.988x / 0.971x, 6 0.921x / 0.892x; prefetch_child on every child a lane enters 1.011x
// / 0.976x.
#undef HWY_TARGET_INCLUDE
#define HWY_TARGET_INCLUDE "simd_kernels.cpp"
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <limits>

#include <hwy/foreach_target.h>  // IWYU pragma: keep
#include <hwy/highway.h>

#include "accel/geometry.h"
#include "accel/kernels.h"
#include "accel/wide_bvh.h"

HWY_BEFORE_NAMESPACE();
namespace dtraced::accel::detail {
namespace HWY_NAMESPACE {
namespace hn = hwy::HWY_NAMESPACE;

constexpr int kStackSize = (kNodeWidth - 1) * Geometry::kMaxDepth + kNodeWidth;
constexpr int kMaxPacket = kPacketSize16;  // lanes of the widest packet

// The first n (at most 16) bits StoreMaskBits wrote to mb.
inline std::uint32_t low_bits(const std::uint8_t* mb, std::size_t n) {
  return (std::uint32_t(mb[0]) | std::uint32_t(mb[1]) << 8) & ((1u << n) - 1u);
}
// Bit i of every lane i (the lane masks of a packet as a vector mask).
alignas(64) inline constexpr std::uint32_t kLaneBit[16] = {1u << 0,  1u << 1,  1u << 2,  1u << 3, 1u << 4,  1u << 5,
                                                           1u << 6,  1u << 7,  1u << 8,  1u << 9, 1u << 10, 1u << 11,
                                                           1u << 12, 1u << 13, 1u << 14, 1u << 15};

constexpr int kSwitch = 2;  // lanes at or below which a packet continues as single rays
// The same for the coherent traversal: only a lone lane leaves the packet. Measured again after
// the packet set-up moved into registers (the round 6 comparison was within noise): 1 against 2,
// dtraced-bench-rays' rays through a driver, avx512, the two alternated, medians of per-round
// ratios at load 3-5: sphere field camera 16 rays 1.04x (20 rounds), 8 rays 1.08x (8), mesh
// camera 16 rays 1.07x and 8 rays 1.04x (5-6), shadow rays 1.00-1.01x. 0 (a lone lane stays in
// the packet) against 1: sphere field camera 16 rays 1.05x (14 rounds, 0.69-1.43), mesh 0.94x (5).
constexpr int kSwitchCoherent = 1;
constexpr float kInfF = std::numeric_limits<float>::infinity();

// ---------------------------------------------------------------------------------------------
// Single ray.

// The ray's constants stay where the caller made them: Single points at them. A copy (as it was)
// is one wide load over the caller's scalar stores of a RayPre just made, which cannot be
// forwarded from them and waits for them to reach the cache, and a wide store read back by the
// walk's scalar loads: perf put about a third of Intersect1's samples on the first use of the copy.
struct Single {
  const RayPre* rp;
  float t_min;
  double a;  // |d|^2 in double, as sphere_roots computes it
  const RayPre& r() const { return *rp; }
};

inline Single make_single(const RayPre& r, float t_min) {
  Single s;
  s.rp = &r;
  s.t_min = t_min;
  const double dx = r.d[0], dy = r.d[1], dz = r.d[2];
  s.a = dx * dx + dy * dy + dz * dz;
  return s;
}

// A single ray's node-test constants, made once per walk (Embree's habit): per axis the byte offsets
// in a WideNode of the child planes the ray meets first and last (lo or hi by the direction's sign,
// so no select per node and axis), and the origin, inverse direction and t_min as vectors.
template <class D>
struct NodeRay1 {
  std::size_t near_off[3], far_off[3];
  hn::Vec<D> o[3], inv[3], t_min;
};
template <class D>
HWY_INLINE NodeRay1<D> make_node_ray1(D d, const Single& s) {
  NodeRay1<D> nr;
  for (int a = 0; a < 3; ++a) {
    const std::size_t lo = offsetof(WideNode, lo) + std::size_t(a) * sizeof(WideNode::lo[0]);
    const std::size_t hi = offsetof(WideNode, hi) + std::size_t(a) * sizeof(WideNode::hi[0]);
    nr.near_off[a] = s.r().neg[a] ? hi : lo;
    nr.far_off[a] = s.r().neg[a] ? lo : hi;
    nr.o[a] = hn::Set(d, s.r().o[a]);
    nr.inv[a] = hn::Set(d, s.r().inv_d[a]);
  }
  nr.t_min = hn::Set(d, s.t_min);
  return nr;
}
inline const float* node_planes(const WideNode& node, std::size_t off) {
  return reinterpret_cast<const float*>(reinterpret_cast<const char*>(&node) + off);
}

// Entry distances of the ray into the node's 8 child boxes (lanes whose bit is set in the
// result pass node_hit against `cull`).
template <class D>
HWY_INLINE std::uint32_t node_test1(D d, const WideNode& node, const NodeRay1<D>& nr, float cull, float* t_near) {
  const std::size_t n = hn::Lanes(d);
  std::uint32_t bits = 0;
  for (std::size_t i = 0; i < std::size_t(kNodeWidth); i += n) {
    auto t0 = nr.t_min;
    auto tf = hn::Set(d, kInfF);
    for (int a = 0; a < 3; ++a) {
      const auto tn = hn::Mul(hn::Sub(hn::LoadU(d, node_planes(node, nr.near_off[a]) + i), nr.o[a]), nr.inv[a]);
      const auto tfa = hn::Mul(hn::Sub(hn::LoadU(d, node_planes(node, nr.far_off[a]) + i), nr.o[a]), nr.inv[a]);
      // Max(tn, t0) is tn > t0 ? tn : t0 on x86 (maxps returns its second operand when one is
      // NaN) and skips NaN on Highway's scalar target: a NaN slab (0 * inf) never constrains.
      t0 = hn::Max(tn, t0);
      tf = hn::Min(tfa, tf);
    }
    tf = hn::Mul(tf, hn::Set(d, kFarScale));
    const auto lim = hn::Min(tf, hn::Set(d, cull));
    hn::StoreU(t0, d, t_near + i);
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, hn::Le(t0, lim), mb);
    bits |= low_bits(mb, n) << i;
  }
  return bits;
}

// The sphere test of kernels.h (sphere_roots, then sphere_t's choice of root) on one vector of
// lanes, operation for operation: from f = o - c, the direction d, a = |d|^2 and r^2, all in
// double, and t_min per lane, t gets each lane's chosen float root or NaN. Shared by the single-ray
// and the packet kernels, whose loops make the constants once (SphereConsts) and pass them in.
template <class DD, class DF>
struct SphereConsts {
  hn::Vec<DD> zero, nan;  // double
  hn::Vec<DF> inf, nanf;  // float
};
template <class DD, class DF>
HWY_INLINE SphereConsts<DD, DF> sphere_consts(DD dd, DF df) {
  return {hn::Zero(dd), hn::Set(dd, std::numeric_limits<double>::quiet_NaN()), hn::Set(df, kInfF),
          hn::Set(df, std::numeric_limits<float>::quiet_NaN())};
}
// The discriminant part (disc / 4 = a r^2 - |f x d|^2); lanes with disc >= 0 may hit.
template <class VD>
HWY_INLINE VD sphere_disc(VD fx, VD fy, VD fz, VD dx, VD dy, VD dz, VD a, VD rr) {
  const auto cx = hn::Sub(hn::Mul(fy, dz), hn::Mul(fz, dy));
  const auto cy = hn::Sub(hn::Mul(fz, dx), hn::Mul(fx, dz));
  const auto cz = hn::Sub(hn::Mul(fx, dy), hn::Mul(fy, dx));
  return hn::Sub(hn::Mul(a, rr), hn::Add(hn::Add(hn::Mul(cx, cx), hn::Mul(cy, cy)), hn::Mul(cz, cz)));
}
// The rest, for lanes `ok` (disc >= 0): each lane's chosen float root or NaN.
template <class DD, class DF, class VD, class VF>
HWY_INLINE VF sphere_root(DD /*dd*/, DF df, const SphereConsts<DD, DF>& k, hn::Mask<DD> ok, VD disc, VD fx, VD fy,
                          VD fz, VD dx, VD dy, VD dz, VD a, VD rr, VF tmin) {
  const auto zero = k.zero, nan = k.nan;
  const auto inf = k.inf, nanf = k.nanf;
  const auto bq = hn::Add(hn::Add(hn::Mul(fx, dx), hn::Mul(fy, dy)), hn::Mul(fz, dz));
  const auto c = hn::Sub(hn::Add(hn::Add(hn::Mul(fx, fx), hn::Mul(fy, fy)), hn::Mul(fz, fz)), rr);
  const auto q = hn::Neg(hn::Add(bq, hn::CopySign(hn::Sqrt(hn::IfThenElse(ok, disc, zero)), bq)));
  const auto r0 = hn::Div(c, q);
  const auto r1 = hn::Div(q, a);
  const auto swap = hn::Gt(r0, r1);
  const auto lo = hn::IfThenElse(ok, hn::IfThenElse(swap, r1, r0), nan);
  const auto hi = hn::IfThenElse(ok, hn::IfThenElse(swap, r0, r1), nan);
  const auto t0 = hn::DemoteTo(df, lo);
  const auto t1 = hn::DemoteTo(df, hi);
  const auto use0 = hn::And(hn::Gt(t0, tmin), hn::Lt(t0, inf));
  const auto use1 = hn::And(hn::Gt(t1, tmin), hn::Lt(t1, inf));
  return hn::IfThenElse(use0, t0, hn::IfThenElse(use1, t1, nanf));
}
template <class DD, class DF, class VD, class VF>
HWY_INLINE void sphere_lanes(DD dd, DF df, const SphereConsts<DD, DF>& k, VD fx, VD fy, VD fz, VD dx, VD dy, VD dz,
                             VD a, VD rr, VF tmin, float* t) {
  const auto disc = sphere_disc(fx, fy, fz, dx, dy, dz, a, rr);
  const auto ok = hn::Ge(disc, k.zero);
  if (hn::AllFalse(dd, ok)) {  // most sphere tests miss: skip the square root and divisions
    hn::StoreU(k.nanf, df, t);
    return;
  }
  hn::StoreU(sphere_root(dd, df, k, ok, disc, fx, fy, fz, dx, dy, dz, a, rr, tmin), df, t);
}

// Sphere roots of one ray against a block of 4 spheres, in double exactly as sphere_roots and
// sphere_t; t[i] gets the chosen float root or NaN.
inline void spheres1(const SphereBlock& b, const Single& s, float* t) {
  const hn::CappedTag<double, kWidth> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const std::size_t n = hn::Lanes(dd);
  const auto ox = hn::Set(dd, double(s.r().o[0])), oy = hn::Set(dd, double(s.r().o[1])),
             oz = hn::Set(dd, double(s.r().o[2]));
  const auto dx = hn::Set(dd, double(s.r().d[0])), dy = hn::Set(dd, double(s.r().d[1])),
             dz = hn::Set(dd, double(s.r().d[2]));
  const auto a = hn::Set(dd, s.a);
  const auto tmin = hn::Set(df, s.t_min);
  const auto k = sphere_consts(dd, df);
  for (std::size_t i = 0; i < std::size_t(kWidth); i += n) {
    const auto fx = hn::Sub(ox, hn::PromoteTo(dd, hn::LoadU(df, b.cx + i)));
    const auto fy = hn::Sub(oy, hn::PromoteTo(dd, hn::LoadU(df, b.cy + i)));
    const auto fz = hn::Sub(oz, hn::PromoteTo(dd, hn::LoadU(df, b.cz + i)));
    const auto rad = hn::PromoteTo(dd, hn::LoadU(df, b.r + i));
    sphere_lanes(dd, df, k, fx, fy, fz, dx, dy, dz, a, hn::Mul(rad, rad), tmin, t + i);
  }
}

// triangle_t_error of kernels.h, lane-wise, with the same operations in the same order (Max of
// two non-NaN values is exact whichever operand wins).
template <class D, class V>
inline V triangle_t_error8(D d, V sax, V say, V sbx, V sby, V scx, V scy, V saz, V sbz, V scz, V u, V v, V w, V det) {
  const auto g2 = hn::Set(d, math::gamma(2)), g3 = hn::Set(d, math::gamma(3)), g5 = hn::Set(d, math::gamma(5));
  const auto max_zt = hn::Max(hn::Max(hn::Abs(saz), hn::Abs(sbz)), hn::Abs(scz));
  const auto max_xt = hn::Max(hn::Max(hn::Abs(sax), hn::Abs(sbx)), hn::Abs(scx));
  const auto max_yt = hn::Max(hn::Max(hn::Abs(say), hn::Abs(sby)), hn::Abs(scy));
  const auto delta_z = hn::Mul(g3, max_zt);
  const auto delta_x = hn::Mul(g5, hn::Add(max_xt, max_zt));
  const auto delta_y = hn::Mul(g5, hn::Add(max_yt, max_zt));
  const auto delta_e = hn::Mul(
      hn::Set(d, 2.0f),
      hn::Add(hn::Add(hn::Mul(hn::Mul(g2, max_xt), max_yt), hn::Mul(delta_y, max_xt)), hn::Mul(delta_x, max_yt)));
  const auto max_e = hn::Max(hn::Max(hn::Abs(u), hn::Abs(v)), hn::Abs(w));
  const auto num =
      hn::Mul(hn::Set(d, 3.0f),
              hn::Add(hn::Add(hn::Mul(hn::Mul(g3, max_e), max_zt), hn::Mul(delta_e, max_zt)), hn::Mul(delta_z, max_e)));
  return hn::Div(num, hn::Abs(det));
}

// Edge functions of the latest triangle test, per lane (a single ray's block of 4 or a packet's
// 8): the float ones, or for the lanes in `fallback` the double ones of triangle_t_double. A
// lane that hit gets them exactly as triangle_t reports them; kept for the nearest hit only.
struct LaneUvw {
  alignas(64) float u[kMaxPacket];
  alignas(64) float v[kMaxPacket];
  alignas(64) float w[kMaxPacket];
  alignas(64) float det[kMaxPacket];
  TriangleUvw fb[kMaxPacket];
  std::uint32_t fallback = 0;
  TriangleUvw get(std::size_t i) const {
    if (fallback >> i & 1u) return fb[i];
    return {double(u[i]), double(v[i]), double(w[i]), double(det[i])};
  }
};

// The watertight test's float edge functions u, v, w of one vector of lanes (from the sheared
// vertices sax ... scy), and which lanes have one below, above or exactly at zero.
template <class V>
struct EdgeFunctions {
  V u, v, w;
  decltype(hn::Lt(std::declval<V>(), std::declval<V>())) neg, pos, zero_edge;
};
template <class V>
HWY_INLINE EdgeFunctions<V> edge_functions(V zero, V sax, V say, V sbx, V sby, V scx, V scy) {
  const auto u = hn::Sub(hn::Mul(scx, sby), hn::Mul(scy, sbx));
  const auto v = hn::Sub(hn::Mul(sax, scy), hn::Mul(say, scx));
  const auto w = hn::Sub(hn::Mul(sbx, say), hn::Mul(sby, sax));
  return {u,
          v,
          w,
          hn::Or(hn::Or(hn::Lt(u, zero), hn::Lt(v, zero)), hn::Lt(w, zero)),
          hn::Or(hn::Or(hn::Gt(u, zero), hn::Gt(v, zero)), hn::Gt(w, zero)),
          hn::Or(hn::Or(hn::Eq(u, zero), hn::Eq(v, zero)), hn::Eq(w, zero))};
}

// The watertight test of kernels.h (triangle_t, float part) on one vector of lanes, operation for
// operation: from the vertices relative to the origin, already sheared in x and y (sax ... scy),
// their z before the shear (az, bz, cz), the shear sz and t_min per lane, t gets each lane's t or
// NaN. Returns the lanes whose float edge function came out exactly zero, which the caller redoes
// with the scalar triangle_t_double. Shared by the single-ray and the packet kernels, whose loops
// make the constants 0, +Inf and NaN once and pass them in. With `uvw`, the lanes' edge functions
// go to uvw->{u, v, w, det}[off ...] (unless every wanted lane misses). kMasked: only the lanes of
// `active` are wanted (else every lane, and `active` is not read): when every wanted lane misses,
// t is all NaN and no lane is returned. `full` (where given) is set when some wanted lane went past
// the edge test.
template <bool kMasked, class D, class V, class M>
HWY_INLINE auto triangle_lanes(D d, V zero, V inf, V nan, V sax, V say, V sbx, V sby, V scx, V scy, V az, V bz, V cz,
                               V sz, V tmin, M active, float* t, LaneUvw* uvw, std::size_t off, bool* full = nullptr) {
  const auto [u, v, w, neg, pos, zero_edge] = edge_functions(zero, sax, say, sbx, sby, scx, scy);
  // The common case: every wanted lane outside.
  if constexpr (kMasked) {
    if (hn::AllFalse(d, hn::And(active, hn::Or(zero_edge, hn::Not(hn::And(neg, pos)))))) {
      hn::StoreU(nan, d, t);
      return hn::And(zero_edge, active);  // no lane
    }
  } else {
    (void)active;
    if (hn::AllTrue(d, hn::AndNot(zero_edge, hn::And(neg, pos)))) {
      hn::StoreU(nan, d, t);
      return zero_edge;  // no lane
    }
  }
  if (full != nullptr) *full = true;
  const auto det = hn::Add(hn::Add(u, v), w);
  if (uvw != nullptr) {
    hn::StoreU(u, d, uvw->u + off);
    hn::StoreU(v, d, uvw->v + off);
    hn::StoreU(w, d, uvw->w + off);
    hn::StoreU(det, d, uvw->det + off);
  }
  const auto saz = hn::Mul(sz, az), sbz = hn::Mul(sz, bz), scz = hn::Mul(sz, cz);
  const auto tt = hn::Add(hn::Add(hn::Mul(u, saz), hn::Mul(v, sbz)), hn::Mul(w, scz));
  const auto tv = hn::Div(tt, det);
  const auto err = triangle_t_error8(d, sax, say, sbx, sby, scx, scy, saz, sbz, scz, u, v, w, det);
  const auto ok = hn::AndNot(hn::And(neg, pos), hn::And(hn::And(hn::Ne(det, zero), hn::Gt(tv, err)),
                                                        hn::And(hn::Gt(tv, tmin), hn::Lt(tv, inf))));
  hn::StoreU(hn::IfThenElse(ok, tv, nan), d, t);
  return zero_edge;
}

// Redoes the lanes of `zero_edge` (a ray through an edge or a vertex: rare) with the scalar
// triangle_t_double, from the sheared coordinates `v` (sax, say, sbx, sby, scx, scy, az, bz, cz).
// lane_ray(k) is lane k's Single. With `uvw`, those lanes' double edge functions go to
// uvw->fb[off + k] and their bits into uvw->fallback.
template <class D, class M, class LaneRay>
HWY_INLINE void redo_zero_edges(D d, M zero_edge, const hn::Vec<D> (&v)[9], float* t, LaneRay lane_ray, LaneUvw* uvw,
                                std::size_t off) {
  if (hn::AllFalse(d, zero_edge)) return;
  alignas(64) float l[9][kMaxPacket];  // lanes of a single-ray block (4) or a packet (8 or 16)
  for (int j = 0; j < 9; ++j) hn::StoreU(v[j], d, l[j]);
  std::uint8_t mb[8] = {};
  hn::StoreMaskBits(d, zero_edge, mb);
  for (std::size_t k = 0; k < hn::Lanes(d); ++k) {
    if (low_bits(mb, hn::Lanes(d)) >> k & 1u) {
      const Single& s = lane_ray(k);
      TriangleUvw* out = nullptr;
      if (uvw != nullptr) {
        out = &uvw->fb[off + k];
        uvw->fallback |= 1u << (off + k);
      }
      t[k] = triangle_t_double(l[0][k], l[1][k], l[2][k], l[3][k], l[4][k], l[5][k], l[6][k], l[7][k], l[8][k], s.r(),
                               s.t_min, out);
    }
  }
}

// Watertight test of one ray against a block of 4 triangles, exactly as triangle_t; lanes whose
// float edge function is zero are redone by the scalar triangle_t_double. With `uvw`, the
// lanes' edge functions too.
inline void triangles1(const TriangleBlock& b, const Single& s, float* t, LaneUvw* uvw) {
  const hn::CappedTag<float, kWidth> d;
  const std::size_t n = hn::Lanes(d);
  const RayPre& r = s.r();
  const auto ox = hn::Set(d, r.o[r.kx]), oy = hn::Set(d, r.o[r.ky]), oz = hn::Set(d, r.o[r.kz]);
  const auto sx = hn::Set(d, r.sx), sy = hn::Set(d, r.sy), sz = hn::Set(d, r.sz);
  const auto tmin = hn::Set(d, s.t_min);
  const auto zero = hn::Zero(d), inf = hn::Set(d, kInfF), nan = hn::Set(d, std::numeric_limits<float>::quiet_NaN());
  if (uvw != nullptr) uvw->fallback = 0;
  for (std::size_t i = 0; i < std::size_t(kWidth); i += n) {
    const auto ax = hn::Sub(hn::LoadU(d, b.v[0][r.kx] + i), ox), ay = hn::Sub(hn::LoadU(d, b.v[0][r.ky] + i), oy),
               az = hn::Sub(hn::LoadU(d, b.v[0][r.kz] + i), oz);
    const auto bx = hn::Sub(hn::LoadU(d, b.v[1][r.kx] + i), ox), by = hn::Sub(hn::LoadU(d, b.v[1][r.ky] + i), oy),
               bz = hn::Sub(hn::LoadU(d, b.v[1][r.kz] + i), oz);
    const auto cx = hn::Sub(hn::LoadU(d, b.v[2][r.kx] + i), ox), cy = hn::Sub(hn::LoadU(d, b.v[2][r.ky] + i), oy),
               cz = hn::Sub(hn::LoadU(d, b.v[2][r.kz] + i), oz);
    const auto sax = hn::Sub(ax, hn::Mul(sx, az)), say = hn::Sub(ay, hn::Mul(sy, az));
    const auto sbx = hn::Sub(bx, hn::Mul(sx, bz)), sby = hn::Sub(by, hn::Mul(sy, bz));
    const auto scx = hn::Sub(cx, hn::Mul(sx, cz)), scy = hn::Sub(cy, hn::Mul(sy, cz));
    const auto zero_edge = triangle_lanes<false>(d, zero, inf, nan, sax, say, sbx, sby, scx, scy, az, bz, cz, sz, tmin,
                                                 hn::Eq(zero, zero), t + i, uvw, i);
    redo_zero_edges(
        d, zero_edge, {sax, say, sbx, sby, scx, scy, az, bz, cz}, t + i,
        [&s](std::size_t) -> const Single& { return s; }, uvw, i);
  }
}

// The nearest-hit rule of Geometry::intersect.
inline bool better(float t, std::uint32_t id, float best_t, std::uint32_t best_id) {
  return t < best_t || (t == best_t && id < best_id);
}

// The triangle slot (block index * kWidth + lane) of a best hit that is not a triangle.
constexpr std::uint32_t kNoSlot = 0xffffffffu;

// One candidate (t, id) of a leaf test that is not a triangle. kAnyHit: true when it blocks
// (t < best_t). Otherwise applies the nearest-hit rule to best_t / best_id and records an
// improvement (the best is then no triangle: *slot = kNoSlot).
template <bool kAnyHit>
inline bool consider1(float t, std::uint32_t id, float& best_t, std::uint32_t& best_id, bool& improved,
                      std::uint32_t* slot) {
  if (kAnyHit) return t < best_t;
  if (better(t, id, best_t, best_id)) {
    best_t = t;
    best_id = id;
    improved = true;
    *slot = kNoSlot;
  }
  return false;
}

// Tests a leaf. kAnyHit: returns true at the first prim with t < best_t. Otherwise updates
// best_t / best_id (and *uvw and *slot when a triangle becomes the best, *slot = kNoSlot when
// another prim does) and returns whether anything improved.
template <bool kAnyHit>
inline bool leaf1(const WideBvh& bvh, const WideLeaf& leaf, const Single& s, float& best_t, std::uint32_t& best_id,
                  TriangleUvw* uvw, std::uint32_t* slot) {
  bool improved = false;
  alignas(64) float t[kWidth];
  for (std::uint32_t k = 0; k < leaf.sphere_blocks; ++k) {
    const SphereBlock& b = bvh.spheres[leaf.sphere_begin + k];
    spheres1(b, s, t);
    for (int i = 0; i < kWidth; ++i) {
      if (consider1<kAnyHit>(t[i], b.id[i], best_t, best_id, improved, slot)) return true;
    }
  }
  for (std::uint32_t k = 0; k < leaf.triangle_blocks; ++k) {
    const TriangleBlock& b = bvh.triangles[leaf.triangle_begin + k];
    if (kAnyHit) {
      triangles1(b, s, t, nullptr);
      for (int i = 0; i < kWidth; ++i) {
        if (t[i] < best_t) return true;
      }
    } else {
      LaneUvw lu;
      triangles1(b, s, t, &lu);
      for (int i = 0; i < kWidth; ++i) {
        if (better(t[i], b.id[i], best_t, best_id)) {
          best_t = t[i];
          best_id = b.id[i];
          improved = true;
          *uvw = lu.get(std::size_t(i));
          *slot = (leaf.triangle_begin + k) * std::uint32_t(kWidth) + std::uint32_t(i);
        }
      }
    }
  }
  for (std::uint32_t k = 0; k < leaf.box_count; ++k) {
    const BoxPrim& bp = bvh.boxes[leaf.box_begin + k];
    if (consider1<kAnyHit>(box_t(bp.b, s.r(), s.t_min), bp.id, best_t, best_id, improved, slot)) return true;
  }
  return improved;
}

struct Entry {
  std::uint32_t ref;
  float t_near;
};

// The leaf a reference (kLeafBit set) names: described by the reference itself (kTriLeaf) or by
// its WideLeaf record.
inline WideLeaf leaf_of(const WideBvh& bvh, std::uint32_t ref) {
  if (ref & kTriLeaf) return tri_leaf_of(ref);
  return bvh.leaves[ref & ~kLeafBit];
}

// Single-ray traversal of the subtree at `start` (a node index or kLeafBit | leaf). For nearest
// hits, best_t / best_id are updated (with *uvw and *slot as leaf1 says) and the result says
// whether they were; for any-hit, best_t is the ray's t_max and the result says whether something
// lies before it.
//
// The stack keeps references and entry distances in two arrays, each pushed and popped a word at a
// time: an Entry pushed as two 4-byte stores and popped as one 8-byte load (as GCC copied it) is a
// load that cannot be forwarded from the stores, and a pop often follows its push closely (the
// near child was a leaf). In one process against the Entry stack (avx512, medians of per-round
// ratios): 1M-triangle mesh secondary rays 1.012x / 1.046x (50 / 60 rounds, load 7 / 4), single
// shadow rays 1.008x, the 104k-triangle mesh 1.028x, sphere field secondary rays 1.023x.
template <bool kAnyHit>
bool traverse1(const WideBvh& bvh, const Single& s, std::uint32_t start, float& best_t, std::uint32_t& best_id,
               TriangleUvw* uvw, std::uint32_t* slot) {
  std::uint32_t stack_ref[kStackSize];
  float stack_t[kStackSize];
  int sp = 0;
  const auto push = [&](std::uint32_t ref, float t) {
    stack_ref[sp] = ref;
    stack_t[sp] = t;
    ++sp;
  };
  std::uint32_t cur = start;
  bool improved = false;
  float cull = best_t * kFarScale;
  const hn::CappedTag<float, kNodeWidth> d;
  const NodeRay1 nr = make_node_ray1(d, s);
  while (true) {
    if (cur & kLeafBit) {
      if (leaf1<kAnyHit>(bvh, leaf_of(bvh, cur), s, best_t, best_id, uvw, slot)) {
        if (kAnyHit) return true;
        improved = true;
        cull = best_t * kFarScale;
      }
    } else {
      const WideNode& node = bvh.nodes[cur];
      alignas(32) float t_near[kNodeWidth];
      std::uint32_t bits = node_test1(d, node, nr, cull, t_near);
      if (bits != 0) {
        // As Embree's single-ray walk: one child hit (the common case) is entered without a push
        // or a sort, two are ordered by one comparison, more by insertion. Nearest hits visit the
        // nearest child now and push the others farthest first. Any-hit queries keep the node's
        // order: any blocker ends them, and skipping the sort made 16-ray shadow packets on the
        // 1M-triangle mesh about 3-8 % faster (neutral on the sphere field).
        const int i0 = std::countr_zero(bits);
        bits &= bits - 1;
        if (bits == 0) {
          cur = node.child[i0];
          continue;
        }
        const int i1 = std::countr_zero(bits);
        bits &= bits - 1;
        if (bits == 0) {
          if (!kAnyHit && t_near[i0] < t_near[i1]) {
            push(node.child[i1], t_near[i1]);
            cur = node.child[i0];
          } else {
            push(node.child[i0], t_near[i0]);
            cur = node.child[i1];
          }
          continue;
        }
        Entry hit[kNodeWidth];
        int n = 0;
        bits |= 1u << i0 | 1u << i1;
        while (bits != 0) {
          const int i = std::countr_zero(bits);
          bits &= bits - 1;
          Entry e{node.child[i], t_near[i]};
          int j = n++;
          while (!kAnyHit && j > 0 && hit[j - 1].t_near < e.t_near) {
            hit[j] = hit[j - 1];
            --j;
          }
          hit[j] = e;
        }
        for (int i = 0; i < n - 1; ++i) push(hit[i].ref, hit[i].t_near);
        cur = hit[n - 1].ref;
        continue;
      }
    }
    // Pop, skipping entries a nearer hit found since has ruled out.
    while (true) {
      if (sp == 0) return improved;
      --sp;
      if (kAnyHit || stack_t[sp] <= cull) {
        cur = stack_ref[sp];
        break;
      }
    }
  }
}

// The triangle of a slot, as its Shape holds it (the blocks keep the vertices bit for bit).
inline TriangleShape slot_triangle(const WideBvh& bvh, std::uint32_t slot) {
  const TriangleBlock& b = bvh.triangles[slot / std::uint32_t(kWidth)];
  const std::uint32_t lane = slot % std::uint32_t(kWidth);
  TriangleShape tri;
  Vec3f* v[3] = {&tri.v0, &tri.v1, &tri.v2};
  for (int vert = 0; vert < 3; ++vert) *v[vert] = Vec3f{b.v[vert][0][lane], b.v[vert][1][lane], b.v[vert][2][lane]};
  return tri;
}

bool Intersect1(const WideBvh& bvh, const RayPre& r, float t_min, float& best_t, std::uint32_t& best_id, Hit& hit,
                bool& finished) {
  const Single s = make_single(r, t_min);
  TriangleUvw uvw{};
  std::uint32_t slot = kNoSlot;
  const bool improved = traverse1<false>(bvh, s, 0, best_t, best_id, &uvw, &slot);
  finished = improved && slot != kNoSlot;
  if (finished) finish_triangle_hit(slot_triangle(bvh, slot), best_id, best_t, uvw, hit);
  return improved;
}

bool Occluded1(const WideBvh& bvh, const RayPre& r, float t_min, float t_max) {
  const Single s = make_single(r, t_min);
  std::uint32_t unused = 0;
  return traverse1<true>(bvh, s, 0, t_max, unused, nullptr, nullptr);
}

// ---------------------------------------------------------------------------------------------
// Packets of 8 rays.

template <int kP>
struct alignas(64) Packet {
  float o[3][kP];
  float d[3][kP];
  float inv[3][kP];
  float negf[3][kP];  // 1 where the direction's sign bit is set, else 0
  float t_min[kP];
  float cull[kP];  // best_t * kFarScale (nearest) or t_max * kFarScale (any-hit)
  float best[kP];  // nearest t so far (nearest) or t_max (any-hit)
  std::uint32_t id[kP];
  double od[3][kP];  // origin and direction in double, for the sphere test
  double dd[3][kP];
  double a[kP];
  // Triangle shear per lane: the selection masks for kx, ky, kz (1 where the axis is 0 / 1).
  float kx0[kP], kx1[kP], ky0[kP], ky1[kP], kz0[kP], kz1[kP];
  float sx[kP], sy[kP], sz[kP];
  LaneUvw tri_uvw;  // edge functions of the latest triangle8 (nearest hits only)
  // Those of each lane's best, when it is a triangle: the float ones of a packet test in bu, bv, bw,
  // bdet (lanes of uvw_soa, set a vector at a time), others (double fallback, single rays) in
  // best_uvw.
  alignas(64) float bu[kP];
  alignas(64) float bv[kP];
  alignas(64) float bw[kP];
  alignas(64) float bdet[kP];
  std::uint32_t uvw_soa;
  TriangleUvw best_uvw[kP];
  // Lanes whose best is a triangle, lanes whose best is a sphere of a packet test, and the slot
  // of either (its block's index * kWidth + lane) per lane.
  std::uint32_t tri;
  std::uint32_t sph;
  alignas(64) std::uint32_t slot[kP];
  TriangleUvw best_of(int i) const {
    if (uvw_soa >> i & 1u) return {double(bu[i]), double(bv[i]), double(bw[i]), double(bdet[i])};
    return best_uvw[i];
  }
  bool uniform_signs;  // every lane has the direction signs sign[0..2]
  std::uint32_t sign[3];
  bool uniform_axes;  // every lane has the shear axes axis[0..2] (kx, ky, kz)
  std::uint32_t axis[3];
  bool uniform_origin;  // every lane has the origin of lane 0, bit for bit (pinhole camera packets)
  // The same rays as single rays (the fallback below kSwitch lanes, zero edge functions, boxes),
  // made on first use (most packets never need them) from the lanes' constants above, which have
  // the bits precompute() and make_single() give: no division again.
  mutable std::uint32_t ready;  // lanes of `single` made
  mutable Single single[kP];
  mutable RayPre single_pre[kP];  // what single[i] points at

  const Single& lane(int i) const {
    single[i].rp = &single_pre[i];  // (again on every call: a copy of the packet points at its own)
    if (!(ready >> i & 1u)) {
      Single& s = single[i];
      RayPre& r = single_pre[i];
      for (std::uint32_t a = 0; a < 3; ++a) {
        r.o[a] = o[a][i];
        r.d[a] = d[a][i];
        r.inv_d[a] = inv[a][i];
        r.neg[a] = negf[a][i] != 0.0f ? 1u : 0u;
        r.near_idx[a] = r.neg[a] ? 3 + a : a;
        r.far_idx[a] = r.neg[a] ? a : 3 + a;
      }
      r.kx = kx0[i] != 0.0f ? 0u : kx1[i] != 0.0f ? 1u : 2u;
      r.ky = ky0[i] != 0.0f ? 0u : ky1[i] != 0.0f ? 1u : 2u;
      r.kz = kz0[i] != 0.0f ? 0u : kz1[i] != 0.0f ? 1u : 2u;
      r.sx = sx[i];
      r.sy = sy[i];
      r.sz = sz[i];
      s.t_min = t_min[i];
      const double dx = r.d[0], dy = r.d[1], dz = r.d[2];
      s.a = dx * dx + dy * dy + dz * dz;
      ready |= 1u << i;
    }
    return single[i];
  }
};

// Fields 0-7 of the rays rays[0 .. n) (o.x, o.y, o.z, d.x, d.y, d.z, t_min, t_max), n the lanes of
// d, as vectors of n lanes. Loaded whole and transposed in registers (each ray as four pairs of
// floats, deinterleaved as 64-bit values, then split into even and odd floats): written lane by
// lane into the packet and read back as vectors, every such read failed its store forward.
static_assert(sizeof(math::Ray) == 8 * sizeof(float) && offsetof(math::Ray, o) == 0 &&
              offsetof(math::Ray, d) == 3 * sizeof(float) && offsetof(math::Ray, t_min) == 6 * sizeof(float) &&
              offsetof(math::Ray, t_max) == 7 * sizeof(float));
template <class D>
HWY_INLINE void load_rays(D d, const math::Ray* rays, hn::Vec<D> (&f)[8]) {
#if HWY_TARGET == HWY_SCALAR
  // One lane: the fields themselves.
  const float* r = &rays[0].o.x;
  for (int k = 0; k < 8; ++k) f[k] = hn::Set(d, r[k]);
#else
  const hn::Repartition<std::uint64_t, D> d64;
  const std::size_t half = hn::Lanes(d64);  // rays per LoadInterleaved4
  hn::Vec<decltype(d64)> lo[4], hi[4];      // lo[k]: pair k (fields 2k, 2k + 1) of the first half's rays
  const auto* w = reinterpret_cast<const std::uint64_t*>(rays);
  hn::LoadInterleaved4(d64, w, lo[0], lo[1], lo[2], lo[3]);
  hn::LoadInterleaved4(d64, w + 4 * half, hi[0], hi[1], hi[2], hi[3]);
  for (int k = 0; k < 4; ++k) {
    f[2 * k] = hn::ConcatEven(d, hn::BitCast(d, hi[k]), hn::BitCast(d, lo[k]));
    f[2 * k + 1] = hn::ConcatOdd(d, hn::BitCast(d, hi[k]), hn::BitCast(d, lo[k]));
  }
#endif
}

// The packet's per-lane constants, computed a vector of lanes at a time with the very operations
// precompute() and set_shear() do per ray (1 / d, the sign bits, the shear axes chosen by the
// same comparisons, d[kx] / d[kz], d[ky] / d[kz], 1 / d[kz]), so every lane has the bits of the
// single-ray constants. Reads all kP rays (the packet's array), live or not.
template <int kP>
inline void make_packet(const WideBvh& bvh, const math::Ray* rays, std::uint32_t live, Packet<kP>& p, bool any_hit) {
  p.ready = 0;

  const hn::CappedTag<float, kP> d;
  const hn::RebindToSigned<decltype(d)> di;
  const hn::RebindToUnsigned<decltype(d)> du;
  const std::size_t n = hn::Lanes(d);
  const auto one = hn::Set(d, 1.0f), zero = hn::Zero(d);
  // Dead lanes get a harmless ray (the first live one) so no lane computes on garbage; their
  // results are masked off.
  const math::Ray& first = rays[std::countr_zero(live)];
  const float first_fields[8] = {first.o.x, first.o.y, first.o.z,   first.d.x,
                                 first.d.y, first.d.z, first.t_min, first.t_max};
  std::uint32_t neg_bits[3] = {0, 0, 0};
  std::uint32_t axis_bits[6] = {0, 0, 0, 0, 0, 0};  // kx0, kx1, ky0, ky1, kz0, kz1
  bool same_origin = true;
  const hn::Vec<decltype(du)> o0[3] = {hn::Set(du, std::bit_cast<std::uint32_t>(first_fields[0])),
                                       hn::Set(du, std::bit_cast<std::uint32_t>(first_fields[1])),
                                       hn::Set(du, std::bit_cast<std::uint32_t>(first_fields[2]))};
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    hn::Vec<decltype(d)> f[8];
    load_rays(d, rays + i, f);
    const std::uint32_t lanes = n >= 32 ? ~0u : (1u << n) - 1u;
    if ((live >> i & lanes) != lanes) {
      // LoadMaskBits may read 8 bytes: the bits sit in the first two, the rest are zero.
      const std::uint8_t live_bytes[8] = {std::uint8_t(live >> i), std::uint8_t(live >> (i + 8))};
      const auto keep = hn::LoadMaskBits(d, live_bytes);
      for (int k = 0; k < 8; ++k) f[k] = hn::IfThenElse(keep, f[k], hn::Set(d, first_fields[k]));
    }
    hn::Vec<decltype(d)> dv[3];
    for (int a = 0; a < 3; ++a) {
      hn::StoreU(f[a], d, p.o[a] + i);
      same_origin = same_origin && hn::AllTrue(du, hn::Eq(hn::BitCast(du, f[a]), o0[a]));
      dv[a] = f[3 + a];
      hn::StoreU(dv[a], d, p.d[a] + i);
      hn::StoreU(hn::Div(one, dv[a]), d, p.inv[a] + i);
      const auto neg = hn::RebindMask(d, hn::Lt(hn::BitCast(di, dv[a]), hn::Zero(di)));
      hn::StoreU(hn::IfThenElseZero(neg, one), d, p.negf[a] + i);
      std::uint8_t mb[8] = {};
      hn::StoreMaskBits(d, neg, mb);
      neg_bits[a] |= low_bits(mb, n) << i;
    }
    hn::StoreU(f[6], d, p.t_min + i);
    if (any_hit) {
      hn::StoreU(f[7], d, p.best + i);
      hn::StoreU(hn::Mul(f[7], hn::Set(d, kFarScale)), d, p.cull + i);
    }
    // set_shear: kz = ax > ay ? (ax > az ? 0 : 2) : (ay > az ? 1 : 2); kx, ky the next two axes,
    // swapped when d[kz] < 0.
    const auto ax = hn::Abs(dv[0]), ay = hn::Abs(dv[1]), az = hn::Abs(dv[2]);
    const auto x_gt_y = hn::Gt(ax, ay);
    const auto kz0 = hn::And(x_gt_y, hn::Gt(ax, az));
    const auto kz1 = hn::AndNot(x_gt_y, hn::Gt(ay, az));
    const auto kz2 = hn::Not(hn::Or(kz0, kz1));
    const auto dkz = hn::IfThenElse(kz0, dv[0], hn::IfThenElse(kz1, dv[1], dv[2]));
    const auto flip = hn::Lt(dkz, zero);
    // Unswapped: kz 0 -> (kx, ky) = (1, 2); kz 1 -> (2, 0); kz 2 -> (0, 1).
    const auto kx0 = hn::Or(hn::AndNot(flip, kz2), hn::And(flip, kz1));
    const auto kx1 = hn::Or(hn::AndNot(flip, kz0), hn::And(flip, kz2));
    const auto ky0 = hn::Or(hn::AndNot(flip, kz1), hn::And(flip, kz2));
    const auto ky1 = hn::Or(hn::AndNot(flip, kz2), hn::And(flip, kz0));
    const auto dkx = hn::IfThenElse(kx0, dv[0], hn::IfThenElse(kx1, dv[1], dv[2]));
    const auto dky = hn::IfThenElse(ky0, dv[0], hn::IfThenElse(ky1, dv[1], dv[2]));
    hn::StoreU(hn::Div(dkx, dkz), d, p.sx + i);
    hn::StoreU(hn::Div(dky, dkz), d, p.sy + i);
    hn::StoreU(hn::Div(one, dkz), d, p.sz + i);
    hn::StoreU(hn::IfThenElseZero(kx0, one), d, p.kx0 + i);
    hn::StoreU(hn::IfThenElseZero(kx1, one), d, p.kx1 + i);
    hn::StoreU(hn::IfThenElseZero(ky0, one), d, p.ky0 + i);
    hn::StoreU(hn::IfThenElseZero(ky1, one), d, p.ky1 + i);
    hn::StoreU(hn::IfThenElseZero(kz0, one), d, p.kz0 + i);
    hn::StoreU(hn::IfThenElseZero(kz1, one), d, p.kz1 + i);
    const hn::Mask<decltype(d)> axis_masks[6] = {kx0, kx1, ky0, ky1, kz0, kz1};
    for (int k = 0; k < 6; ++k) {
      std::uint8_t mb[8] = {};
      hn::StoreMaskBits(d, axis_masks[k], mb);
      axis_bits[k] |= low_bits(mb, n) << i;
    }
  }
  // The sphere test's double copies and a = |d|^2, as make_single computes it (only sphere_apply
  // reads them: a tree without spheres skips them).
  const hn::CappedTag<double, kP> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const std::size_t nd = hn::Lanes(dd);
  for (std::size_t i = 0; i < (bvh.spheres.empty() ? 0 : std::size_t(kP)); i += nd) {
    hn::Vec<decltype(dd)> dv[3];
    for (int a = 0; a < 3; ++a) {
      dv[a] = hn::PromoteTo(dd, hn::LoadU(df, p.d[a] + i));
      hn::StoreU(dv[a], dd, p.dd[a] + i);
      hn::StoreU(hn::PromoteTo(dd, hn::LoadU(df, p.o[a] + i)), dd, p.od[a] + i);
    }
    hn::StoreU(hn::Add(hn::Add(hn::Mul(dv[0], dv[0]), hn::Mul(dv[1], dv[1])), hn::Mul(dv[2], dv[2])), dd, p.a + i);
  }
  constexpr std::uint32_t kAll = (1u << kP) - 1u;
  p.uniform_signs = true;
  for (int a = 0; a < 3; ++a) {
    p.sign[a] = neg_bits[a] & 1u;
    p.uniform_signs = p.uniform_signs && (neg_bits[a] == 0 || neg_bits[a] == kAll);
  }
  p.uniform_axes = true;
  for (int k = 0; k < 3; ++k) {
    const std::uint32_t is0 = axis_bits[2 * k], is1 = axis_bits[2 * k + 1];
    p.uniform_axes = p.uniform_axes && (is0 == 0 || is0 == kAll) && (is1 == 0 || is1 == kAll);
    p.axis[k] = (is0 & 1u) ? 0u : (is1 & 1u) ? 1u : 2u;
  }
  p.uniform_origin = same_origin;
}

// Which of the 8 lanes in `mask` enter each child box of the node (bits[c]) and each such lane's
// entry distance (dist[c][lane]; other lanes' entries are left unspecified). No branch depends on
// the outcome of a child's test. The packet's origins, inverse directions and direction signs are
// loaded once per node, not once per child; when every lane has the same direction signs (camera
// and shadow packets nearly always do), the near and far planes are picked per axis like a single
// ray's instead of lane by lane, and when the lanes also share their origin (pinhole camera
// packets), the plane-minus-origin differences of all 8 children are one vector subtraction per
// plane (the same single rounding each lane would do).
template <int kP>
inline void node_test8(const WideNode& node, const Packet<kP>& p, std::uint32_t mask, std::uint32_t* bits,
                       float (*dist)[kP]) {
  const hn::CappedTag<float, kP> d;
  using V = hn::Vec<decltype(d)>;
  const std::size_t n = hn::Lanes(d);
  const auto inf = hn::Set(d, kInfF);
  const auto scale = hn::Set(d, kFarScale);
  const auto zero = hn::Zero(d);
  for (int c = 0; c < kNodeWidth; ++c) bits[c] = 0;
  // Uniform signs and origin: rel[0][a][c] = near plane - o, rel[1][a][c] = far plane - o.
  alignas(64) float rel[2][3][kNodeWidth];
  const bool shared = p.uniform_signs && p.uniform_origin;
  if (shared) {
    const hn::CappedTag<float, kNodeWidth> d8;
    for (std::size_t i = 0; i < std::size_t(kNodeWidth); i += hn::Lanes(d8)) {
      for (int a = 0; a < 3; ++a) {
        const auto o = hn::Set(d8, p.o[a][0]);
        const float* nb = p.sign[a] ? node.hi[a] : node.lo[a];
        const float* fb = p.sign[a] ? node.lo[a] : node.hi[a];
        hn::Store(hn::Sub(hn::LoadU(d8, nb + i), o), d8, rel[0][a] + i);
        hn::Store(hn::Sub(hn::LoadU(d8, fb + i), o), d8, rel[1][a] + i);
      }
    }
  }
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    V o[3], inv[3];
    for (int a = 0; a < 3; ++a) {
      o[a] = hn::LoadU(d, p.o[a] + i);
      inv[a] = hn::LoadU(d, p.inv[a] + i);
    }
    const auto tmin = hn::LoadU(d, p.t_min + i);
    // LoadMaskBits may read 8 bytes: the bits sit in the first two, the rest are zero.
    const std::uint8_t mask_bytes[8] = {std::uint8_t(mask >> i), std::uint8_t(mask >> (i + 8))};
    const auto active = hn::LoadMaskBits(d, mask_bytes);
    const auto cull = hn::LoadU(d, p.cull + i);
    for (int c = 0; c < kNodeWidth; ++c) {
      if (node.child[c] == kEmptyChild) break;  // empty slots come last
      auto t0 = tmin;
      auto tf = inf;
      if (shared) {
        for (int a = 0; a < 3; ++a) {
          t0 = hn::Max(hn::Mul(hn::Set(d, rel[0][a][c]), inv[a]), t0);  // NaN skipped, see node_test1
          tf = hn::Min(hn::Mul(hn::Set(d, rel[1][a][c]), inv[a]), tf);
        }
      } else if (p.uniform_signs) {
        for (int a = 0; a < 3; ++a) {
          const float nb = p.sign[a] ? node.hi[a][c] : node.lo[a][c];
          const float fb = p.sign[a] ? node.lo[a][c] : node.hi[a][c];
          t0 = hn::Max(hn::Mul(hn::Sub(hn::Set(d, nb), o[a]), inv[a]), t0);  // NaN skipped, see node_test1
          tf = hn::Min(hn::Mul(hn::Sub(hn::Set(d, fb), o[a]), inv[a]), tf);
        }
      } else {
        for (int a = 0; a < 3; ++a) {
          const auto tlo = hn::Mul(hn::Sub(hn::Set(d, node.lo[a][c]), o[a]), inv[a]);
          const auto thi = hn::Mul(hn::Sub(hn::Set(d, node.hi[a][c]), o[a]), inv[a]);
          const auto neg = hn::Gt(hn::LoadU(d, p.negf[a] + i), zero);
          t0 = hn::Max(hn::IfThenElse(neg, thi, tlo), t0);
          tf = hn::Min(hn::IfThenElse(neg, tlo, thi), tf);
        }
      }
      const auto m = hn::And(active, hn::Le(t0, hn::Min(hn::Mul(tf, scale), cull)));
      hn::StoreU(t0, d, dist[c] + i);  // read only for the lanes of bits[c]
      std::uint8_t mb[8] = {};
      hn::StoreMaskBits(d, m, mb);
      bits[c] |= low_bits(mb, n) << i;
    }
  }
}

// Applies candidate distances t[lane] of prim `id` to the lanes in `mask`; returns the lanes
// that improved (nearest) or that are now blocked (any-hit). `uvw`: the candidate is a triangle
// with these edge functions, kept for the lanes it becomes the best of.
template <int kP, bool kAnyHit>
inline std::uint32_t apply8(Packet<kP>& p, const float* t, std::uint32_t id, std::uint32_t mask,
                            const LaneUvw* uvw = nullptr, std::uint32_t slot = kNoSlot) {
  // Which lanes have t < best or t == best (a NaN t, a miss, is neither), a vector at a time;
  // most candidates miss every lane, and then nothing else is done.
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  std::uint32_t lt = 0, eq = 0;
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const auto tv = hn::LoadU(d, t + i), best = hn::LoadU(d, p.best + i);
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, hn::Lt(tv, best), mb);
    lt |= low_bits(mb, n) << i;
    if (!kAnyHit) {
      hn::StoreMaskBits(d, hn::Eq(tv, best), mb);
      eq |= low_bits(mb, n) << i;
    }
  }
  if (kAnyHit) return lt & mask;
  if (((lt | eq) & mask) == 0) return 0;
  // better(): t < best, or t == best and id < best id, a vector at a time (ids compared as signed
  // after flipping the top bit: the unsigned order).
  const hn::RebindToUnsigned<decltype(d)> du;
  const hn::RebindToSigned<decltype(d)> di;
  const auto top = hn::Set(du, 0x80000000u);
  const auto idv = hn::Set(du, id);
  const auto ids = hn::BitCast(di, hn::Xor(idv, top));
  std::uint32_t out = 0;
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const auto tv = hn::LoadU(d, t + i), best = hn::LoadU(d, p.best + i);
    const auto old_id = hn::LoadU(du, p.id + i);
    const auto id_lt = hn::RebindMask(d, hn::Lt(ids, hn::BitCast(di, hn::Xor(old_id, top))));
    const auto active = hn::RebindMask(d, hn::TestBit(hn::Set(du, mask), hn::Load(du, kLaneBit + i)));
    const auto win = hn::And(active, hn::Or(hn::Lt(tv, best), hn::And(hn::Eq(tv, best), id_lt)));
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, win, mb);
    const std::uint32_t bits = low_bits(mb, n);
    if (bits == 0) continue;
    out |= bits << i;
    hn::StoreU(hn::IfThenElse(win, tv, best), d, p.best + i);
    hn::StoreU(hn::IfThenElse(win, hn::Mul(tv, hn::Set(d, kFarScale)), hn::LoadU(d, p.cull + i)), d, p.cull + i);
    hn::StoreU(hn::IfThenElse(hn::RebindMask(du, win), idv, old_id), du, p.id + i);
    if (uvw != nullptr) {
      float* const dst[4] = {p.bu + i, p.bv + i, p.bw + i, p.bdet + i};
      const float* const src[4] = {uvw->u + i, uvw->v + i, uvw->w + i, uvw->det + i};
      for (int k = 0; k < 4; ++k)
        hn::StoreU(hn::IfThenElse(win, hn::LoadU(d, src[k]), hn::LoadU(d, dst[k])), d, dst[k]);
      hn::StoreU(hn::IfThenElse(hn::RebindMask(du, win), hn::Set(du, slot), hn::LoadU(du, p.slot + i)), du, p.slot + i);
    }
  }
  p.sph &= ~out;
  if (uvw == nullptr) {
    p.uvw_soa &= ~out;
    p.tri &= ~out;
    return out;
  }
  p.tri |= out;
  // The rare lanes whose edge functions came from the double fallback keep them in best_uvw.
  p.uvw_soa |= out & ~uvw->fallback;
  for (std::uint32_t m = out & uvw->fallback; m != 0; m &= m - 1) {
    const int i = std::countr_zero(m);
    p.best_uvw[i] = uvw->fb[i];
    p.uvw_soa &= ~(1u << i);
  }
  return out;
}

// One sphere against the packet's lanes in `mask`, in double exactly as sphere_t, with apply8's
// rule applied as each chunk of lanes (one double vector) is done: returns the lanes that
// improved (nearest) or that are blocked (any-hit). The candidate distances stay in registers: a
// double vector's roots demote to half a float vector, and storing them by halves for apply8 to
// load as one vector stalled every sphere test on a failed store forward (the hottest spot of
// 16-ray sphere packets on avx512). A pinhole packet's f = o - c is the same for every lane:
// computed once, with the same single rounding each lane would do.
template <int kP, bool kAnyHit>
HWY_INLINE std::uint32_t sphere_apply(Packet<kP>& p, float cx, float cy, float cz, float radius, std::uint32_t id,
                                      std::uint32_t mask, std::uint32_t slot) {
  const hn::CappedTag<double, kP> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const hn::RebindToUnsigned<decltype(df)> du;
  const hn::RebindToSigned<decltype(df)> di;
  const std::size_t n = hn::Lanes(dd);
  const auto rad = hn::Set(dd, double(radius));
  const auto rr = hn::Mul(rad, rad);
  const auto k = sphere_consts(dd, df);
  const bool shared = p.uniform_origin;
  const auto sfx = hn::Set(dd, double(p.o[0][0]) - double(cx));
  const auto sfy = hn::Set(dd, double(p.o[1][0]) - double(cy));
  const auto sfz = hn::Set(dd, double(p.o[2][0]) - double(cz));
  const auto maskv = hn::Set(du, mask);
  std::uint32_t out = 0;
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    auto fx = sfx, fy = sfy, fz = sfz;
    if (!shared) {
      fx = hn::Sub(hn::LoadU(dd, p.od[0] + i), hn::Set(dd, double(cx)));
      fy = hn::Sub(hn::LoadU(dd, p.od[1] + i), hn::Set(dd, double(cy)));
      fz = hn::Sub(hn::LoadU(dd, p.od[2] + i), hn::Set(dd, double(cz)));
    }
    const auto dx = hn::LoadU(dd, p.dd[0] + i), dy = hn::LoadU(dd, p.dd[1] + i), dz = hn::LoadU(dd, p.dd[2] + i);
    const auto a = hn::LoadU(dd, p.a + i);
    const auto disc = sphere_disc(fx, fy, fz, dx, dy, dz, a, rr);
    const auto ok = hn::Ge(disc, k.zero);
    if (hn::AllFalse(dd, ok)) continue;  // most sphere tests miss: skip the roots
    const auto tv = sphere_root(dd, df, k, ok, disc, fx, fy, fz, dx, dy, dz, a, rr, hn::LoadU(df, p.t_min + i));
    const auto best = hn::LoadU(df, p.best + i);
    const auto active = hn::RebindMask(df, hn::TestBit(maskv, hn::Load(du, kLaneBit + i)));
    auto win = hn::And(active, hn::Lt(tv, best));
    if (!kAnyHit) {
      // better(): t < best, or t == best and id < best id (compared as signed after flipping the
      // top bit: the unsigned order).
      const auto top = hn::Set(du, 0x80000000u);
      const auto idv = hn::Set(du, id);
      const auto old_id = hn::LoadU(du, p.id + i);
      const auto id_lt =
          hn::RebindMask(df, hn::Lt(hn::BitCast(di, hn::Xor(idv, top)), hn::BitCast(di, hn::Xor(old_id, top))));
      win = hn::Or(win, hn::And(active, hn::And(hn::Eq(tv, best), id_lt)));
      if (hn::AllFalse(df, win)) continue;
      hn::StoreU(hn::IfThenElse(win, tv, best), df, p.best + i);
      hn::StoreU(hn::IfThenElse(win, hn::Mul(tv, hn::Set(df, kFarScale)), hn::LoadU(df, p.cull + i)), df, p.cull + i);
      hn::StoreU(hn::IfThenElse(hn::RebindMask(du, win), idv, old_id), du, p.id + i);
      hn::StoreU(hn::IfThenElse(hn::RebindMask(du, win), hn::Set(du, slot), hn::LoadU(du, p.slot + i)), du, p.slot + i);
    }
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(df, win, mb);
    out |= low_bits(mb, n) << i;
  }
  if (!kAnyHit) {
    p.uvw_soa &= ~out;
    p.tri &= ~out;
    p.sph |= out;
  }
  return out;
}

// The any-hit form of triangle_lanes followed by apply8 for the packet's lanes i .. i + n (n the
// lanes of d) of `mask`: returns the bits (from lane i) of those whose t is below their best (the
// ray's t_max), with the same answers: the same edge test and all-outside exit over every lane,
// then t = tt / det, and a lane is blocked where t_min < t < best (t < inf follows), det != 0 and
// t exceeds the error bound. The bound (a second division) is skipped when no lane inside the
// triangle has t in (t_min, best): it could only turn a candidate into a miss. Lanes with a zero
// edge function are redone with triangle_t_double, as triangle8 does. c: sax, say, sbx, sby, scx,
// scy, az, bz, cz. Against triangle8 and apply8 (1M-triangle mesh, dtraced-bench-rays, avx512,
// 1 thread, the binaries alternated, 5 pairs, medians of per-pair ratios, load 4-5): shadow
// packets of 16 rays 1.057x (every pair above 1), of 8 rays 1.027x; against rtcOccluded16 in the
// same runs 0.891 -> 0.928. The sphere field's shadow packets 1.034x (16) and 1.012x (8).
template <class D, int kP>
HWY_INLINE std::uint32_t blocked_lanes(D d, const Packet<kP>& p, std::size_t i, std::uint32_t mask,
                                       const hn::Vec<D> (&c)[9], hn::Vec<D> sz) {
  const hn::RebindToUnsigned<D> du;
  const std::size_t n = hn::Lanes(d);
  const auto zero = hn::Zero(d);
  const auto sax = c[0], say = c[1], sbx = c[2], sby = c[3], scx = c[4], scy = c[5];
  const auto [u, v, w, neg, pos, zero_edge] = edge_functions(zero, sax, say, sbx, sby, scx, scy);
  const auto outside = hn::Or(hn::And(neg, pos), zero_edge);
  if (hn::AllTrue(d, hn::AndNot(zero_edge, hn::And(neg, pos)))) return 0;  // triangle_lanes' exit
  const auto active = hn::RebindMask(d, hn::TestBit(hn::Set(du, mask), hn::Load(du, kLaneBit + i)));
  const auto best = hn::LoadU(d, p.best + i);
  std::uint32_t out = 0;
  const auto in = hn::AndNot(outside, active);
  if (!hn::AllFalse(d, in)) {
    const auto det = hn::Add(hn::Add(u, v), w);
    const auto saz = hn::Mul(sz, c[6]), sbz = hn::Mul(sz, c[7]), scz = hn::Mul(sz, c[8]);
    const auto tt = hn::Add(hn::Add(hn::Mul(u, saz), hn::Mul(v, sbz)), hn::Mul(w, scz));
    const auto tv = hn::Div(tt, det);
    const auto cand = hn::And(in, hn::And(hn::Gt(tv, hn::LoadU(d, p.t_min + i)), hn::Lt(tv, best)));
    if (!hn::AllFalse(d, cand)) {
      const auto err = triangle_t_error8(d, sax, say, sbx, sby, scx, scy, saz, sbz, scz, u, v, w, det);
      const auto hit = hn::And(cand, hn::And(hn::Ne(det, zero), hn::Gt(tv, err)));
      std::uint8_t mb[8] = {};
      hn::StoreMaskBits(d, hit, mb);
      out = low_bits(mb, n);
    }
  }
  const auto redo = hn::And(zero_edge, active);
  if (!hn::AllFalse(d, redo)) {
    alignas(64) float t[kMaxPacket];
    redo_zero_edges(
        d, redo, c, t, [&p, i](std::size_t k) -> const Single& { return p.lane(int(i + k)); }, nullptr, i);
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, redo, mb);
    for (std::uint32_t m = low_bits(mb, n); m != 0; m &= m - 1) {
      const int k = std::countr_zero(m);
      if (t[k] < p.best[i + std::size_t(k)]) out |= 1u << k;
    }
  }
  return out;
}

// One triangle (vertices v[vertex][axis]) against the 8 rays, exactly as triangle_t; each lane
// picks its own shear axes. With `uvw`, the lanes' edge functions too. Forced inline: GCC left it
// out of leaf8, whose candidate distances and edge functions then went through memory (16-ray
// mesh camera packets 1.10x, shadow 1.04x inlined). kMasked: returns whether some lane of `mask`
// went past the edge test (else every t is NaN and the caller skips apply8); only those lanes (those
// that entered the leaf) decide the early exit after the edge test; a lane left out of the leaf (it
// missed the leaf's box or has a nearer hit) may lie inside a triangle of it, and then took the
// whole test, divisions and error bound, for nothing. A 16-ray mesh camera packet tests 8.9
// triangles, 2.9 of them a candidate hit for a lane of the mask, in 2.6 leaves of 7.9 lanes each
// (counted). Against all
// lanes (dtraced-bench-rays, avx512, 1 thread, the binaries alternated, medians of per-pair ratios,
// load 6-8): mesh camera x16 1.026x (6 pairs), sphere field camera x16 0.985x (10 pairs, both
// orders; its secondary rays, code unchanged, 0.99x in the same pairs). Any-hit queries keep all
// lanes (and return false): masked, mesh shadow x16 measured 0.98x (11 pairs); 0.2 tests a packet
// find a candidate hit. Unmasked, triangle_lanes keeps its all-lanes exit as written before the
// mask: through the masked form with an all-true mask, mesh shadow x16 measured 0.977x against the
// code before the mask (5 pairs, load 3), this form 1.028x (5 pairs, load 2-3).
//
// kBlocked (any-hit queries): instead of the distances, *blocked gets the lanes of `mask` the
// triangle blocks (blocked_lanes: t < best without t going through memory and apply8).
template <int kP, bool kMasked, bool kBlocked = false>
HWY_INLINE bool triangle8(const Packet<kP>& p, const float (&v)[3][3], std::uint32_t mask, float* t, LaneUvw* uvw,
                          std::uint32_t* blocked = nullptr) {
  const hn::CappedTag<float, kP> d;
  const hn::RebindToUnsigned<decltype(d)> du;
  const std::size_t n = hn::Lanes(d);
  const auto maskv = hn::Set(du, kMasked ? mask : ~0u);
  bool full = false;
  const auto zero = hn::Zero(d), inf = hn::Set(d, kInfF), nan = hn::Set(d, std::numeric_limits<float>::quiet_NaN());
  if (uvw != nullptr) uvw->fallback = 0;
  if (p.uniform_axes) {
    // Every lane shears along the same axes (nearly every camera and shadow packet): the
    // vertices' coordinates are picked once, not lane by lane.
    const std::uint32_t kx = p.axis[0], ky = p.axis[1], kz = p.axis[2];
    for (std::size_t i = 0; i < std::size_t(kP); i += n) {
      const auto ox = hn::LoadU(d, p.o[kx] + i), oy = hn::LoadU(d, p.o[ky] + i), oz = hn::LoadU(d, p.o[kz] + i);
      const auto sx = hn::LoadU(d, p.sx + i), sy = hn::LoadU(d, p.sy + i), sz = hn::LoadU(d, p.sz + i);
      const auto az = hn::Sub(hn::Set(d, v[0][kz]), oz), bz = hn::Sub(hn::Set(d, v[1][kz]), oz),
                 cz = hn::Sub(hn::Set(d, v[2][kz]), oz);
      const auto sax = hn::Sub(hn::Sub(hn::Set(d, v[0][kx]), ox), hn::Mul(sx, az));
      const auto say = hn::Sub(hn::Sub(hn::Set(d, v[0][ky]), oy), hn::Mul(sy, az));
      const auto sbx = hn::Sub(hn::Sub(hn::Set(d, v[1][kx]), ox), hn::Mul(sx, bz));
      const auto sby = hn::Sub(hn::Sub(hn::Set(d, v[1][ky]), oy), hn::Mul(sy, bz));
      const auto scx = hn::Sub(hn::Sub(hn::Set(d, v[2][kx]), ox), hn::Mul(sx, cz));
      const auto scy = hn::Sub(hn::Sub(hn::Set(d, v[2][ky]), oy), hn::Mul(sy, cz));
      if constexpr (kBlocked) {
        *blocked |= blocked_lanes(d, p, i, mask, {sax, say, sbx, sby, scx, scy, az, bz, cz}, sz) << i;
        continue;
      }
      const auto active =
          kMasked ? hn::RebindMask(d, hn::TestBit(maskv, hn::Load(du, kLaneBit + i))) : hn::Eq(zero, zero);
      const auto zero_edge =
          triangle_lanes<kMasked>(d, zero, inf, nan, sax, say, sbx, sby, scx, scy, az, bz, cz, sz,
                                  hn::LoadU(d, p.t_min + i), active, t + i, uvw, i, kMasked ? &full : nullptr);
      redo_zero_edges(
          d, zero_edge, {sax, say, sbx, sby, scx, scy, az, bz, cz}, t + i,
          [&p, i](std::size_t k) -> const Single& { return p.lane(int(i + k)); }, uvw, i);
    }
    return full;
  }
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const auto kx0 = hn::Gt(hn::LoadU(d, p.kx0 + i), zero), kx1 = hn::Gt(hn::LoadU(d, p.kx1 + i), zero);
    const auto ky0 = hn::Gt(hn::LoadU(d, p.ky0 + i), zero), ky1 = hn::Gt(hn::LoadU(d, p.ky1 + i), zero);
    const auto kz0 = hn::Gt(hn::LoadU(d, p.kz0 + i), zero), kz1 = hn::Gt(hn::LoadU(d, p.kz1 + i), zero);
    const auto o0 = hn::LoadU(d, p.o[0] + i), o1 = hn::LoadU(d, p.o[1] + i), o2 = hn::LoadU(d, p.o[2] + i);
    auto pick = [&](const auto& m0, const auto& m1, const auto& x, const auto& y, const auto& z) {
      return hn::IfThenElse(m0, x, hn::IfThenElse(m1, y, z));
    };
    // Vertex k relative to the origin, permuted per lane to (kx, ky, kz).
    hn::Vec<decltype(d)> rel[3][3];
    for (int k = 0; k < 3; ++k) {
      const auto x = hn::Sub(hn::Set(d, v[k][0]), o0);
      const auto y = hn::Sub(hn::Set(d, v[k][1]), o1);
      const auto z = hn::Sub(hn::Set(d, v[k][2]), o2);
      rel[k][0] = pick(kx0, kx1, x, y, z);
      rel[k][1] = pick(ky0, ky1, x, y, z);
      rel[k][2] = pick(kz0, kz1, x, y, z);
    }
    const auto sx = hn::LoadU(d, p.sx + i), sy = hn::LoadU(d, p.sy + i), sz = hn::LoadU(d, p.sz + i);
    const auto sax = hn::Sub(rel[0][0], hn::Mul(sx, rel[0][2])), say = hn::Sub(rel[0][1], hn::Mul(sy, rel[0][2]));
    const auto sbx = hn::Sub(rel[1][0], hn::Mul(sx, rel[1][2])), sby = hn::Sub(rel[1][1], hn::Mul(sy, rel[1][2]));
    const auto scx = hn::Sub(rel[2][0], hn::Mul(sx, rel[2][2])), scy = hn::Sub(rel[2][1], hn::Mul(sy, rel[2][2]));
    if constexpr (kBlocked) {
      *blocked |= blocked_lanes(d, p, i, mask, {sax, say, sbx, sby, scx, scy, rel[0][2], rel[1][2], rel[2][2]}, sz)
                  << i;
      continue;
    }
    const auto active =
        kMasked ? hn::RebindMask(d, hn::TestBit(maskv, hn::Load(du, kLaneBit + i))) : hn::Eq(zero, zero);
    const auto zero_edge =
        triangle_lanes<kMasked>(d, zero, inf, nan, sax, say, sbx, sby, scx, scy, rel[0][2], rel[1][2], rel[2][2], sz,
                                hn::LoadU(d, p.t_min + i), active, t + i, uvw, i, kMasked ? &full : nullptr);
    redo_zero_edges(
        d, zero_edge, {sax, say, sbx, sby, scx, scy, rel[0][2], rel[1][2], rel[2][2]}, t + i,
        [&p, i](std::size_t k) -> const Single& { return p.lane(int(i + k)); }, uvw, i);
  }
  return full;
}

// One box shape b = [lo, hi] against the 8 rays, exactly as box_t: the slab distances, the near
// and far planes picked by each lane's direction sign, Max / Min in the order and with the NaN
// rule of slab_span's comparisons (maxps / minps return their second operand when one is NaN, so
// a NaN slab never constrains), then box_t's choice between the near and the far distance.
template <int kP>
inline void box8(const Packet<kP>& p, const float* b, float* t) {
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  const auto zero = hn::Zero(d), inf = hn::Set(d, kInfF), nan = hn::Set(d, std::numeric_limits<float>::quiet_NaN());
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    auto t_near = hn::Set(d, -kInfF), t_far = inf;
    for (int a = 0; a < 3; ++a) {
      const auto o = hn::LoadU(d, p.o[a] + i), inv = hn::LoadU(d, p.inv[a] + i);
      const auto tlo = hn::Mul(hn::Sub(hn::Set(d, b[a]), o), inv);
      const auto thi = hn::Mul(hn::Sub(hn::Set(d, b[3 + a]), o), inv);
      const auto neg = hn::Gt(hn::LoadU(d, p.negf[a] + i), zero);
      t_near = hn::Max(hn::IfThenElse(neg, thi, tlo), t_near);
      t_far = hn::Min(hn::IfThenElse(neg, tlo, thi), t_far);
    }
    const auto tmin = hn::LoadU(d, p.t_min + i);
    const auto crosses = hn::Le(t_near, hn::Mul(t_far, hn::Set(d, kFarScale)));
    const auto use_far = hn::And(hn::Gt(t_far, tmin), hn::Lt(t_far, inf));
    const auto tv = hn::IfThenElse(hn::Gt(t_near, tmin), t_near, hn::IfThenElse(use_far, t_far, nan));
    hn::StoreU(hn::IfThenElse(crosses, tv, nan), d, t + i);
  }
}

// Tests a leaf against the lanes in `mask`. Returns the lanes that improved (nearest) or that are
// blocked (any-hit).
template <int kP, bool kAnyHit>
inline std::uint32_t leaf8(const WideBvh& bvh, const WideLeaf& leaf, Packet<kP>& p, std::uint32_t mask) {
  std::uint32_t out = 0;
  alignas(64) float t[kP];
  for (std::uint32_t k = 0; k < leaf.sphere_blocks; ++k) {
    const SphereBlock& b = bvh.spheres[leaf.sphere_begin + k];
    for (int j = 0; j < kWidth && mask != 0; ++j) {
      if (b.id[j] == kEmptyChild) break;
      const std::uint32_t hit =
          sphere_apply<kP, kAnyHit>(p, b.cx[j], b.cy[j], b.cz[j], b.r[j], b.id[j], mask,
                                    (leaf.sphere_begin + k) * std::uint32_t(kWidth) + std::uint32_t(j));
      out |= hit;
      if (kAnyHit) mask &= ~hit;
    }
  }
  for (std::uint32_t k = 0; k < leaf.triangle_blocks; ++k) {
    const TriangleBlock& b = bvh.triangles[leaf.triangle_begin + k];
    for (int j = 0; j < kWidth && mask != 0; ++j) {
      if (b.id[j] == kEmptyChild) break;
      const float v[3][3] = {{b.v[0][0][j], b.v[0][1][j], b.v[0][2][j]},
                             {b.v[1][0][j], b.v[1][1][j], b.v[1][2][j]},
                             {b.v[2][0][j], b.v[2][1][j], b.v[2][2][j]}};
      if constexpr (kAnyHit) {
        std::uint32_t hit = 0;
        triangle8<kP, false, true>(p, v, mask, t, nullptr, &hit);
        out |= hit;
        mask &= ~hit;
        continue;
      }
      if (!triangle8<kP, !kAnyHit>(p, v, mask, t, kAnyHit ? nullptr : &p.tri_uvw) && !kAnyHit) continue;
      const std::uint32_t hit =
          apply8<kP, kAnyHit>(p, t, b.id[j], mask, kAnyHit ? nullptr : &p.tri_uvw,
                              (leaf.triangle_begin + k) * std::uint32_t(kWidth) + std::uint32_t(j));
      out |= hit;
      if (kAnyHit) mask &= ~hit;
    }
  }
  for (std::uint32_t k = 0; k < leaf.box_count && mask != 0; ++k) {
    const BoxPrim& bp = bvh.boxes[leaf.box_begin + k];
    box8(p, bp.b, t);
    const std::uint32_t hit = apply8<kP, kAnyHit>(p, t, bp.id, mask);
    out |= hit;
    if (kAnyHit) mask &= ~hit;
  }
  return out;
}

struct Entry8 {
  std::uint32_t ref;
  std::uint32_t mask;
  float key;  // ordering key: the entry distance of the entry's first lane
  int child;  // slot in the node (while ordering)
};

// Bits of the lanes i with a[i] <= b[i].
template <int kP>
inline std::uint32_t lanes_le(const float* a, const float* b) {
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  std::uint32_t bits = 0;
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, hn::Le(hn::LoadU(d, a + i), hn::LoadU(d, b + i)), mb);
    bits |= low_bits(mb, n) << i;
  }
  return bits;
}

// Finishes the subtree `node` for the lanes of `mask` one ray at a time (a packet with few live
// lanes left): a lane whose ray improves (nearest) or is blocked (any-hit) joins `result`; any-hit
// lanes blocked leave `alive`.
template <int kP, bool kAnyHit>
inline void finish_singles(const WideBvh& bvh, Packet<kP>& p, std::uint32_t node, std::uint32_t mask,
                           std::uint32_t& result, std::uint32_t& alive) {
  for (std::uint32_t m = mask; m != 0; m &= m - 1) {
    const int i = std::countr_zero(m);
    if (traverse1<kAnyHit>(bvh, p.lane(i), node, p.best[i], p.id[i], kAnyHit ? nullptr : &p.best_uvw[i],
                           kAnyHit ? nullptr : &p.slot[i])) {
      result |= 1u << i;
      if (kAnyHit) {
        alive &= ~(1u << i);
      } else {
        p.cull[i] = p.best[i] * kFarScale;
        p.uvw_soa &= ~(1u << i);
        p.tri = (p.tri & ~(1u << i)) | (p.slot[i] != kNoSlot ? 1u << i : 0u);
        p.sph &= ~(1u << i);
      }
    }
  }
}

// Packet traversal. A stack entry keeps each of its lanes' entry distance (nearest hits only), so
// a pop drops exactly the lanes whose nearest hit found since is closer than their own entry
// into the box: what testing the box again against the tightened interval would drop.
template <int kP, bool kAnyHit>
std::uint32_t traverse8(const WideBvh& bvh, Packet<kP>& p, std::uint32_t live) {
  Entry8 stack[kStackSize];
  alignas(64) float stack_dist[kAnyHit ? 1 : kStackSize][kP];
  int sp = 0;
  std::uint32_t cur = 0;
  std::uint32_t mask = live;
  std::uint32_t result = 0;    // nearest: lanes that improved; any-hit: lanes blocked
  std::uint32_t alive = live;  // any-hit: lanes not yet blocked
  while (true) {
    if (std::popcount(mask) <= kSwitch) {
      // Few lanes left here: finish this subtree one ray at a time.
      finish_singles<kP, kAnyHit>(bvh, p, cur, mask, result, alive);
    } else if (cur & kLeafBit) {
      const std::uint32_t hit = leaf8<kP, kAnyHit>(bvh, leaf_of(bvh, cur), p, mask);
      result |= hit;
      if (kAnyHit) alive &= ~hit;
    } else {
      const WideNode& node = bvh.nodes[cur];
      Entry8 hit[kNodeWidth];
      int n = 0;
      std::uint32_t bits[kNodeWidth];
      alignas(64) float dist[kNodeWidth][kP];
      node_test8(node, p, mask, bits, dist);
      for (int c = 0; c < kNodeWidth; ++c) {
        if (bits[c] == 0) continue;
        Entry8 e{node.child[c], bits[c], dist[c][std::countr_zero(bits[c])], c};
        int j = n++;
        while (!kAnyHit && j > 0 && hit[j - 1].key < e.key) {
          hit[j] = hit[j - 1];
          --j;
        }
        hit[j] = e;
      }
      if (n > 0) {
        for (int i = 0; i < n - 1; ++i) {
          if (!kAnyHit) std::copy_n(dist[hit[i].child], kP, stack_dist[sp]);
          stack[sp++] = hit[i];
        }
        cur = hit[n - 1].ref;
        mask = hit[n - 1].mask;
        continue;
      }
    }
    if (kAnyHit && alive == 0) return result;
    // Pop; nearest hits drop the lanes whose hit since is closer than their entry into the box.
    while (true) {
      if (sp == 0) return result;
      --sp;
      std::uint32_t m = stack[sp].mask & alive;
      if (!kAnyHit) m &= lanes_le<kP>(stack_dist[sp], p.cull);
      if (m != 0) {
        cur = stack[sp].ref;
        mask = m;
        break;
      }
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Coherent traversal of a packet as a whole (Embree's scheme for coherent
// packets): a node's 8 boxes are first tested against the packet's frustum, bounds over all its
// lanes of the slab distances, in one vector; only the children it passes are tested lane by
// lane, giving each child its mask of lanes. Hit children are visited near first by the
// frustum's entry distance, and pushed as (child, lane mask, that distance): no per-lane distance
// stack. On a pop a lane is dropped when its nearest hit found since is closer than the entry's
// distance (a bound on every lane's own entry distance, so it never drops a lane the lane test
// would keep).
//
// The bounds are exact for every lane: rounding is monotone, so for a near plane b and an
// origin o in [o_lo, o_hi] the lane's rounded b - o lies in [fl(b - o_hi), fl(b - o_lo)], and
// its rounded product with 1 / d in [inv_lo, inv_hi] lies between the rounded corner products.
// Only packets whose lanes share the direction signs get here (the lanes' near plane is then the
// same box face), and an axis where some lane's direction is exactly zero (an infinite inverse:
// the lane's slab distance can be NaN, which the lane test skips) does not constrain the frustum.
struct Frustum {
  float o_lo[3], o_hi[3];
  float inv_lo[3], inv_hi[3];
  bool finite[3];  // inv_lo and inv_hi finite: the axis constrains the frustum
  float t_min;     // smallest t_min of the lanes
};

template <int kP>
inline Frustum make_frustum(const Packet<kP>& p) {
  // Over every lane: dead lanes hold a copy of a live one.
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  const auto lo_hi = [&](const float* v, float& lo, float& hi) {
    auto vlo = hn::LoadU(d, v), vhi = vlo;
    for (std::size_t i = n; i < std::size_t(kP); i += n) {
      vlo = hn::Min(vlo, hn::LoadU(d, v + i));
      vhi = hn::Max(vhi, hn::LoadU(d, v + i));
    }
    lo = hn::GetLane(hn::MinOfLanes(d, vlo));
    hi = hn::GetLane(hn::MaxOfLanes(d, vhi));
  };
  Frustum f;
  for (int a = 0; a < 3; ++a) {
    lo_hi(p.o[a], f.o_lo[a], f.o_hi[a]);
    lo_hi(p.inv[a], f.inv_lo[a], f.inv_hi[a]);
    f.finite[a] = std::abs(f.inv_lo[a]) < kInfF && std::abs(f.inv_hi[a]) < kInfF;
  }
  float unused = 0;
  lo_hi(p.t_min, f.t_min, unused);
  return f;
}

struct EntryC {
  std::uint32_t ref;
  std::uint32_t mask;
  float t_near;  // no lane of the mask enters the box before this
};

// The frustum test of a node's children: returns the children some lane may enter, with the
// frustum's entry distance of each in t_near[c]. `cull_hi` bounds the lanes' cull distances.
template <int kP>
inline std::uint32_t frustum_test(const WideNode& node, const Packet<kP>& p, const Frustum& f, float cull_hi,
                                  float* t_near) {
  const hn::CappedTag<float, kNodeWidth> d8;
  const std::size_t n8 = hn::Lanes(d8);
  const auto zero = hn::Zero(d8);
  std::uint32_t bits = 0;
  for (std::size_t i = 0; i < std::size_t(kNodeWidth); i += n8) {
    auto lo = hn::Set(d8, f.t_min);
    auto hi = hn::Set(d8, kInfF);
    for (int a = 0; a < 3; ++a) {
      if (!f.finite[a]) continue;
      const float* nb = p.sign[a] ? node.hi[a] : node.lo[a];
      const float* fb = p.sign[a] ? node.lo[a] : node.hi[a];
      const auto vn = hn::LoadU(d8, nb + i), vf = hn::LoadU(d8, fb + i);
      // Near: the smallest lane product. Rising in b - o when 1 / d > 0 (take the smallest
      // difference), falling when 1 / d < 0 (the largest); then the smallest product is with
      // inv_lo where that difference is >= 0, with inv_hi where it is negative.
      const auto rn = hn::Sub(vn, hn::Set(d8, p.sign[a] ? f.o_lo[a] : f.o_hi[a]));
      const auto rn_pos = hn::Ge(rn, zero);
      const auto tn = hn::Mul(rn, hn::IfThenElse(rn_pos, hn::Set(d8, f.inv_lo[a]), hn::Set(d8, f.inv_hi[a])));
      // Far: the largest lane product, mirror image.
      const auto rf = hn::Sub(vf, hn::Set(d8, p.sign[a] ? f.o_hi[a] : f.o_lo[a]));
      const auto rf_pos = hn::Ge(rf, zero);
      const auto tf = hn::Mul(rf, hn::IfThenElse(rf_pos, hn::Set(d8, f.inv_hi[a]), hn::Set(d8, f.inv_lo[a])));
      lo = hn::Max(tn, lo);
      hi = hn::Min(tf, hi);
    }
    hi = hn::Min(hn::Mul(hi, hn::Set(d8, kFarScale)), hn::Set(d8, cull_hi));
    hn::StoreU(lo, d8, t_near + i);
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d8, hn::Le(lo, hi), mb);
    bits |= low_bits(mb, n8) << i;
  }
  // Empty slots (lo = +inf, hi = -inf) fail the test: +inf - o is +inf, and so is every product.
  return bits;
}

// The lane test of child c for the lanes in `mask` (node_test8's arithmetic for one child).
template <int kP>
inline std::uint32_t child_lanes(const WideNode& node, const Packet<kP>& p, int c, std::uint32_t mask) {
  const hn::CappedTag<float, kP> d;
  const hn::RebindToUnsigned<decltype(d)> du;
  const std::size_t n = hn::Lanes(d);
  const auto scale = hn::Set(d, kFarScale);
  std::uint32_t bits = 0;
  float nb[3], fb[3];
  for (int a = 0; a < 3; ++a) {
    nb[a] = p.sign[a] ? node.hi[a][c] : node.lo[a][c];
    fb[a] = p.sign[a] ? node.lo[a][c] : node.hi[a][c];
  }
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const auto active = hn::RebindMask(d, hn::TestBit(hn::Set(du, mask), hn::Load(du, kLaneBit + i)));
    auto t0 = hn::LoadU(d, p.t_min + i);
    auto tf = hn::Set(d, kInfF);
    for (int a = 0; a < 3; ++a) {
      const auto o = hn::LoadU(d, p.o[a] + i), inv = hn::LoadU(d, p.inv[a] + i);
      t0 = hn::Max(hn::Mul(hn::Sub(hn::Set(d, nb[a]), o), inv), t0);  // NaN skipped, see node_test1
      tf = hn::Min(hn::Mul(hn::Sub(hn::Set(d, fb[a]), o), inv), tf);
    }
    const auto m = hn::And(active, hn::Le(t0, hn::Min(hn::Mul(tf, scale), hn::LoadU(d, p.cull + i))));
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, m, mb);
    bits |= low_bits(mb, n) << i;
  }
  return bits;
}

// The largest cull distance of the packet's lanes (dead lanes included: a bound is all the
// frustum needs).
template <int kP>
inline float cull_max(const Packet<kP>& p) {
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  auto m = hn::LoadU(d, p.cull);
  for (std::size_t i = n; i < std::size_t(kP); i += n) m = hn::Max(m, hn::LoadU(d, p.cull + i));
  return hn::GetLane(hn::MaxOfLanes(d, m));
}

// Bits of the lanes i with t <= cull[i].
template <int kP>
inline std::uint32_t lanes_within(float t, const float* cull) {
  const hn::CappedTag<float, kP> d;
  const std::size_t n = hn::Lanes(d);
  std::uint32_t bits = 0;
  const auto tv = hn::Set(d, t);
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    std::uint8_t mb[8] = {};
    hn::StoreMaskBits(d, hn::Le(tv, hn::LoadU(d, cull + i)), mb);
    bits |= low_bits(mb, n) << i;
  }
  return bits;
}

// Asks for the cache lines of a child some lane enters, as soon as the lane test says so: a node's
// 4 lines, or a triangle leaf's first block (3 lines), so that its misses overlap the rest of this
// node's work. Forced inline: as a plain inline function GCC 12 deleted every call of it (a
// function that only calls it compiled to a bare ret), so no prefetch was emitted at all (objdump
// of this object: 0 prefetcht0), and the figures once measured for it were noise. Emitted, for any-hit packets only
// (dtraced-bench-rays, avx512, 1 thread, binaries alternated, medians of per-pair ratios, load 4-5): 1M-triangle mesh
// shadow x16 1.017x (8 pairs, 7 above 1; against rtcOccluded16 in the same runs 0.93-0.97 -> 0.95-1.00), x8 1.002x;
// sphere field shadow x16 1.001x, x8 0.989x (5 pairs). Nearest-hit packets do not call it: mesh camera x16 0.994x and
// x8 0.988x (6 pairs; x8 below 1 in all 6), 1.033x / 0.990x in 5 more pairs.
HWY_INLINE void prefetch_child(const WideBvh& bvh, std::uint32_t ref) {
  if (!(ref & kLeafBit)) {
    const char* q = reinterpret_cast<const char*>(&bvh.nodes[ref]);
    for (int k = 0; k < 4; ++k) __builtin_prefetch(q + 64 * k);
  } else if ((ref & kTriLeaf) && tri_leaf_blocks(ref) == 0) {
    // A sphere block (80 bytes, 16-aligned: at most two lines).
    const char* q = reinterpret_cast<const char*>(&bvh.spheres[ref & kTriLeafBeginMask]);
    __builtin_prefetch(q);
    __builtin_prefetch(q + sizeof(SphereBlock) - 1);
  } else if (ref & kTriLeaf) {
    const char* q = reinterpret_cast<const char*>(&bvh.triangles[ref & kTriLeafBeginMask]);
    for (int k = 0; k < 3; ++k) __builtin_prefetch(q + 64 * k);
  }
}

template <int kP, bool kAnyHit>
std::uint32_t traverse_coherent(const WideBvh& bvh, Packet<kP>& p, std::uint32_t live) {
  const Frustum f = make_frustum(p);
  float cull_hi = cull_max(p);  // updated when a lane's cull distance shrinks
  EntryC stack[kStackSize];
  int sp = 0;
  std::uint32_t cur = 0;
  std::uint32_t mask = live;
  std::uint32_t result = 0;    // nearest: lanes that improved; any-hit: lanes blocked
  std::uint32_t alive = live;  // any-hit: lanes not yet blocked
  while (true) {
    if (std::popcount(mask) <= kSwitchCoherent) {
      finish_singles<kP, kAnyHit>(bvh, p, cur, mask, result, alive);
      if (!kAnyHit) cull_hi = cull_max(p);
    } else if (cur & kLeafBit) {
      const std::uint32_t hit = leaf8<kP, kAnyHit>(bvh, leaf_of(bvh, cur), p, mask);
      result |= hit;
      if (kAnyHit) alive &= ~hit;
      if (!kAnyHit && hit != 0) cull_hi = cull_max(p);
    } else {
      const WideNode& node = bvh.nodes[cur];
      alignas(64) float t_near[kNodeWidth];
      std::uint32_t fm = frustum_test(node, p, f, cull_hi, t_near);
      EntryC hit[kNodeWidth];
      int n = 0;
      while (fm != 0) {
        const int c = std::countr_zero(fm);
        fm &= fm - 1;
        // No test of the child reference for an empty slot: the frustum and lane tests fail those
        // (see frustum_test), so the reference's line is read only for a child some lane enters. It
        // was a branch on that load for every child the frustum passed (the hottest instruction of
        // the walk in perf). Without it (1M-triangle mesh, dtraced-bench-rays, avx512, 1 thread,
        // binaries alternated, 7 pairs, medians of per-pair ratios, load 3-4): shadow x16 1.038x
        // (6 pairs above 1), x8 1.010x, camera x16 1.004x, x8 1.008x; sphere field (5 pairs) camera
        // x16 0.998x, x8 1.026x, shadow x16 1.009x, x8 1.016x.
        const std::uint32_t bits = child_lanes(node, p, c, mask);
        if (bits == 0) continue;
        EntryC e{node.child[c], bits, t_near[c]};
        if (kAnyHit) prefetch_child(bvh, e.ref);
        int j = n++;
        while (!kAnyHit && j > 0 && hit[j - 1].t_near < e.t_near) {
          hit[j] = hit[j - 1];
          --j;
        }
        hit[j] = e;
      }
      if (n > 0) {
        for (int i = 0; i < n - 1; ++i) stack[sp++] = hit[i];
        cur = hit[n - 1].ref;
        mask = hit[n - 1].mask;
        continue;
      }
    }
    if (kAnyHit && alive == 0) return result;
    while (true) {
      if (sp == 0) return result;
      --sp;
      std::uint32_t m = stack[sp].mask & alive;
      if (!kAnyHit && m != 0) m &= lanes_within<kP>(stack[sp].t_near, p.cull);
      if (m != 0) {
        cur = stack[sp].ref;
        mask = m;
        break;
      }
    }
  }
}

// The coherent traversal for packets whose lanes share their direction signs; others take the
// per-lane one.
template <int kP, bool kAnyHit>
std::uint32_t traverse_packet(const WideBvh& bvh, Packet<kP>& p, std::uint32_t live) {
  if (p.uniform_signs) return traverse_coherent<kP, kAnyHit>(bvh, p, live);
  return traverse8<kP, kAnyHit>(bvh, p, live);
}

// The hit records of the lanes `lanes` from a finish's per-axis rows: p, p_error and n.
template <int kP>
inline void write_hits(const Packet<kP>& p, std::uint32_t lanes, const float (&out)[9][kP], Hit* hits) {
  for (std::uint32_t m = lanes; m != 0; m &= m - 1) {
    const int i = std::countr_zero(m);
    Hit& hit = hits[i];
    hit.t = p.best[i];
    hit.shape = p.id[i];
    hit.p = Vec3f{out[0][i], out[1][i], out[2][i]};
    hit.p_error = Vec3f{out[3][i], out[4][i], out[5][i]};
    hit.n = Vec3f{out[6][i], out[7][i], out[8][i]};
  }
}

// finish_triangle_hit for the lanes `lanes` of a packet whose best is a triangle (Packet::tri), a
// vector of lanes at a time in double: the same operations in the same order (IEEE division and
// square root, no fused ones), so the same bits, but the lanes' six divisions and square root
// each overlap instead of waiting on one divider lane by lane (they were most of a mesh camera
// packet's hit records). The vertices come from the leaf blocks, which the packet has just tested.
template <int kP>
inline void finish_triangles(const WideBvh& bvh, const Packet<kP>& p, std::uint32_t lanes, Hit* hits) {
  const hn::CappedTag<double, kP> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const std::size_t n = hn::Lanes(dd);
  // Per lane: the edge functions (u, v, w, det) and the vertices (v[vertex][axis]), a vector of
  // lanes at a time: the float edge functions of packet tests from bu ... bdet, the others (double
  // fallback, lanes finished as single rays) patched in lane by lane, and the vertices gathered from
  // the blocks by slot. Lanes not finished take the first finished lane's triangle and edge
  // functions (their results are not written). Against a loop over the lanes, each a branch on
  // whether it is finished and nine scalar loads (dtraced-bench-rays, avx512, 1 thread, the
  // binaries alternated, medians of per-pair ratios, load 6-10): mesh camera x16 1.042x and x8
  // 1.031x (5 pairs); sphere field camera x16 1.089x (5 pairs, against the code before this and
  // the masked early exit of triangle8 together, that one alone 0.985x).
  alignas(64) double e[4][kP];
  alignas(64) float v[3][3][kP];
  const int first = std::countr_zero(lanes);
  const std::uint32_t fill_slot = p.slot[first];
  static_assert(sizeof(TriangleBlock) == 40 * sizeof(float) && offsetof(TriangleBlock, v) == 0);
  const float* const base = &bvh.triangles[0].v[0][0][0];
  // Element indices of the gather are 32-bit: blocks past 2^31 / 40 take a loop over the lanes.
  const bool gather = bvh.triangles.size() <= std::size_t(std::numeric_limits<std::int32_t>::max()) / 40;
  {
    const hn::CappedTag<float, kP> d;
    const hn::RebindToSigned<decltype(d)> di;
    const hn::RebindToUnsigned<decltype(d)> du;
    const std::size_t nf = hn::Lanes(d);
    const auto lanes_v = hn::Set(du, lanes);
    const TriangleUvw fe = p.best_of(first);
    const float* const src[4] = {p.bu, p.bv, p.bw, p.bdet};
    for (std::size_t i = 0; i < std::size_t(kP); i += nf) {
      const auto on = hn::TestBit(lanes_v, hn::Load(du, kLaneBit + i));
      const auto slot = hn::IfThenElse(on, hn::Load(du, p.slot + i), hn::Set(du, fill_slot));
      // Element (slot / kWidth) * 40 + vertex * 12 + axis * 4 + slot % kWidth of the block array.
      if (gather) {
        const auto at = hn::BitCast(
            di, hn::Add(hn::Mul(hn::ShiftRight<2>(slot), hn::Set(du, 40u)), hn::And(slot, hn::Set(du, 3u))));
        for (int k = 0; k < 3; ++k)
          for (int a = 0; a < 3; ++a)
            hn::Store(hn::GatherIndex(d, base, hn::Add(at, hn::Set(di, 12 * k + 4 * a))), d, v[k][a] + i);
      } else {
        alignas(64) std::uint32_t slots[kP];
        hn::Store(slot, du, slots + i);
        for (std::size_t j = i; j < i + nf; ++j) {
          const TriangleBlock& b = bvh.triangles[slots[j] / std::uint32_t(kWidth)];
          for (int k = 0; k < 3; ++k)
            for (int a = 0; a < 3; ++a) v[k][a][j] = b.v[k][a][slots[j] % std::uint32_t(kWidth)];
        }
      }
    }
    const double fill_e[4] = {fe.u, fe.v, fe.w, fe.det};
    for (std::size_t i = 0; i < std::size_t(kP); i += hn::Lanes(dd)) {
      // LoadMaskBits may read 8 bytes: the bits sit in the first two, the rest are zero.
      const std::uint8_t soa_bytes[8] = {std::uint8_t((lanes & p.uvw_soa) >> i),
                                         std::uint8_t((lanes & p.uvw_soa) >> (i + 8))};
      const auto soa = hn::LoadMaskBits(dd, soa_bytes);
      for (int k = 0; k < 4; ++k)
        hn::Store(hn::IfThenElse(soa, hn::PromoteTo(dd, hn::LoadU(df, src[k] + i)), hn::Set(dd, fill_e[k])), dd,
                  e[k] + i);
    }
  }
  for (std::uint32_t m = lanes & ~p.uvw_soa; m != 0; m &= m - 1) {
    const int i = std::countr_zero(m);
    const TriangleUvw& uvw = p.best_uvw[i];
    e[0][i] = uvw.u;
    e[1][i] = uvw.v;
    e[2][i] = uvw.w;
    e[3][i] = uvw.det;
  }
  alignas(64) float out[9][kP];  // p, p_error, n per axis
  const auto g7 = hn::Set(df, math::gamma(7));
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const auto det = hn::Load(dd, e[3] + i);
    const hn::Vec<decltype(dd)> bary[3] = {hn::Div(hn::Load(dd, e[0] + i), det), hn::Div(hn::Load(dd, e[1] + i), det),
                                           hn::Div(hn::Load(dd, e[2] + i), det)};
    hn::Vec<decltype(dd)> vd[3][3];
    for (int k = 0; k < 3; ++k)
      for (int a = 0; a < 3; ++a) vd[k][a] = hn::PromoteTo(dd, hn::LoadU(df, v[k][a] + i));
    for (int a = 0; a < 3; ++a) {
      const auto x0 = hn::Mul(bary[0], vd[0][a]), x1 = hn::Mul(bary[1], vd[1][a]), x2 = hn::Mul(bary[2], vd[2][a]);
      hn::StoreU(hn::DemoteTo(df, hn::Add(hn::Add(x0, x1), x2)), df, out[a] + i);
      const auto sum_abs = hn::Add(hn::Add(hn::Abs(x0), hn::Abs(x1)), hn::Abs(x2));
      hn::StoreU(hn::Mul(g7, hn::DemoteTo(df, sum_abs)), df, out[3 + a] + i);
    }
    // triangle_normal_d: cross(v1 - v0, v2 - v0), then normalize: each component / its length.
    hn::Vec<decltype(dd)> e1[3], e2[3];
    for (int a = 0; a < 3; ++a) {
      e1[a] = hn::Sub(vd[1][a], vd[0][a]);
      e2[a] = hn::Sub(vd[2][a], vd[0][a]);
    }
    const hn::Vec<decltype(dd)> nv[3] = {hn::Sub(hn::Mul(e1[1], e2[2]), hn::Mul(e1[2], e2[1])),
                                         hn::Sub(hn::Mul(e1[2], e2[0]), hn::Mul(e1[0], e2[2])),
                                         hn::Sub(hn::Mul(e1[0], e2[1]), hn::Mul(e1[1], e2[0]))};
    const auto len = hn::Sqrt(hn::Add(hn::Add(hn::Mul(nv[0], nv[0]), hn::Mul(nv[1], nv[1])), hn::Mul(nv[2], nv[2])));
    for (int a = 0; a < 3; ++a) hn::StoreU(hn::DemoteTo(df, hn::Div(nv[a], len)), df, out[6 + a] + i);
  }
  write_hits(p, lanes, out, hits);
}

// finish_sphere_hits (finish_hit's sphere case) for the lanes `lanes` of a packet whose best is a
// sphere a packet test found (Packet::sph), a vector of lanes at a time in double with the same
// operations in the same order: the roots again, the one sphere_t chose, the point projected onto
// the sphere. The sphere comes from its leaf block, the ray from the packet's double copies.
template <int kP>
inline void finish_spheres(const WideBvh& bvh, const Packet<kP>& p, std::uint32_t lanes, Hit* hits) {
  const hn::CappedTag<double, kP> dd;
  const hn::Rebind<float, decltype(dd)> df;
  const std::size_t n = hn::Lanes(dd);
  alignas(64) float sc[4][kP];  // center x, y, z, radius per lane; lanes not finished get a unit sphere
  for (int i = 0; i < kP; ++i) {
    if (lanes >> i & 1u) {
      const SphereBlock& b = bvh.spheres[p.slot[i] / std::uint32_t(kWidth)];
      const std::uint32_t lane = p.slot[i] % std::uint32_t(kWidth);
      sc[0][i] = b.cx[lane];
      sc[1][i] = b.cy[lane];
      sc[2][i] = b.cz[lane];
      sc[3][i] = b.r[lane];
    } else {
      sc[0][i] = sc[1][i] = sc[2][i] = 0.0f;
      sc[3][i] = 1.0f;
    }
  }
  alignas(64) float out[9][kP];  // p, p_error, n per axis
  const auto err_d = hn::Set(dd, kSphereDoubleError);
  const auto g1 = hn::Set(df, math::gamma(1));
  const auto inf = hn::Set(dd, std::numeric_limits<double>::infinity());
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    hn::Vec<decltype(dd)> c[3], f[3], dv[3];
    for (int a = 0; a < 3; ++a) {
      c[a] = hn::PromoteTo(dd, hn::LoadU(df, sc[a] + i));
      f[a] = hn::Sub(hn::LoadU(dd, p.od[a] + i), c[a]);
      dv[a] = hn::LoadU(dd, p.dd[a] + i);
    }
    const auto rad = hn::PromoteTo(dd, hn::LoadU(df, sc[3] + i));
    const auto rr = hn::Mul(rad, rad);
    const auto a = hn::LoadU(dd, p.a + i);
    const auto disc = sphere_disc(f[0], f[1], f[2], dv[0], dv[1], dv[2], a, rr);
    const auto bq = hn::Add(hn::Add(hn::Mul(f[0], dv[0]), hn::Mul(f[1], dv[1])), hn::Mul(f[2], dv[2]));
    const auto cc = hn::Sub(hn::Add(hn::Add(hn::Mul(f[0], f[0]), hn::Mul(f[1], f[1])), hn::Mul(f[2], f[2])), rr);
    const auto q = hn::Neg(hn::Add(bq, hn::CopySign(hn::Sqrt(disc), bq)));
    const auto r0 = hn::Div(cc, q), r1 = hn::Div(q, a);
    const auto swap = hn::Gt(r0, r1);
    const auto t0 = hn::IfThenElse(swap, r1, r0), t1 = hn::IfThenElse(swap, r0, r1);
    // sphere_t's test of the float root, on its exact double image: float(t0) > t_min && < inf.
    const auto t0f = hn::PromoteTo(dd, hn::DemoteTo(df, t0));
    const auto use0 = hn::And(hn::Gt(t0f, hn::PromoteTo(dd, hn::LoadU(df, p.t_min + i))), hn::Lt(t0f, inf));
    const auto td = hn::IfThenElse(use0, t0, t1);
    hn::Vec<decltype(dd)> pl[3];
    for (int k = 0; k < 3; ++k) pl[k] = hn::Add(f[k], hn::Mul(td, dv[k]));
    const auto len = hn::Sqrt(hn::Add(hn::Add(hn::Mul(pl[0], pl[0]), hn::Mul(pl[1], pl[1])), hn::Mul(pl[2], pl[2])));
    const auto scale = hn::Div(rad, len);
    for (int k = 0; k < 3; ++k) {
      pl[k] = hn::Mul(pl[k], scale);
      hn::StoreU(hn::DemoteTo(df, hn::Div(pl[k], rad)), df, out[6 + k] + i);
      const auto pk = hn::DemoteTo(df, hn::Add(c[k], pl[k]));
      hn::StoreU(pk, df, out[k] + i);
      const auto e = hn::DemoteTo(df, hn::Mul(err_d, hn::Add(hn::Abs(pl[k]), hn::Abs(c[k]))));
      hn::StoreU(hn::Add(e, hn::Mul(g1, hn::Abs(pk))), df, out[3 + k] + i);
    }
  }
  write_hits(p, lanes, out, hits);
}

template <int kP>
std::uint32_t IntersectN(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid, float* best_t,
                         std::uint32_t* best_id, Hit* hits, std::uint32_t& finished) {
  Packet<kP> p;
  make_packet(bvh, rays, valid, p, false);
  // A vector at a time: the traversal reads them as vectors at once, and values stored lane by
  // lane do not forward to a vector load.
  const hn::CappedTag<float, kP> d;
  const hn::RebindToUnsigned<decltype(d)> du;
  const std::size_t n = hn::Lanes(d);
  for (std::size_t i = 0; i < std::size_t(kP); i += n) {
    const std::uint8_t valid_bytes[8] = {std::uint8_t(valid >> i), std::uint8_t(valid >> (i + 8))};
    const auto best = hn::IfThenElse(hn::LoadMaskBits(d, valid_bytes), hn::LoadU(d, best_t + i), hn::Set(d, -kInfF));
    hn::StoreU(best, d, p.best + i);
    hn::StoreU(hn::Mul(best, hn::Set(d, kFarScale)), d, p.cull + i);
    hn::StoreU(hn::LoadU(du, best_id + i), du, p.id + i);
  }
  p.uvw_soa = 0;
  p.tri = 0;
  p.sph = 0;
  const std::uint32_t improved = traverse_packet<kP, false>(bvh, p, valid);
  for (int i = 0; i < kP; ++i) {
    if (improved >> i & 1u) {
      best_t[i] = p.best[i];
      best_id[i] = p.id[i];
    }
  }
  const std::uint32_t tri = improved & p.tri, sph = improved & p.sph;
  if (tri != 0) finish_triangles(bvh, p, tri, hits);
  if (sph != 0) finish_spheres(bvh, p, sph, hits);
  finished = tri | sph;
  return improved;
}

template <int kP>
std::uint32_t OccludedN(const WideBvh& bvh, const math::Ray* rays, std::uint32_t valid) {
  Packet<kP> p;
  make_packet(bvh, rays, valid, p, true);
  return traverse_packet<kP, true>(bvh, p, valid);
}

extern const Kernels kKernels;
const Kernels kKernels = {&Intersect1,
                          &Occluded1,
                          &IntersectN<kPacketSize>,
                          &OccludedN<kPacketSize>,
                          &IntersectN<kPacketSize16>,
                          &OccludedN<kPacketSize16>};

}  // namespace HWY_NAMESPACE
}  // namespace dtraced::accel::detail
HWY_AFTER_NAMESPACE();

#if HWY_ONCE
namespace dtraced::accel::detail {

const Kernels& kernels_for(Isa isa) {
  switch (isa) {
#if HWY_TARGETS & HWY_SSE4
    case Isa::kSse4:
      return N_SSE4::kKernels;
#endif
#if HWY_TARGETS & HWY_AVX2
    case Isa::kAvx2:
      return N_AVX2::kKernels;
#endif
#if HWY_TARGETS & HWY_AVX3
    case Isa::kAvx512:
      return N_AVX3::kKernels;
#endif
    default:
      break;
  }
  // Geometry::build only accepts isas supported_isas() lists, and those are compiled here.
  std::abort();
}

}  // namespace dtraced::accel::detail
#endif  // HWY_ONCE
