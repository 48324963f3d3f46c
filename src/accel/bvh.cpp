// dtraced::accel BVH: binned-SAH build into a depth-first node array, and iterative nearest-hit /
// any-hit traversal with a fixed stack. Planes are infinite and tested linearly beside the tree.
//
// The build runs on up to the caller's thread count and gives the same node array whatever that
// count: the levels above kParallelGrain prims are split one node at a time with their bounds,
// binning and partition cut into fixed-size chunks (merged in chunk order; the largest ranges by
// all threads together, the others by one thread each, the same operations), the ranges below
// become independent subtrees built one per thread, and the subtrees are stitched back in
// depth-first order (each copied to its place by one of the threads). The threads are started once per build
// (util::ThreadPool).
#include <algorithm>
#include <array>
#include <atomic>
#include <bit>
#include <cassert>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstring>
#include <deque>
#include <exception>
#include <limits>
#include <memory>
#include <mutex>
#include <new>
#include <optional>
#include <thread>
#include <tuple>
#include <utility>

#if defined(__linux__)
#include <sys/mman.h>
#include <unistd.h>
#endif

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "accel/geometry.h"
#include "accel/kernels.h"
#include "util/cpus.h"
#include "util/huge_pages.h"
#include "util/thread_pool.h"

namespace dtraced::accel {

namespace {

constexpr int kBins = 32;
// A prim's bin is kept in a byte (Scratch::bins), and split_sparse keeps the non-empty bins in a
// 32-bit mask (1u << bin): kBins = 64 compiled, and the 1M-triangle mesh's build then ran for minutes.
static_assert(kBins <= 32, "split_sparse's bin mask has 32 bits");
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
// Ranges of fewer prims are built as one subtree by one thread; larger ones are split by all.
// A constant, not derived from the thread count, so the work split is the same on every host.
constexpr std::uint32_t kParallelGrain = 1u << 15;
// Prims per chunk of the parallel loops (binning, bounds, prim packing).
constexpr std::size_t kChunk = 1u << 14;
// Most threads a build starts, whatever the caller asks.
constexpr unsigned kMaxBuildThreads = 64;
// Ranges of at most this many prims take Splitter::split_sparse (same decisions, less fixed cost).
constexpr std::uint32_t kSparseMax = 16;

// No member is written by the default constructor (Bounds3f and Vec3f have default values, hence
// the unions), so that sizing the array writes no memory: the threads that fill it touch its pages
// first (a serial write of the default values took 0.02-0.17 s for 1M prims).
struct BuildPrim {
  BuildPrim() {}  // leaves every member unset
  BuildPrim(float lx, float ly, float lz, float hx, float hy, float hz, float cx, float cy, float cz, std::uint32_t i)
      : bounds(Bounds3f{Vec3f{lx, ly, lz}, Vec3f{hx, hy, hz}}), centroid(Vec3f{cx, cy, cz}), id(i) {}
  union {
    Bounds3f bounds;
  };
  union {
    Vec3f centroid;
  };
  std::uint32_t id;
};
// BoxAccumulator reads 4 floats from each of bounds.lo, bounds.hi and centroid.
static_assert(offsetof(BuildPrim, bounds) == 0 && offsetof(BuildPrim, centroid) == sizeof(Bounds3f) &&
              sizeof(Bounds3f) == 6 * sizeof(float) && sizeof(BuildPrim) >= sizeof(Bounds3f) + 4 * sizeof(float));

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

std::size_t chunks_of(std::size_t n) { return (n + kChunk - 1) / kChunk; }

struct RangeBounds {
  Bounds3f bounds, centroids;
};

// Bounds3f::extend for the build's passes over prims (their bounds and the bins), most of whose
// time went to those minima and maxima: x, y and z in one SSE2 instruction where there is SSE2.
// The same bits as Bounds3f::extend: _mm_min_ps(a, b) is a < b ? a : b in each lane, so
// _mm_min_ps(new, held) keeps `held` unless `new` is below it, as std::min(held, new) does (for
// +0 / -0 and NaN too), and likewise _mm_max_ps.
#if defined(__SSE2__)
class BoxAccumulator {
 public:
  // Reads the float after `lo` and after `hi` too (lane 3, ignored): both must be followed by
  // one, as a BuildPrim's bounds and centroid are.
  void extend(const Vec3f& lo, const Vec3f& hi) {
    lo_ = _mm_min_ps(_mm_loadu_ps(&lo.x), lo_);
    hi_ = _mm_max_ps(_mm_loadu_ps(&hi.x), hi_);
  }
  // The same from floats held in registers (lane 3 is ignored, as above).
  void extend(float lx, float ly, float lz, float hx, float hy, float hz) {
    lo_ = _mm_min_ps(_mm_setr_ps(lx, ly, lz, 0.0f), lo_);
    hi_ = _mm_max_ps(_mm_setr_ps(hx, hy, hz, 0.0f), hi_);
  }
  void merge(const BoxAccumulator& o) {
    lo_ = _mm_min_ps(o.lo_, lo_);
    hi_ = _mm_max_ps(o.hi_, hi_);
  }
  // area(bounds()) to the bit (the same operations in double), without going through memory.
  double area() const {
    if ((_mm_movemask_ps(_mm_cmpgt_ps(lo_, hi_)) & 7) != 0) return 0.0;  // empty
    const __m128d e_xy = _mm_sub_pd(_mm_cvtps_pd(hi_), _mm_cvtps_pd(lo_));
    const __m128d e_zw = _mm_sub_pd(_mm_cvtps_pd(_mm_movehl_ps(hi_, hi_)), _mm_cvtps_pd(_mm_movehl_ps(lo_, lo_)));
    const double ex = _mm_cvtsd_f64(e_xy), ey = _mm_cvtsd_f64(_mm_unpackhi_pd(e_xy, e_xy)), ez = _mm_cvtsd_f64(e_zw);
    return 2.0 * (ex * ey + ey * ez + ez * ex);
  }
  Bounds3f bounds() const {
    alignas(16) float lo[4], hi[4];
    _mm_store_ps(lo, lo_);
    _mm_store_ps(hi, hi_);
    Bounds3f b;
    b.lo = {lo[0], lo[1], lo[2]};
    b.hi = {hi[0], hi[1], hi[2]};
    return b;
  }

 private:
  __m128 lo_ = _mm_set1_ps(std::numeric_limits<float>::infinity());
  __m128 hi_ = _mm_set1_ps(-std::numeric_limits<float>::infinity());
};
#else
class BoxAccumulator {
 public:
  void extend(const Vec3f& lo, const Vec3f& hi) { b_.extend(Bounds3f{lo, hi}); }
  void extend(float lx, float ly, float lz, float hx, float hy, float hz) {
    b_.extend(Bounds3f{Vec3f{lx, ly, lz}, Vec3f{hx, hy, hz}});
  }
  void merge(const BoxAccumulator& o) { b_.extend(o.b_); }
  double area() const { return dtraced::accel::area(b_); }
  Bounds3f bounds() const { return b_; }

 private:
  Bounds3f b_;
};
#endif

// Each bin's bounds stay in an accumulator, which the SAH sweeps merge and measure without making
// a Bounds3f of it: the same minima and maxima in the same order as Bounds3f::extend, and
// BoxAccumulator::area is area() to the bit, so the same costs.
struct Bins {
  std::array<BoxAccumulator, kBins> bounds;
  std::array<std::uint32_t, kBins> count{};
};

// What one thread's splits of ranges of up to `size` prims write as they go: each prim's bin
// (bins[i - begin] for prim i), and the positions partition_by_bins swaps.
struct Scratch {
  explicit Scratch(std::size_t size) : bins(size), misplaced(size) {}
  std::vector<std::uint8_t> bins;
  std::vector<std::uint32_t> misplaced;
};

// std::partition of prims[begin, end) by bins[i - begin] <= best_k, in the order libstdc++ leaves
// them (the tree depends on it), given `mid`, the number of prims that go left plus begin.
// libstdc++'s partition for random-access iterators walks in from both ends and swaps the next prim
// from the left that belongs right with the next prim from the right that belongs left until the
// two meet, which is at `mid`: so the k-th prim of [begin, mid) that belongs right trades places
// with the k-th prim of [mid, end), counted from the end, that belongs left, and nothing else
// moves. In that form the loops that find them have no branch that depends on the prims, the bins
// were found by the binning pass (std::partition computed each prim's bin again), and the order
// no longer depends on the C++ library either. Tested: BVH build's tree hashes recorded with
// std::partition.
void partition_by_bins(BuildPrim* prims, std::uint32_t begin, std::uint32_t mid, std::uint32_t end,
                       const std::uint8_t* bins, int best_k, std::uint32_t* misplaced) {
  // Each loop writes a slot before it knows whether the prim counts; the first writes at most
  // mid - begin slots, the second end - mid after the first's count: `misplaced` holds end - begin.
  std::uint32_t left = 0;
  for (std::uint32_t i = begin; i < mid; ++i) {
    misplaced[left] = i;
    left += bins[i - begin] > best_k;
  }
  std::uint32_t* const from_right = misplaced + left;
  std::uint32_t right = 0;
  for (std::uint32_t i = end; i-- > mid;) {
    from_right[right] = i;
    right += bins[i - begin] <= best_k;
  }
  assert(right == left);
  for (std::uint32_t k = 0; k < left; ++k) std::swap(prims[misplaced[k]], prims[from_right[k]]);
}

// The prims of a sparse range (split_sparse) whose bin is `b`, as a mask (bit i: prim i).
std::uint32_t prims_in_bin(const std::array<std::uint8_t, kSparseMax>& bin_at, int b) {
  static_assert(kSparseMax == 16, "one SSE2 comparison covers the range");
#if defined(__SSE2__)
  const __m128i bins = _mm_load_si128(reinterpret_cast<const __m128i*>(bin_at.data()));
  return std::uint32_t(_mm_movemask_epi8(_mm_cmpeq_epi8(bins, _mm_set1_epi8(char(b)))));
#else
  std::uint32_t mask = 0;
  for (std::size_t i = 0; i < bin_at.size(); ++i) mask |= std::uint32_t(bin_at[i] == b) << i;
  return mask;
#endif
}

// The outcome of looking at one range: a leaf, or a split at `mid` along `axis`. (Handing the
// children their bounds from the bins, to save them a pass, was tried: tracking centroid bounds
// per bin cost more than the pass. Gathering them in the partition as it moved the prims was
// tried too: the same bits take care, as the partition meets the right side's prims last to
// first and +0 and -0 are equal bounds of different bits, and 1M spheres took 5 % more CPU.)
struct Split {
  Bounds3f bounds;
  bool leaf = false;
  std::uint32_t axis = 0;
  std::uint32_t mid = 0;
};

// Binned SAH over refs[begin, end): the same decisions for a range whoever looks at it. With
// `threads` > 1 the passes over the range go in kChunk pieces, merged in chunk order; `chunked`
// selects that form (also on one thread) so a range's bounds come out of the same operations
// whatever the thread count.
class Splitter {
 public:
  // Ranges of kParallelGrain prims or more are split on several threads with partition_chunked,
  // whose scratch (2 bytes a prim, left unwritten until used) is made here once for the whole build.
  Splitter(std::vector<BuildPrim>& refs, Isa isa, util::ThreadPool& pool)
      : refs_(refs),
        isa_(isa),
        pool_(pool),
        offsets_(refs.size() >= kParallelGrain && pool.size() > 1 ? new std::uint16_t[refs.size()] : nullptr) {}

  // The shape ids of refs_[begin, end) into ids[begin, end).
  void copy_ids(std::uint32_t begin, std::uint32_t end, std::uint32_t* ids) const {
    for (std::uint32_t i = begin; i < end; ++i) ids[i] = refs_[i].id;
  }

  // `scratch` (when not chunked) holds at least end - begin prims. `known`, where given, is the
  // range's range_bounds_chunked, found without a pass over its prims (the root's: Geometry::build).
  Split split(std::uint32_t begin, std::uint32_t end, std::uint32_t depth, bool chunked, unsigned threads,
              Scratch* scratch = nullptr, const RangeBounds* known = nullptr) const {
    assert(chunked || (scratch && scratch->bins.size() >= end - begin));
    Split out;
    const RangeBounds rb = known     ? *known
                           : chunked ? range_bounds_chunked(begin, end, threads)
                                     : range_bounds(begin, end);
    out.bounds = rb.bounds;
    const std::uint32_t n = end - begin;
    if (n == 1 || depth + 1 >= Geometry::kMaxDepth) {
      out.leaf = true;
      return out;
    }
    const auto axis = std::uint32_t(math::max_dimension(rb.centroids.extent()));
    out.axis = axis;
    const double c_lo = rb.centroids.lo[axis];
    const double c_extent = double(rb.centroids.hi[axis]) - c_lo;
    if (!(c_extent > 0.0)) {
      // All centroids coincide: SAH cannot separate them, split the range in half.
      out.leaf = n <= kMaxLeafSize;
      out.mid = begin + n / 2;
      return out;
    }
    const double scale = kBins / c_extent;
    if (!chunked && n <= kSparseMax) return split_sparse(begin, end, rb.bounds, axis, c_lo, scale, *scratch);
    const Bins bins = chunked ? bin_chunked(begin, end, axis, c_lo, scale, threads)
                              : bin(begin, end, axis, c_lo, scale, scratch->bins.data());
    // SAH cost of splitting after bin k, scaled by the node's area to avoid a division (flat or
    // point-like nodes have zero area): kTraversalCost A + A_left n_left + A_right n_right.
    // Only splits between the first and the last non-empty bin have two non-empty sides; the
    // sweeps skip the rest (most bins of a small range are empty).
    int first_bin = 0, last_bin = kBins - 1;
    while (bins.count[first_bin] == 0) ++first_bin;
    while (bins.count[last_bin] == 0) --last_bin;
    std::array<double, kBins - 1> left_cost{};
    BoxAccumulator acc;
    std::uint32_t acc_n = 0;
    for (int k = first_bin; k < last_bin; ++k) {
      acc.merge(bins.bounds[k]);
      acc_n += bins.count[k];
      left_cost[k] = acc_n == 0 ? -1.0 : acc.area() * acc_n;  // -1: empty side, not a split
    }
    const double node_area = area(rb.bounds);
    double best_cost = std::numeric_limits<double>::infinity();
    int best_k = -1;
    acc = BoxAccumulator();
    acc_n = 0;
    for (int k = last_bin - 1; k >= first_bin; --k) {
      acc.merge(bins.bounds[k + 1]);
      acc_n += bins.count[k + 1];
      if (acc_n == 0 || left_cost[k] < 0.0) continue;
      const double cost = kTraversalCost * node_area + left_cost[k] + acc.area() * acc_n;
      if (cost <= best_cost) {
        best_cost = cost;
        best_k = k;
      }
    }
    // The SIMD kernels test a leaf's prims 4 at a time, so for them a fuller leaf costs little
    // more than a single prim: favour leaves of up to kMaxLeafSize (fewer, fuller blocks).
    const double leaf_cost = (isa_ == Isa::kScalar ? double(n) : 1.0 + kSimdLeafSlope * (n - 1)) * node_area;
    if (n <= kMaxLeafSize && leaf_cost <= best_cost) {
      out.leaf = true;
      return out;
    }
    if (best_k < 0) {
      out.mid = begin + n / 2;  // NaN costs (cannot happen for valid shapes): split in half
    } else if (!chunked) {
      out.mid = begin;
      for (int k = 0; k <= best_k; ++k) out.mid += bins.count[k];
      partition_by_bins(refs_.data(), begin, out.mid, end, scratch->bins.data(), best_k, scratch->misplaced.data());
    } else if (threads <= 1 || !offsets_) {
      // One thread: std::partition's one pass (partition_chunked's two passes cost more there).
      auto* first = refs_.data() + begin;
      auto* last = refs_.data() + end;
      out.mid = std::uint32_t(
          std::partition(first, last,
                         [&](const BuildPrim& p) { return bin_of(p.centroid[axis], c_lo, scale) <= best_k; }) -
          refs_.data());
    } else {
      out.mid = begin;
      for (int k = 0; k <= best_k; ++k) out.mid += bins.count[k];
      partition_chunked(begin, out.mid, end, axis, c_lo, scale, best_k, threads);
    }
    assert(out.mid > begin && out.mid < end);
    return out;
  }

 private:
  // Small ranges (most nodes of a tree) fill few of the kBins bins, and the fixed cost of the bins
  // (clearing them, two sweeps with a surface area in double per bin) outweighed their prims. This
  // is the same binned SAH over the non-empty bins only: the same bins (bin_of), each bin's bounds
  // gathered in prim order and the sides in bin order (minima and maxima, extending by an empty bin
  // changes nothing), so the same costs to the bit; a split between two non-empty bins stands for
  // every split among the empty bins between them (same sides, same cost) and, like the sweep over
  // all bins, ties go to the lowest. Same decisions, same tree.
  Split split_sparse(std::uint32_t begin, std::uint32_t end, const Bounds3f& bounds, std::uint32_t axis, double c_lo,
                     double scale, Scratch& scratch) const {
    Split out;
    out.bounds = bounds;
    out.axis = axis;
    const std::uint32_t n = end - begin;
    // Each prim's bin (a byte; lanes past n hold 0xff, no bin) and the set of non-empty bins.
    const BuildPrim* const prims = refs_.data() + begin;
    alignas(16) std::array<std::uint8_t, kSparseMax> bin_at;
    bin_at.fill(0xff);
    std::uint32_t occupied = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
      const int b = bin_of(prims[i].centroid[axis], c_lo, scale);
      bin_at[i] = std::uint8_t(b);
      occupied |= 1u << b;
    }
    std::copy_n(bin_at.begin(), n, scratch.bins.begin());
    // The non-empty bins in bin order: their index, count and bounds (gathered in prim order).
    std::array<int, kSparseMax> bin_index;
    std::array<std::uint32_t, kSparseMax> count;
    std::array<BoxAccumulator, kSparseMax> bin_bounds;
    std::uint32_t groups = 0;
    for (; occupied != 0; occupied &= occupied - 1, ++groups) {
      const int b = std::countr_zero(occupied);
      bin_index[groups] = b;
      count[groups] = 0;  // counted here: std::popcount is a library call without -mpopcnt
      BoxAccumulator& box = bin_bounds[groups];
      for (std::uint32_t members = prims_in_bin(bin_at, b); members != 0; members &= members - 1) {
        const BuildPrim& p = prims[std::countr_zero(members)];  // bit i: prim i
        box.extend(p.bounds.lo, p.bounds.hi);
        ++count[groups];
      }
    }
    // Split after group g (g + 1 < groups): the sweeps of split() over these groups.
    std::array<double, kSparseMax> left_cost;
    BoxAccumulator acc;
    std::uint32_t acc_n = 0;
    for (std::uint32_t g = 0; g + 1 < groups; ++g) {
      acc.merge(bin_bounds[g]);
      acc_n += count[g];
      left_cost[g] = acc.area() * acc_n;
    }
    const double node_area = area(bounds);
    double best_cost = std::numeric_limits<double>::infinity();
    int best_k = -1;
    std::uint32_t best_left = 0;  // prims in groups [0, best group]
    acc = BoxAccumulator();
    acc_n = 0;
    for (std::uint32_t g = groups - 1; g-- > 0;) {
      acc.merge(bin_bounds[g + 1]);
      acc_n += count[g + 1];
      const double cost = kTraversalCost * node_area + left_cost[g] + acc.area() * acc_n;
      if (cost <= best_cost) {
        best_cost = cost;
        best_k = bin_index[g];
        best_left = n - acc_n;
      }
    }
    const double leaf_cost = (isa_ == Isa::kScalar ? double(n) : 1.0 + kSimdLeafSlope * (n - 1)) * node_area;
    if (n <= kMaxLeafSize && leaf_cost <= best_cost) {
      out.leaf = true;
      return out;
    }
    if (best_k < 0) {
      out.mid = begin + n / 2;
    } else {
      out.mid = begin + best_left;
      partition_by_bins(refs_.data(), begin, out.mid, end, scratch.bins.data(), best_k, scratch.misplaced.data());
    }
    assert(out.mid > begin && out.mid < end);
    return out;
  }

  // std::partition of refs_[begin, end) by bin_of(centroid) <= best_k, in its order (see
  // partition_by_bins: the k-th prim of [begin, mid) that belongs right trades places with the k-th
  // prim of [mid, end), counted from the end, that belongs left), on `threads` threads. The left
  // side is cut into kChunk pieces from `begin`, the right side from `end` down; a first pass
  // finds each piece's misplaced prims (their offsets in the piece, 2 bytes each), a second swaps
  // the k-th of the left with the k-th of the right, pieces of the left side in parallel. (The top
  // levels used std::partition itself, on one thread while the others waited.)
  void partition_chunked(std::uint32_t begin, std::uint32_t mid, std::uint32_t end, std::uint32_t axis, double c_lo,
                         double scale, int best_k, unsigned threads) const {
    static_assert(kChunk <= (std::size_t(1) << 16), "an offset in a piece is kept in 2 bytes");
    const std::size_t left_n = mid - begin, right_n = end - mid;
    const std::size_t left_chunks = chunks_of(left_n), right_chunks = chunks_of(right_n);
    // Piece c of the left writes at offsets[c * kChunk...], piece j of the right at
    // offsets[left_n + j * kChunk...]: each writes at most its own size.
    std::uint16_t* const offsets = offsets_.get();
    std::vector<std::uint32_t> misplaced(left_chunks + right_chunks);
    BuildPrim* const prims = refs_.data();
    pool_.parallel_for(left_chunks + right_chunks, threads, [&](std::size_t c) {
      std::uint32_t count = 0;
      if (c < left_chunks) {
        const std::size_t lo = begin + c * kChunk, hi = std::min<std::size_t>(mid, lo + kChunk);
        std::uint16_t* const out = offsets + c * kChunk;
        for (std::size_t i = lo; i < hi; ++i) {
          out[count] = std::uint16_t(i - lo);
          count += bin_of(prims[i].centroid[axis], c_lo, scale) > best_k;
        }
      } else {
        const std::size_t j = c - left_chunks;
        const std::size_t hi = end - j * kChunk, lo = hi - std::min<std::size_t>(kChunk, hi - mid);
        std::uint16_t* const out = offsets + left_n + j * kChunk;
        for (std::size_t i = hi; i-- > lo;) {
          out[count] = std::uint16_t(hi - 1 - i);
          count += bin_of(prims[i].centroid[axis], c_lo, scale) <= best_k;
        }
      }
      misplaced[c] = count;
    });
    // The first rank of each right piece (right_first[j]); the left pieces' in the loop below.
    std::vector<std::size_t> right_first(right_chunks + 1, 0);
    for (std::size_t j = 0; j < right_chunks; ++j) right_first[j + 1] = right_first[j] + misplaced[left_chunks + j];
    std::vector<std::size_t> left_first(left_chunks + 1, 0);
    for (std::size_t c = 0; c < left_chunks; ++c) left_first[c + 1] = left_first[c] + misplaced[c];
    assert(left_first[left_chunks] == right_first[right_chunks]);
    pool_.parallel_for(left_chunks, threads, [&](std::size_t c) {
      const std::size_t first = left_first[c], count = misplaced[c];
      if (count == 0) return;
      const std::uint16_t* const from_left = offsets + c * kChunk;
      const std::size_t left_base = begin + c * kChunk;
      // The right piece that holds rank `first`.
      std::size_t j =
          std::size_t(std::upper_bound(right_first.begin(), right_first.end(), first) - right_first.begin()) - 1;
      for (std::size_t t = 0, k = first; t < count; ++t, ++k) {
        while (k >= right_first[j + 1]) ++j;
        const std::size_t right = end - 1 - j * kChunk - offsets[left_n + j * kChunk + (k - right_first[j])];
        std::swap(prims[left_base + from_left[t]], prims[right]);
      }
    });
  }

  RangeBounds range_bounds(std::size_t begin, std::size_t end) const {
    BoxAccumulator bounds, centroids;
    for (std::size_t i = begin; i < end; ++i) {
      const BuildPrim& p = refs_[i];
      bounds.extend(p.bounds.lo, p.bounds.hi);
      centroids.extend(p.centroid, p.centroid);
    }
    return {bounds.bounds(), centroids.bounds()};
  }
  RangeBounds range_bounds_chunked(std::size_t begin, std::size_t end, unsigned threads) const {
    std::vector<RangeBounds> parts(chunks_of(end - begin));
    pool_.parallel_for(parts.size(), threads, [&](std::size_t c) {
      parts[c] = range_bounds(begin + c * kChunk, std::min(end, begin + (c + 1) * kChunk));
    });
    RangeBounds rb;
    for (const RangeBounds& p : parts) {
      rb.bounds.extend(p.bounds);
      rb.centroids.extend(p.centroids);
    }
    return rb;
  }
  // With `bin_at`, also each prim's bin: bin_at[i - begin] for prim i.
  Bins bin(std::size_t begin, std::size_t end, std::uint32_t axis, double c_lo, double scale,
           std::uint8_t* bin_at = nullptr) const {
    Bins bins;
    const BuildPrim* const prims = refs_.data();
    for (std::size_t i = begin; i < end; ++i) {
      const BuildPrim& p = prims[i];
      const int b = bin_of(p.centroid[axis], c_lo, scale);
      ++bins.count[b];
      bins.bounds[b].extend(p.bounds.lo, p.bounds.hi);
      if (bin_at) bin_at[i - begin] = std::uint8_t(b);
    }
    return bins;
  }
  Bins bin_chunked(std::size_t begin, std::size_t end, std::uint32_t axis, double c_lo, double scale,
                   unsigned threads) const {
    std::vector<Bins> parts(chunks_of(end - begin));
    pool_.parallel_for(parts.size(), threads, [&](std::size_t c) {
      parts[c] = bin(begin + c * kChunk, std::min(end, begin + (c + 1) * kChunk), axis, c_lo, scale);
    });
    Bins bins;
    for (const Bins& p : parts) {
      for (int k = 0; k < kBins; ++k) {
        bins.bounds[k].merge(p.bounds[k]);
        bins.count[k] += p.count[k];
      }
    }
    return bins;
  }

  std::vector<BuildPrim>& refs_;
  Isa isa_;
  util::ThreadPool& pool_;
  std::unique_ptr<std::uint16_t[]> offsets_;  // partition_chunked's, for refs_.size() prims
};

// A subtree built by one thread: nodes in depth-first order, `offset`s of interior nodes local to
// `nodes` (copy_subtrees adds the subtree's place in the whole array), leaf offsets into refs.
template <typename Node>
struct Subtree {
  std::uint32_t begin = 0, end = 0, depth = 0;
  std::vector<Node> nodes;
  std::uint32_t leaves = 0;
  std::uint32_t max_depth = 0;
};

template <typename Node>
void fill_node(Node& node, const Split& s, std::uint32_t begin, std::uint32_t end) {
  for (int i = 0; i < 3; ++i) {
    node.bounds[i] = s.bounds.lo[i];
    node.bounds[3 + i] = s.bounds.hi[i];
  }
  if (s.leaf) {
    node.offset = begin;
    node.count = end - begin;
    node.axis = 0;
  } else {
    node.offset = 0;
    node.count = 0;
    node.axis = s.axis;
  }
}

// Appends the tree of refs[begin, end) to `nodes` depth first, on the calling thread; interior
// nodes' `offset`s are indices into `nodes`. Returns how many leaves it made and the deepest depth.
template <typename Node>
std::pair<std::uint32_t, std::uint32_t> build_range(const Splitter& splitter, std::uint32_t begin, std::uint32_t end,
                                                    std::uint32_t depth, std::vector<Node>& nodes, Scratch& scratch) {
  std::uint32_t leaves = 0, max_depth = 0;
  std::vector<Task> stack;
  stack.push_back({begin, end, depth, kNoParent});
  while (!stack.empty()) {
    const Task task = stack.back();
    stack.pop_back();
    const auto index = std::uint32_t(nodes.size());
    if (task.parent != kNoParent) nodes[task.parent].offset = index;
    max_depth = std::max(max_depth, task.depth);
    const Split s = splitter.split(task.begin, task.end, task.depth, /* chunked = */ false, 1, &scratch);
    fill_node(nodes.emplace_back(), s, task.begin, task.end);
    if (s.leaf) {
      ++leaves;
      continue;
    }
    // LIFO: the first child is popped next and so lands at index + 1.
    stack.push_back({s.mid, task.end, task.depth + 1, index});
    stack.push_back({task.begin, s.mid, task.depth + 1, kNoParent});
  }
  return {leaves, max_depth};
}

// Builds refs[t.begin, t.end) depth first into t.nodes and copies their ids to ids[t.begin, t.end),
// on the calling thread, with a scratch of its own (one scratch a thread for all its subtrees
// raised the 1M-sphere build's peak by 8 MiB: the allocator then kept the freed subtree nodes
// instead of handing their memory to copy_subtrees).
template <typename Node>
void build_subtree(const Splitter& splitter, Subtree<Node>& t, std::uint32_t* ids) {
  t.nodes.reserve(std::size_t(t.end - t.begin) * 2 / 3 + 1);  // leaves hold about two prims
  Scratch scratch(t.end - t.begin);
  std::tie(t.leaves, t.max_depth) = build_range(splitter, t.begin, t.end, t.depth, t.nodes, scratch);
  splitter.copy_ids(t.begin, t.end, ids);
}

// The levels above kParallelGrain: one node each (`subtree` < 0), or a range left to a subtree.
// Kept in a std::deque: a thread holds on to its node while another appends.
template <typename Node>
struct TopNode {
  Node node;
  int first = -1, second = -1;  // children, indices into the top node list
  int subtree = -1;             // index into the subtree list
  std::uint32_t depth = 0;
  std::uint32_t begin = 0, end = 0;  // the node's prims
};

// The top levels that all threads split together (each pass over a range cut in chunks): the
// ranges of more than a thread's share of the prims (`shared_above`). The ranges below are left in
// `pending` for split_pending. Returns the node's index. `known`: the range's bounds, if known.
template <typename Node>
int split_top(const Splitter& splitter, std::uint32_t begin, std::uint32_t end, std::uint32_t depth, unsigned threads,
              std::size_t shared_above, std::deque<TopNode<Node>>& top, std::vector<TopNode<Node>*>& pending,
              const RangeBounds* known = nullptr) {
  const int index = int(top.size());
  TopNode<Node>& tn = top.emplace_back();
  tn.depth = depth;
  tn.begin = begin;
  tn.end = end;
  if (end - begin < kParallelGrain || end - begin <= shared_above) {
    pending.push_back(&tn);
    return index;
  }
  const Split s = splitter.split(begin, end, depth, /* chunked = */ true, threads, nullptr, known);
  fill_node(tn.node, s, begin, end);
  if (!s.leaf) {
    // Recursion depth is bounded by log2(prims / kParallelGrain) + 1: both children are smaller.
    const int first = split_top(splitter, begin, s.mid, depth + 1, threads, shared_above, top, pending);
    const int second = split_top(splitter, s.mid, end, depth + 1, threads, shared_above, top, pending);
    tn.first = first;
    tn.second = second;
  }
  return index;
}

// The rest of the tree below split_top's levels, on `threads` threads: each thread takes the
// largest pending range, splits it alone (the same chunked passes on one thread, so the same bits)
// and leaves its two halves pending, or builds it as a subtree once it holds fewer than
// kParallelGrain prims. (Splitting those levels with all threads at once made each pass wait for
// the others: a few hundred short loops, most of whose items one thread took alone.) The nodes
// and subtrees are linked as split_top links them, so the stitch (place and copy_subtrees) gives
// the same tree whichever thread made what.
template <typename Node>
void split_pending(const Splitter& splitter, util::ThreadPool& pool, unsigned threads, std::deque<TopNode<Node>>& top,
                   std::deque<Subtree<Node>>& subtrees, std::vector<TopNode<Node>*> pending, std::uint32_t* ids) {
  std::mutex mutex;
  std::condition_variable wake;  // a range is pending, or nothing is left to do
  std::size_t busy = 0;          // threads working on a range (they may leave two more)
  bool failed = false;
  pool.parallel_for(threads, threads, [&](std::size_t) {
    std::unique_lock lock(mutex);
    for (;;) {
      wake.wait(lock, [&] { return failed || !pending.empty() || busy == 0; });
      if (failed || pending.empty()) return;
      const auto largest = std::max_element(pending.begin(), pending.end(), [](const auto* a, const auto* b) {
        return a->end - a->begin < b->end - b->begin;
      });
      TopNode<Node>& tn = **largest;
      *largest = pending.back();
      pending.pop_back();
      ++busy;
      try {
        if (tn.end - tn.begin < kParallelGrain) {
          tn.subtree = int(subtrees.size());
          Subtree<Node>& t = subtrees.emplace_back();
          t.begin = tn.begin;
          t.end = tn.end;
          t.depth = tn.depth;
          lock.unlock();
          build_subtree(splitter, t, ids);
          lock.lock();
        } else {
          lock.unlock();
          const Split s = splitter.split(tn.begin, tn.end, tn.depth, /* chunked = */ true, 1);
          fill_node(tn.node, s, tn.begin, tn.end);
          lock.lock();
          if (!s.leaf) {
            for (const auto& [b, e, link] :
                 {std::tuple(tn.begin, s.mid, &tn.first), std::tuple(s.mid, tn.end, &tn.second)}) {
              *link = int(top.size());
              TopNode<Node>& child = top.emplace_back();
              child.depth = tn.depth + 1;
              child.begin = b;
              child.end = e;
              pending.push_back(&child);
            }
            wake.notify_all();
          }
        }
      } catch (...) {
        if (!lock.owns_lock()) lock.lock();
        failed = true;  // the others stop; the pool throws this once they have
        --busy;
        wake.notify_all();
        throw;
      }
      if (--busy == 0 && pending.empty()) wake.notify_all();
    }
  });
}

// On one thread: the tree split_top, build_subtree and the stitch make, each node appended to
// `nodes` as it is made, in the order place gives it (split_top's levels chunked as there, so their
// bounds come out of the same operations): no subtree nodes to fill and copy. `nodes` should not
// reallocate (reserve the most nodes the range can make). Each range's ids go to `ids` once built.
// `known`: the range's bounds, if known.
template <typename Node>
void build_in_place(const Splitter& splitter, std::uint32_t begin, std::uint32_t end, std::uint32_t depth,
                    std::vector<Node>& nodes, Scratch& scratch, std::uint32_t& leaves, std::uint32_t& max_depth,
                    std::uint32_t* ids, const RangeBounds* known = nullptr) {
  if (end - begin < kParallelGrain) {
    const auto [l, d] = build_range(splitter, begin, end, depth, nodes, scratch);
    leaves += l;
    max_depth = std::max(max_depth, d);
    splitter.copy_ids(begin, end, ids);
    return;
  }
  const Split s = splitter.split(begin, end, depth, /* chunked = */ true, 1, nullptr, known);
  const auto index = std::uint32_t(nodes.size());
  fill_node(nodes.emplace_back(), s, begin, end);
  max_depth = std::max(max_depth, depth);
  if (s.leaf) {
    ++leaves;
    splitter.copy_ids(begin, end, ids);
    return;
  }
  build_in_place(splitter, begin, s.mid, depth + 1, nodes, scratch, leaves, max_depth, ids);  // lands at index + 1
  nodes[index].offset = std::uint32_t(nodes.size());
  build_in_place(splitter, s.mid, end, depth + 1, nodes, scratch, leaves, max_depth, ids);
}

// Gives top node `t` and everything below it their places in the depth-first node array from
// `next` on (depth first, each subtree's nodes one run): writes the top nodes there,
// their second children's indices included, and each subtree's first index into `subtree_at`
// for copy_subtrees. Returns t's index. Serial, but it touches only the top nodes (a few dozen).
template <typename Node>
std::uint32_t place(int t, const std::deque<TopNode<Node>>& top, const std::deque<Subtree<Node>>& subtrees,
                    std::vector<std::uint32_t>& subtree_at, Node* nodes, std::uint32_t& next) {
  const std::uint32_t index = next;
  const TopNode<Node>& tn = top[t];
  if (tn.subtree >= 0) {
    subtree_at[tn.subtree] = index;
    next += std::uint32_t(subtrees[tn.subtree].nodes.size());
    return index;
  }
  nodes[index] = tn.node;
  ++next;
  if (tn.first >= 0) {
    place(tn.first, top, subtrees, subtree_at, nodes, next);  // lands at index + 1
    nodes[index].offset = place(tn.second, top, subtrees, subtree_at, nodes, next);
  }
  return index;
}

// Copies one subtree's nodes to their place `at`, its interior nodes' offsets moved by it, and
// frees them.
template <typename Node>
void copy_subtree(std::vector<Node>& from, std::uint32_t at, Node* nodes) {
  Node* const to = nodes + at;
  for (std::size_t i = 0; i < from.size(); ++i) {
    Node n = from[i];
    if (n.count == 0) n.offset += at;
    to[i] = n;
  }
  std::vector<Node>().swap(from);
}

// Copies each subtree's nodes to its place (place's `subtree_at`), its interior nodes' offsets
// moved by that place, the subtrees spread over `threads` threads (they write disjoint ranges);
// each subtree's nodes are freed once copied, so that the two copies of the nodes are never all
// alive at once. The same array as a serial depth-first copy, which ran on one thread while the
// others waited (1M spheres on 2 threads, the stitch's wall time in one process, serial and
// parallel alternated: median pair ratio 0.77 over 56 pairs at a load average of 6-8, where the
// copy mostly waits for a core, so only 31 of them lower).
template <typename Node>
void copy_subtrees(std::deque<Subtree<Node>>& subtrees, const std::vector<std::uint32_t>& subtree_at, Node* nodes,
                   util::ThreadPool& pool, unsigned threads) {
  pool.parallel_for(subtrees.size(), threads,
                    [&](std::size_t k) { copy_subtree(subtrees[k].nodes, subtree_at[k], nodes); });
}

// A subtree whose copy into place runs in the tree hash's loop: its first node there, its index
// among the subtrees and its node count.
struct Stitch {
  std::uint32_t at = 0, subtree = 0, size = 0;
};

// While a large sphere scene's tree is collapsed, its shapes (40 bytes a sphere) are not held (the
// array keeps its place but not its pages, drop_pages): the spheres of the tree are in its prims,
// and then in the wide tree's sphere blocks, from which they are put back bit for bit. Only the
// other shapes (planes, invalid shapes, the huge shapes beside the tree) are set aside whole.
struct SetAside {
  std::vector<std::pair<std::uint32_t, Shape>> others;  // (id, shape), in id order
  std::size_t count = 0;                                // shapes in all
};
// Most planes a scene may set aside (44 bytes each); a scene with more keeps its shapes. Invalid
// spheres (a scene split by transparency holds one for each transparent shape, render_scene.cpp)
// are set aside however many there are: at most the scene's shape count.
constexpr std::size_t kMaxSetAside = 4096;

// Maps [data, data + bytes) writable now, on up to `threads` threads, each taking whole 2 MiB
// pieces (aligned as huge pages are): the kernel zeroes fresh pages on the thread that faults them,
// and a serial first write of a large array spent half its time there. Only where it pays (large
// ranges, several threads) and where MADV_POPULATE_WRITE exists (Linux 5.14); otherwise the first
// write faults the pages in as before. Writes no object: the bytes read as zero either way.
void populate_in_parallel(const void* data, std::size_t bytes, util::ThreadPool& pool) {
#if defined(__linux__) && defined(MADV_POPULATE_WRITE)
  constexpr std::uintptr_t kPiece = std::uintptr_t(2) << 20;
  if (pool.size() <= 1 || data == nullptr || bytes < 4 * kPiece) return;
  const auto begin = reinterpret_cast<std::uintptr_t>(data);
  const std::uintptr_t first = (begin + kPiece - 1) & ~(kPiece - 1);
  const std::uintptr_t last = (begin + bytes) & ~(kPiece - 1);
  if (last <= first) return;
  pool.parallel_for((last - first) / kPiece, pool.size(), [&](std::size_t i) {
    madvise(reinterpret_cast<void*>(first + i * kPiece), kPiece, MADV_POPULATE_WRITE);  // a hint: errors ignored
  });
#else
  (void)data;
  (void)bytes;
  (void)pool;
#endif
}

// The tree hash (BuildStats::tree_hash): FNV-1a steps over 32-bit words, in pieces of kHashPiece
// nodes and kHashPiece prim ids (a constant: the same pieces whatever the thread count), each
// piece's hash folded in order into the tree's. Within a piece each of a node's nine words has a
// chain of its own (and the ids eight chains, id i in chain i % 8): one chain over every word was
// bound by the multiply's latency (9.5-10 ms of 1M spheres, the critical path of a 2-thread build
// after its split), independent chains by its throughput, and the pieces run in parallel. Still a
// pure function of the tree, and as sensitive: each step is a bijection of its chain's value, so a
// word that differs changes its chain's value, and then its piece's and the tree's hash but for a
// 64-bit collision.
constexpr std::size_t kHashPiece = kChunk;
constexpr std::uint64_t kFnvBasis = 0xcbf29ce484222325ull;
inline std::uint64_t fnv_step(std::uint64_t hash, std::uint32_t word) { return (hash ^ word) * 0x100000001b3ull; }
inline std::uint64_t fnv_fold(std::uint64_t hash, std::uint64_t value) {
  return fnv_step(fnv_step(hash, std::uint32_t(value)), std::uint32_t(value >> 32));
}

template <typename Node>
std::uint64_t hash_nodes(const Node* nodes, std::size_t count) {
  std::uint64_t chain[9];
  for (std::uint64_t& c : chain) c = kFnvBasis;
  for (std::size_t i = 0; i < count; ++i) {
    const Node& n = nodes[i];
    for (int k = 0; k < 6; ++k) chain[k] = fnv_step(chain[k], std::bit_cast<std::uint32_t>(n.bounds[k]));
    chain[6] = fnv_step(chain[6], n.offset);
    chain[7] = fnv_step(chain[7], n.count);
    chain[8] = fnv_step(chain[8], n.axis);
  }
  std::uint64_t hash = kFnvBasis;
  for (const std::uint64_t c : chain) hash = fnv_fold(hash, c);
  return hash;
}

inline std::uint64_t hash_ids(const std::uint32_t* ids, std::size_t count) {
  std::uint64_t chain[8];
  for (std::uint64_t& c : chain) c = kFnvBasis;
  std::size_t i = 0;
  for (; i + 8 <= count; i += 8) {
    for (int k = 0; k < 8; ++k) chain[k] = fnv_step(chain[k], ids[i + k]);
  }
  for (; i < count; ++i) chain[i % 8] = fnv_step(chain[i % 8], ids[i]);
  std::uint64_t hash = kFnvBasis;
  for (const std::uint64_t c : chain) hash = fnv_fold(hash, c);
  return hash;
}

// Gives the pages wholly inside [data, data + bytes) back to the kernel (MADV_DONTNEED on private
// memory): they stay mapped, read as zero and count no more in the resident set until written
// again. Returns false, having changed nothing, where it cannot.
bool drop_pages(const void* data, std::size_t bytes) {
#if defined(__linux__) && defined(MADV_DONTNEED)
  const long page_size = sysconf(_SC_PAGESIZE);
  if (data == nullptr || page_size <= 0) return false;
  const auto page = std::uintptr_t(page_size);
  const auto begin = reinterpret_cast<std::uintptr_t>(data);
  const std::uintptr_t first = (begin + page - 1) & ~(page - 1);
  const std::uintptr_t last = (begin + bytes) & ~(page - 1);
  return last <= first || madvise(reinterpret_cast<void*>(first), last - first, MADV_DONTNEED) == 0;
#else
  (void)data;
  (void)bytes;
  return false;
#endif
}

// The shapes again, into `shapes`: the tree's spheres from `prims` or, once those are freed, from
// the wide tree's sphere blocks, and the others from `a`. `shapes` is either the scene's own array,
// kept at its size with its pages dropped (drop_pages: every element is written again here), or
// empty, and then made anew. The sphere blocks are read in chunks on up to `threads` threads (each
// writes the shapes of its own blocks; the ids are distinct), after the array's pages are mapped
// on all of them (populate_in_parallel). An array made anew runs Shape's constructor on one thread
// first (1M spheres: 6.6 ms of a 2-thread build's 15 ms in put_back, 9.4 ms on one thread).
template <typename Prims>
void put_back(std::vector<Shape>& shapes, SetAside& a, const detail::WideBvh& wide, const Prims& prims,
              util::ThreadPool& pool) {
  if (shapes.size() == a.count) {
    util::advise_huge_pages_for(shapes);  // the dropped pages fault in again (util/huge_pages.h)
    populate_in_parallel(shapes.data(), shapes.size() * sizeof(Shape), pool);
  } else {
    std::vector<Shape>().swap(shapes);
    shapes.reserve(a.count);
    util::advise_huge_pages_for(shapes);  // first touches are costly page faults (util/huge_pages.h)
    populate_in_parallel(shapes.data(), shapes.capacity() * sizeof(Shape), pool);
    shapes.resize(a.count);
  }
  // Every byte of each sphere's Shape is written: the same shape whether the array was kept or
  // made anew. Each is the bytes of a default Shape (`proto`: its type, padding and the zeros after
  // the sphere) with the centre and radius in their place, stored in three stores from registers.
  // Assigning a Shape made on the stack cost a stalled load a sphere (1M spheres, put_back on one
  // thread 16.2 -> 10.1 ms of CPU).
#if defined(__SSE2__)
  static_assert(sizeof(Shape) == 40 && offsetof(Shape, sphere) == 4 && sizeof(SphereShape) == 16,
                "a sphere's Shape: 4 bytes of type, centre and radius, 20 bytes after them");
  alignas(16) std::uint8_t proto[48] = {};
  {
    const Shape s;
    std::memcpy(proto, &s, sizeof(Shape));
  }
  const __m128i head =
      _mm_and_si128(_mm_load_si128(reinterpret_cast<const __m128i*>(proto)), _mm_setr_epi32(-1, 0, 0, 0));
  const __m128i mid =
      _mm_and_si128(_mm_load_si128(reinterpret_cast<const __m128i*>(proto + 16)), _mm_setr_epi32(0, -1, -1, -1));
  const __m128i tail = _mm_loadl_epi64(reinterpret_cast<const __m128i*>(proto + 32));
  const auto put = [&shapes, head, mid, tail](std::uint32_t id, float x, float y, float z, float r) {
    auto* const to = reinterpret_cast<std::uint8_t*>(shapes.data() + id);
    const __m128i sphere = _mm_castps_si128(_mm_setr_ps(x, y, z, r));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(to), _mm_or_si128(head, _mm_slli_si128(sphere, 4)));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(to + 16), _mm_or_si128(mid, _mm_srli_si128(sphere, 12)));
    _mm_storel_epi64(reinterpret_cast<__m128i*>(to + 32), tail);
  };
#else
  const auto put = [&shapes](std::uint32_t id, float x, float y, float z, float r) {
    Shape s;
    s.sphere = {{x, y, z}, r};
    shapes[id] = s;
  };
#endif
  if (!prims.empty()) {
    for (const auto& p : prims) put(p.id, p.data[0], p.data[1], p.data[2], p.data[3]);
  } else {
    constexpr std::size_t kBlocksPerChunk = kChunk / detail::kWidth;
    const std::size_t blocks = wide.spheres.size();
    pool.parallel_for((blocks + kBlocksPerChunk - 1) / kBlocksPerChunk, blocks >= kBlocksPerChunk ? pool.size() : 1,
                      [&](std::size_t c) {
                        const std::size_t end = std::min(blocks, (c + 1) * kBlocksPerChunk);
                        for (std::size_t i = c * kBlocksPerChunk; i < end; ++i) {
                          const detail::SphereBlock& b = wide.spheres[i];
                          for (int lane = 0; lane < detail::kWidth; ++lane) {
                            if (b.id[lane] != detail::kEmptyChild)
                              put(b.id[lane], b.cx[lane], b.cy[lane], b.cz[lane], b.r[lane]);
                          }
                        }
                      });
  }
  for (const auto& [id, shape] : a.others) shapes[id] = shape;
  a = SetAside();
}

}  // namespace

Geometry Geometry::build(std::vector<Shape> shapes, Isa isa, unsigned threads) {
  static_assert(sizeof(Node) == 32 && sizeof(Prim) == 32, "two nodes / prims per 64-byte cache line");
  const auto start = std::chrono::steady_clock::now();
  if (threads == 0) threads = util::usable_cpus();
  threads = std::min(threads, kMaxBuildThreads);
  Geometry g;
  g.shapes_ = std::move(shapes);

  // A large scene of spheres (and a few planes) that gets a wide tree holds no Shape array's pages
  // while its tree is built and collapsed (SetAside): only bare spheres (16 bytes where a Shape takes
  // 40) until the prims are made, then the prims and the wide tree's blocks hold them. They are
  // set aside before the build prims (40 bytes) are made from them, so that the shapes and the
  // build prims are never alive together. Enough spheres that, even after the huge ones leave
  // the tree (kMaxOutside at most), it is far above kMinWidePrims: it gets a wide tree. Whether
  // a scene is set aside changes its memory, not its tree or its shapes.
  const std::size_t n = g.shapes_.size();
  const unsigned shape_threads = n >= kParallelGrain ? threads : 1;
  // The build's threads, started once for all its parallel passes (a scene too small to split
  // across threads starts none).
  util::ThreadPool pool(shape_threads);
  const bool may_set_aside = isa != Isa::kScalar && n >= std::max<std::size_t>(kMinWidePrims, kParallelGrain);
  std::vector<detail::AsideSphere> spheres;  // aside: each shape's sphere, by id, until the collapse
  if (may_set_aside) {
    spheres.reserve(n);
    util::advise_huge_pages_for(spheres);  // first touches are costly page faults (util/huge_pages.h)
    spheres.resize(n);                     // writes nothing (detail::AsideSphere)
  }

  // What each shape is (0 invalid, 1 plane, 2 bounded), in chunks (in parallel for large scenes);
  // where the scene may be set aside, the same pass copies the spheres out (on the thread that
  // reads them; only spheres, so a mesh touches none of that array, and only the bounded ones
  // are read back) and counts the shapes that forbid it: more than kMaxSetAside planes, or any
  // shape that is neither a sphere nor a plane. The copies are dropped if it may not.
  struct ChunkCounts {
    std::size_t bounded = 0, planes = 0, others = 0, triangles = 0;  // triangles: valid ones
  };
  std::vector<std::uint8_t> kind(n);
  std::vector<ChunkCounts> counts(chunks_of(n));
  pool.parallel_for(chunks_of(n), shape_threads, [&](std::size_t c) {
    const std::size_t end = std::min(n, (c + 1) * kChunk);
    ChunkCounts k;
    for (std::size_t id = c * kChunk; id < end; ++id) {
      const Shape& s = g.shapes_[id];
      const bool valid = s.type == ShapeType::kSphere ? sphere_is_valid(s.sphere) : detail::shape_is_valid(s);
      const std::uint8_t what = !valid ? 0 : s.type == ShapeType::kPlane ? 1 : 2;
      kind[id] = what;
      k.bounded += what == 2;
      k.planes += s.type == ShapeType::kPlane;
      k.others += s.type != ShapeType::kPlane && s.type != ShapeType::kSphere;
      k.triangles += what != 0 && s.type == ShapeType::kTriangle;
      if (may_set_aside && s.type == ShapeType::kSphere) spheres[id].sphere = s.sphere;
    }
    counts[c] = k;
  });
  ChunkCounts all_counts;
  for (const ChunkCounts& k : counts) {
    all_counts.bounded += k.bounded;
    all_counts.planes += k.planes;
    all_counts.others += k.others;
    all_counts.triangles += k.triangles;
  }
  const std::size_t bounded = all_counts.bounded;
  const bool aside = may_set_aside && bounded >= std::max<std::size_t>(kMinWidePrims, kParallelGrain) &&
                     all_counts.others == 0 && all_counts.planes <= kMaxSetAside;
  SetAside set;
  if (aside) {
    set.count = n;
    // Planes and invalid spheres, from the chunks that hold any (a serial pass over the others).
    for (std::size_t c = 0; c < counts.size(); ++c) {
      const std::size_t end = std::min(n, (c + 1) * kChunk);
      if (counts[c].bounded == end - c * kChunk) continue;
      for (std::size_t id = c * kChunk; id < end; ++id) {
        if (kind[id] != 2) set.others.push_back({std::uint32_t(id), g.shapes_[id]});
      }
    }
    // The array is kept at its size with its pages given back, rather than freed and made anew in
    // put_back, whose serial run of Shape's constructor was its largest part; if the pages cannot
    // be given back, it is freed.
    // Its capacity too: a loaded scene's array may have room past its shapes whose pages the loader
    // mapped ahead of its writes.
    if (!drop_pages(g.shapes_.data(), g.shapes_.capacity() * sizeof(Shape))) std::vector<Shape>().swap(g.shapes_);
  } else {
    std::vector<detail::AsideSphere>().swap(spheres);
  }
  // The bounds of a bounded shape (kind 2, so valid): shape_bounds, or for a set-aside sphere
  // sphere_bounds, which is what shape_bounds gives a valid sphere.
  const auto bounds_of = [&](std::size_t id) {
    if (!aside) return shape_bounds(g.shapes_[id]);
    return sphere_bounds(spheres[id].sphere);
  };

  // Bounds of every bounded shape, in chunks, and their union per chunk, each written straight to
  // its place among the bounded shapes in id order: chunk c's first place is the number of bounded
  // shapes in the chunks before it (the kind pass counted them). Moving them down past the planes
  // and invalid shapes afterwards was a serial pass over all of them (a scene whose first object
  // is its ground plane moves every one).
  std::vector<BuildPrim> refs;
  refs.reserve(bounded);
  util::advise_huge_pages_for(refs);  // first touches are costly page faults (util/huge_pages.h)
  refs.resize(bounded);               // writes nothing (BuildPrim)
  // Also a bound on each chunk's largest surface area, so that the search for huge shapes below
  // reads only the chunks that may hold one (a second pass over all the prims took 6-7 ms of 1M
  // spheres on one thread, and none of them is huge), and each chunk's bounds and centroid bounds
  // as range_bounds gathers them (the same minima and maxima in prim order).
  std::vector<RangeBounds> chunk_bounds(chunks_of(n));
  std::vector<double> chunk_area(chunks_of(n));
  std::vector<std::size_t> first(chunks_of(n) + 1, 0);  // chunk c's prims: refs[first[c], first[c + 1])
  for (std::size_t c = 0; c < counts.size(); ++c) first[c + 1] = first[c] + counts[c].bounded;
  pool.parallel_for(chunks_of(n), shape_threads, [&](std::size_t c) {
    const std::size_t end = std::min(n, (c + 1) * kChunk);
    std::size_t at = first[c];
    BoxAccumulator bounds, centroids;
    float extent[3] = {0.0f, 0.0f, 0.0f};  // the largest of each axis
    for (std::size_t id = c * kChunk; id < end; ++id) {
      if (kind[id] != 2) continue;
      // Made in place from its floats: assigning a prim made of `b` went through a copy on the
      // stack whose wide loads waited on the narrow stores that had just written it.
      const Bounds3f b = bounds_of(id);
      const Vec3f c = b.centroid();
      new (&refs[at++]) BuildPrim(b.lo.x, b.lo.y, b.lo.z, b.hi.x, b.hi.y, b.hi.z, c.x, c.y, c.z, std::uint32_t(id));
      bounds.extend(b.lo.x, b.lo.y, b.lo.z, b.hi.x, b.hi.y, b.hi.z);
      centroids.extend(c.x, c.y, c.z, c.x, c.y, c.z);
      for (int k = 0; k < 3; ++k) extent[k] = std::max(extent[k], b.hi[k] - b.lo[k]);
    }
    chunk_bounds[c] = {bounds.bounds(), centroids.bounds()};
    // At least the largest area() of the chunk: the area of its largest extents, each widened
    // past its float rounding (2^-24 relative, 2^-150 below the normal range), the result 1e-5
    // above the double rounding of area()'s operations. Infinite or NaN when an extent overflows.
    const auto wide = [](float e) { return double(e) * (1.0 + 0x1p-20) + 0x1p-149; };
    const double ex = wide(extent[0]), ey = wide(extent[1]), ez = wide(extent[2]);
    chunk_area[c] = 2.0 * (ex * ey + ey * ez + ez * ex) * (1.0 + 1e-5);
  });
  g.has_triangles_ = all_counts.triangles > 0;
  for (std::size_t c = 0; c < counts.size(); ++c) {
    if (counts[c].planes == 0) continue;  // the chunks without planes are not read again
    const std::size_t end = std::min(n, (c + 1) * kChunk);
    for (std::size_t id = c * kChunk; id < end; ++id) {
      if (kind[id] == 1) g.outside_.push_back(std::uint32_t(id));
    }
  }
  std::vector<std::uint8_t>().swap(kind);

  // Huge shapes (a floor or the walls of a room as boxes or big triangles) overlap every SAH
  // split and make the tree worse for everything else; like planes, they are tested one by one
  // beside it. Huge: bounds with more than a quarter of the surface area of all shapes' bounds.
  // At most kMaxOutside are taken out, the largest first, so the linear part stays short.
  if (refs.size() > 1) {
    // The union of the chunks' unions in chunk order: the bounds in id order, as one pass over
    // the prims would extend them (a minimum keeps the value it holds on a tie, so the same bits).
    Bounds3f all;
    for (const RangeBounds& cb : chunk_bounds) all.extend(cb.bounds);
    const double limit = kHugeFraction * area(all);
    // The shapes above the limit in index order (each chunk's in its own list, joined in order),
    // from the chunks whose largest area may be above it.
    std::vector<std::vector<std::pair<double, std::uint32_t>>> huge_in(chunks_of(n));
    pool.parallel_for(chunks_of(n), shape_threads, [&](std::size_t c) {
      if (chunk_area[c] <= limit) return;  // not for NaN
      for (std::size_t i = first[c]; i < first[c + 1]; ++i) {
        const double a = area(refs[i].bounds);
        if (a > limit) huge_in[c].push_back({a, std::uint32_t(i)});
      }
    });
    std::vector<std::pair<double, std::uint32_t>> huge;  // (area, index into refs)
    for (const auto& part : huge_in) huge.insert(huge.end(), part.begin(), part.end());
    std::sort(huge.begin(), huge.end(), [](const auto& x, const auto& y) { return x.first > y.first; });
    if (huge.size() > kMaxOutside) huge.resize(kMaxOutside);
    if (!huge.empty() && huge.size() < refs.size()) {
      std::vector<bool> out(refs.size(), false);
      for (const auto& h : huge) {
        out[h.second] = true;
        const std::uint32_t id = refs[h.second].id;
        g.outside_.push_back(id);
        if (aside) {  // beside the tree, so not in its blocks: set aside whole
          Shape s;
          s.sphere = spheres[id].sphere;
          set.others.push_back({id, s});
        }
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
  std::sort(set.others.begin(), set.others.end(), [](const auto& a, const auto& b) { return a.first < b.first; });

  // The root's range_bounds_chunked without a pass over the prims (1M spheres: 40 MB read; on 2
  // threads the top levels' split 1.7 ms faster, median of 30 pairs, 21 agreeing): the union of the
  // chunks' bounds in chunk order. Both keep the first of equal values (+0 and -0) in prim order
  // however the prims are cut into chunks, so the same bits even where planes or invalid shapes
  // between the prims move the shape chunks against the prim chunks; not once huge shapes have
  // left the prims.
  std::optional<RangeBounds> root_bounds;
  if (refs.size() == bounded) {
    root_bounds.emplace();
    for (const RangeBounds& cb : chunk_bounds) {
      root_bounds->bounds.extend(cb.bounds);
      root_bounds->centroids.extend(cb.centroids);
    }
  }
  const RangeBounds* const root = root_bounds ? &*root_bounds : nullptr;

  std::uint32_t leaves = 0;
  std::uint32_t max_depth = 0;
  // Once the tree is built only the ids of the build prims are left to use: those are kept (4
  // bytes a prim) and the rest (40) freed before the nodes are stitched and the prims (32) made,
  // which lowers the build's peak. Each range's ids are copied out by the thread that built it,
  // as it finishes (the prims are still in its cache), instead of in a serial pass over all the
  // prims afterwards (3 ms of 1M spheres on 2 threads while the other thread waited).
  std::vector<std::uint32_t> order(refs.size());
  // On several threads the tree hash's pieces run in one pool loop with the making of the prims
  // and, where the pool has a second thread to do them, the subtrees' copies into place (`stitch`,
  // in node order; a piece of the nodes waits for the copies it reads).
  const bool hash_beside = threads > 1 && refs.size() >= kParallelGrain;
  const bool stitch_beside = hash_beside && pool.size() > 1;
  std::deque<Subtree<Node>> subtrees;
  std::vector<Stitch> stitch;
  if (!refs.empty() && threads == 1) {
    // One thread: no subtrees to stitch, the nodes go straight into place (at most 2 n - 1 of
    // them: the reserved pages that are not used are never touched).
    const Splitter splitter(refs, isa, pool);
    g.nodes_.reserve(2 * refs.size() - 1);
    util::advise_huge_pages_for(g.nodes_);
    {
      Scratch scratch(std::min<std::size_t>(refs.size(), kParallelGrain));
      build_in_place(splitter, 0, std::uint32_t(refs.size()), 0, g.nodes_, scratch, leaves, max_depth, order.data(),
                     root);
    }
    std::vector<BuildPrim>().swap(refs);
  } else if (!refs.empty()) {
    const Splitter splitter(refs, isa, pool);
    std::deque<TopNode<Node>> top;
    std::vector<TopNode<Node>*> pending;
    split_top(splitter, 0, std::uint32_t(refs.size()), 0, threads, refs.size() / threads, top, pending, root);
    split_pending(splitter, pool, threads, top, subtrees, std::move(pending), order.data());
    // The subtrees' ids are copied; a top node that is a leaf (not for valid spheres) has its own.
    for (const TopNode<Node>& t : top) {
      if (t.subtree < 0 && t.node.count > 0) splitter.copy_ids(t.begin, t.end, order.data());
    }
    std::vector<BuildPrim>().swap(refs);
    std::size_t total = 0;
    for (const TopNode<Node>& t : top) total += t.subtree < 0;
    for (const auto& t : subtrees) total += t.nodes.size();
    g.nodes_.reserve(total);
    util::advise_huge_pages_for(g.nodes_);
    g.nodes_.resize(total);  // writes nothing (Node): copy_subtrees' threads touch the pages first
    {
      std::vector<std::uint32_t> subtree_at(subtrees.size());
      std::uint32_t next = 0;
      place(0, top, subtrees, subtree_at, g.nodes_.data(), next);
      assert(next == total);
      if (stitch_beside) {
        for (std::size_t k = 0; k < subtrees.size(); ++k)
          stitch.push_back({subtree_at[k], std::uint32_t(k), std::uint32_t(subtrees[k].nodes.size())});
        std::sort(stitch.begin(), stitch.end(), [](const Stitch& a, const Stitch& b) { return a.at < b.at; });
      } else {
        copy_subtrees(subtrees, subtree_at, g.nodes_.data(), pool, threads);
      }
    }
    for (const TopNode<Node>& t : top) {
      if (t.subtree >= 0) continue;
      max_depth = std::max(max_depth, t.depth);
      if (t.node.count > 0) ++leaves;
    }
    for (const auto& t : subtrees) {
      leaves += t.leaves;
      max_depth = std::max(max_depth, t.max_depth);
    }
  }
  // A set-aside scene makes no prims (32 bytes a sphere, written and read once): the collapse
  // reads each sphere by id from `spheres` in the order of `order`, which the prims were made from
  // (the same random reads, now in the collapse). 1M spheres, the first build of separate
  // processes, ABBA: 1 thread 1.056 (8 of 8 pairs; base against base 1.031, 4 of 8); in
  // dtraced-bench-scale's repeated builds, which inherit the heap the build before left, 1 thread
  // 0.91 and 2 threads 1.08-1.12. Such a scene always gets a collapsed tree: it has 2^15 bounded
  // shapes or more, of which at most kMaxOutside leave the tree. Should its wide tree come out
  // flat, the prims are made after it (a guard: with leaves of at most 4 prims it has more than
  // one node; 33,000 coinciding spheres, which the splits cannot separate, give 1,305).
  static_assert(kParallelGrain >= kMinWidePrims + kMaxOutside, "a set-aside scene's tree is collapsed");
  const std::size_t prim_count = order.size();
  const bool prims_later = aside;
  if (!prims_later) {
    g.prims_.reserve(prim_count);
    util::advise_huge_pages_for(g.prims_);
    g.prims_.resize(prim_count);
  }
  // The tree hash's pieces (hash_nodes, hash_ids), folded in order once all are done: node piece k
  // reads nodes [k kHashPiece, (k + 1) kHashPiece), id piece c the ids of prim chunk c.
  static_assert(kHashPiece == kChunk, "make_prims hashes the ids of its own chunk");
  const std::size_t prim_chunks = chunks_of(order.size());
  const std::size_t node_pieces = (g.nodes_.size() + kHashPiece - 1) / kHashPiece;
  std::vector<std::uint64_t> node_hash(node_pieces), id_hash(prim_chunks);
  // stitch[k]'s copy: 0 not taken, 1 taken, 2 in place. Whichever thread takes it first copies it:
  // a node piece's hash too, rather than wait for a thread that has not woken yet.
  std::vector<std::atomic<int>> copied(stitch.size());
  const auto copy_stitch = [&](std::size_t k) {
    int untaken = 0;
    if (!copied[k].compare_exchange_strong(untaken, 1, std::memory_order_relaxed)) return;
    copy_subtree(subtrees[stitch[k].subtree].nodes, stitch[k].at, g.nodes_.data());
    copied[k].store(2, std::memory_order_release);
  };
  const auto hash_node_piece = [&](std::size_t k) {
    const std::size_t from = k * kHashPiece, to = std::min(g.nodes_.size(), from + kHashPiece);
    // The subtrees copied into [from, to) (stitch is in node order) must be in place first.
    auto s = std::partition_point(stitch.begin(), stitch.end(),
                                  [from](const Stitch& t) { return std::size_t(t.at) + t.size <= from; });
    for (; s != stitch.end() && s->at < to; ++s) {
      const auto j = std::size_t(s - stitch.begin());
      copy_stitch(j);
      while (copied[j].load(std::memory_order_acquire) != 2) std::this_thread::yield();
    }
    node_hash[k] = hash_nodes(g.nodes_.data() + from, to - from);
  };
  // Prim i of a set-aside scene: every prim is a sphere (planes and invalid shapes are not in the tree).
  const auto sphere_prim = [&](std::size_t i) {
    const SphereShape& sphere = spheres[order[i]].sphere;
    Prim& p = g.prims_[i];
    p.id = order[i];
    p.type = ShapeType::kSphere;
    p.data[0] = sphere.center.x;
    p.data[1] = sphere.center.y;
    p.data[2] = sphere.center.z;
    p.data[3] = sphere.radius;
    p.data[4] = p.data[5] = 0.0f;
  };
  const auto make_prims = [&](std::size_t c) {
    const std::size_t end = std::min(order.size(), (c + 1) * kChunk);
    for (std::size_t i = c * kChunk; !prims_later && i < end; ++i) {
      Prim& p = g.prims_[i];
      p.id = order[i];
      const Shape& s = g.shapes_[order[i]];
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
    }
    id_hash[c] = hash_ids(order.data() + c * kChunk, end - c * kChunk);  // order[i] is prims_[i].id
  };
  if (hash_beside) {
    // The subtrees' copies into place first (in node order), then the prims with their ids' hashes,
    // then the nodes' hashes, each of which waits for the copies it reads (taken by earlier items).
    pool.parallel_for(stitch.size() + prim_chunks + node_pieces, threads, [&](std::size_t c) {
      if (c < stitch.size()) {
        copy_stitch(c);
      } else if (c < stitch.size() + prim_chunks) {
        make_prims(c - stitch.size());
      } else {
        hash_node_piece(c - stitch.size() - prim_chunks);
      }
    });
  } else {
    for (std::size_t c = 0; c < prim_chunks; ++c) make_prims(c);
    for (std::size_t k = 0; k < node_pieces; ++k) hash_node_piece(k);
  }
  std::uint64_t hash = fnv_fold(fnv_fold(kFnvBasis, g.nodes_.size()), order.size());
  for (const std::uint64_t h : node_hash) hash = fnv_fold(hash, h);
  for (const std::uint64_t h : id_hash) hash = fnv_fold(hash, h);
  // Until put_back nothing reads shapes_: the collapse reads prims, or the set-aside spheres (and
  // shapes only for triangles, which a scene set aside has none of).
  const auto drop_aside = [&] {
    std::vector<std::uint32_t>().swap(order);
    std::vector<detail::AsideSphere>().swap(spheres);
  };
  if (!prims_later) drop_aside();

  g.stats_.tree_hash = hash;
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
  if (isa != Isa::kScalar && prim_count > 0) {
    const auto wide_start = std::chrono::steady_clock::now();
    if (prim_count >= kMinWidePrims) {
      // A set-aside scene's prims are all spheres (planes and invalid shapes are not in the tree).
      const detail::AsideSpheres aside_spheres{spheres.data(), order.data(), prim_count};
      g.wide_ = detail::collapse_to_wide(g, aside, /* spheres_only = */ aside, pool, threads,
                                         prims_later ? &aside_spheres : nullptr);
      if (prims_later && (g.wide_.empty() || detail::is_flat(g.wide_))) {
        // The walks that are not wide read the prims (the collapse then kept the ids' pages).
        g.prims_.resize(prim_count);
        for (std::size_t i = 0; i < prim_count; ++i) sphere_prim(i);
      }
      if (prims_later) drop_aside();
      // Every query now walks the wide tree (intersect, occluded and the packets take the wide
      // path whenever it is not flat): the binary nodes and prims, 32 bytes a prim and as much
      // again a node, are never read again.
      if (!g.wide_.empty() && !detail::is_flat(g.wide_)) {
        std::vector<Node>().swap(g.nodes_);
        std::vector<Prim>().swap(g.prims_);
      }
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
    if (aside) put_back(g.shapes_, set, g.wide_, g.prims_, pool);  // after the nodes and prims are freed
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
    bool finished = false;
    const bool found = outside_hit(r, ray.t_min, best_t, best_id);
    const bool tree = wide_kernels().intersect1(wide_, r, ray.t_min, best_t, best_id, hit, finished);
    if (!found && !tree) return false;
    // A triangle of the tree: the kernel wrote the record (no second test, no load of the shape).
    if (!(tree && finished)) detail::finish_hit(shapes_[best_id], best_id, ray, r, best_t, hit);
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
[[maybe_unused]] bool ray_ok(const Ray& ray) {
  return ray.t_min < ray.t_max && math::is_finite(ray.o) && math::is_finite(ray.d);
}

// The lanes of `valid` whose rays pass ray_ok. With SSE2 four lanes at a time and without a
// branch per value: the lane by lane test of 7 values was most of intersect_n's own time on
// whitted10 (the render phase went down by 1.6 %). Each lane's values are loaded one by one where
// the ray is (a wide load of the ray's narrow stores would wait for them). |x| < inf is
// std::isfinite (false for NaN, as is t_min < t_max).
template <int N>
std::uint32_t live_lanes(const Ray* rays, std::uint32_t valid) {
  std::uint32_t live = 0;
#if defined(__SSE2__)
  static_assert(N % 4 == 0);
  const __m128 inf = _mm_set1_ps(detail::kInf), magnitude = _mm_castsi128_ps(_mm_set1_epi32(0x7fffffff));
  for (int g = 0; g < N; g += 4) {
    if ((valid >> g & 0xfu) == 0) continue;
    const Ray &r0 = rays[g], &r1 = rays[g + 1], &r2 = rays[g + 2], &r3 = rays[g + 3];
    const auto finite = [&](__m128 v) { return _mm_cmplt_ps(_mm_and_ps(v, magnitude), inf); };
    __m128 ok = _mm_cmplt_ps(_mm_setr_ps(r0.t_min, r1.t_min, r2.t_min, r3.t_min),
                             _mm_setr_ps(r0.t_max, r1.t_max, r2.t_max, r3.t_max));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.o.x, r1.o.x, r2.o.x, r3.o.x)));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.o.y, r1.o.y, r2.o.y, r3.o.y)));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.o.z, r1.o.z, r2.o.z, r3.o.z)));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.d.x, r1.d.x, r2.d.x, r3.d.x)));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.d.y, r1.d.y, r2.d.y, r3.d.y)));
    ok = _mm_and_ps(ok, finite(_mm_setr_ps(r0.d.z, r1.d.z, r2.d.z, r3.d.z)));
    live |= std::uint32_t(_mm_movemask_ps(ok)) << g;
  }
  live &= valid;
#else
  for (int i = 0; i < N; ++i) {
    if ((valid >> i & 1u) && ray_ok(rays[i])) live |= 1u << i;
  }
#endif
  return live;
}

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

// intersect8 and intersect16: N lanes through the kernels of that width.
template <int N>
std::uint32_t Geometry::intersect_n(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  const std::uint32_t live = live_lanes<N>(rays, valid);
  if (live == 0) return 0;
  if (wide_.empty()) {
    std::uint32_t found = 0;
    for (int i = 0; i < N; ++i) {
      if ((live >> i & 1u) && intersect(rays[i], hits[i])) found |= 1u << i;
    }
    return found;
  }
  float best_t[N];
  std::uint32_t best_id[N];
  std::uint32_t found = 0;
  const Outside outside = outside_kind(shapes_, outside_, wide_);
  for (int i = 0; i < N; ++i) {
    best_t[i] = rays[i].t_max;
    best_id[i] = 0;
  }
  if (outside == Outside::kPlanes) {
    found = outside_planes<N>(rays, live, best_t, best_id);
  } else if (outside == Outside::kAny) {
    for (int i = 0; i < N; ++i) {
      if ((live >> i & 1u) &&
          outside_hit(detail::precompute(rays[i], has_triangles_), rays[i].t_min, best_t[i], best_id[i])) {
        found |= 1u << i;
      }
    }
  }
  std::uint32_t finished = 0;
  const std::uint32_t tree = (N == kPacketSize ? wide_kernels().intersect8 : wide_kernels().intersect16)(
      wide_, rays, live, best_t, best_id, hits, finished);
  found |= tree;
  // The tree's triangle hits (and sphere hits of packet tests) come finished from the kernel.
  const std::uint32_t rest = found & ~(tree & finished);
  // Sphere hits are finished together (their square roots and divisions overlap), the rest one
  // by one.
  const Shape* sph_shape[N];
  std::uint32_t sph_id[N];
  const Ray* sph_ray[N];
  float sph_t[N];
  Hit* sph_hit[N];
  int spheres = 0;
  for (int i = 0; i < N; ++i) {
    if (rest >> i & 1u) {
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
  // finish_sphere_hits takes up to kPacketSize lanes at a time.
  for (int k = 0; k < spheres; k += kPacketSize) {
    detail::finish_sphere_hits(sph_shape + k, sph_id + k, sph_ray + k, sph_t + k, sph_hit + k,
                               std::min(kPacketSize, spheres - k));
  }
  return found;
}

template <int N>
std::uint32_t Geometry::occluded_n(const Ray* rays, std::uint32_t valid) const {
  const std::uint32_t live = live_lanes<N>(rays, valid);
  if (live == 0) return 0;
  if (wide_.empty()) {
    std::uint32_t blocked = 0;
    for (int i = 0; i < N; ++i) {
      if ((live >> i & 1u) && occluded(rays[i])) blocked |= 1u << i;
    }
    return blocked;
  }
  std::uint32_t blocked = 0;
  const Outside outside = outside_kind(shapes_, outside_, wide_);
  if (outside == Outside::kPlanes) {
    float t[N];
    std::uint32_t id[N];
    for (int i = 0; i < N; ++i) {
      t[i] = rays[i].t_max;
      id[i] = 0;
    }
    blocked = outside_planes<N>(rays, live, t, id);
  } else if (outside == Outside::kAny) {
    for (int i = 0; i < N; ++i) {
      float t = rays[i].t_max;
      std::uint32_t id = 0;
      if ((live >> i & 1u) && outside_hit(detail::precompute(rays[i], has_triangles_), rays[i].t_min, t, id)) {
        blocked |= 1u << i;
      }
    }
  }
  const std::uint32_t rest = live & ~blocked;
  if (rest != 0)
    blocked |= (N == kPacketSize ? wide_kernels().occluded8 : wide_kernels().occluded16)(wide_, rays, rest);
  return blocked;
}

std::uint32_t Geometry::intersect8(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  return intersect_n<kPacketSize>(rays, valid, hits);
}
std::uint32_t Geometry::intersect16(const Ray* rays, std::uint32_t valid, Hit* hits) const {
  return intersect_n<kPacketSize16>(rays, valid, hits);
}
std::uint32_t Geometry::occluded8(const Ray* rays, std::uint32_t valid) const {
  return occluded_n<kPacketSize>(rays, valid);
}
std::uint32_t Geometry::occluded16(const Ray* rays, std::uint32_t valid) const {
  return occluded_n<kPacketSize16>(rays, valid);
}

}  // namespace dtraced::accel
