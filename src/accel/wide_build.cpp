// dtraced::accel: collapsing the binary BVH into the 8-wide SoA tree of wide_bvh.h.
//
// Each wide node takes a binary node's two children and keeps opening the interior child with
// the largest surface area until it has eight (Wald et al., "Getting rid of packets", 2008; the
// usual collapse of Embree and tinybvh). The binary tree's SAH decisions are kept; only the
// layout changes, so both trees hold exactly the same prims in their leaves.
#if defined(__linux__)
#include <sys/mman.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <cassert>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <vector>

#include "accel/geometry.h"
#include "accel/kernels.h"
#include "util/huge_pages.h"

namespace dtraced::accel::detail {

namespace {

constexpr float kNaNf = std::numeric_limits<float>::quiet_NaN();

double node_area(const float* b) {
  const double ex = double(b[3]) - b[0], ey = double(b[4]) - b[1], ez = double(b[5]) - b[2];
  return 2.0 * (ex * ey + ey * ez + ez * ex);
}

SphereBlock empty_sphere_block() {
  SphereBlock b;
  for (int i = 0; i < kWidth; ++i) {
    b.cx[i] = b.cy[i] = b.cz[i] = b.r[i] = kNaNf;
    b.id[i] = kEmptyChild;
  }
  return b;
}

TriangleBlock empty_triangle_block() {
  TriangleBlock b;
  for (auto& vertex : b.v)
    for (auto& axis : vertex)
      for (float& x : axis) x = kNaNf;
  for (std::uint32_t& id : b.id) id = kEmptyChild;
  return b;
}

// Gives back the pages of an array read once, as soon as every element on them has been read
// (madvise MADV_DONTNEED: they read as zeros after, and cost no memory). The array's memory is
// counted in blocks of 2 MiB aligned as a huge page is (util/huge_pages.h: the large arrays are
// advised to use them), so that a block goes back whole: giving back part of a huge page splits
// it, which made the collapse of 1M spheres a quarter slower with 1 MiB regions of elements.
// Does nothing where `on` is false, the array is small, or madvise is missing.
class ReadOnce {
 public:
  ReadOnce(const void* data, std::size_t count, std::size_t element_bytes, bool on)
      : begin_(reinterpret_cast<std::uintptr_t>(data)), element_bytes_(element_bytes) {
#if defined(__linux__) && defined(MADV_DONTNEED)
    if (on && count * element_bytes >= kMinBytes) {
      end_ = begin_ + count * element_bytes;
      base_ = begin_ & ~(kBlock - 1);
      left_.resize((end_ - 1 - base_) / kBlock + 1);
      for (std::size_t b = 0; b < left_.size(); ++b) {
        const std::uintptr_t lo = std::max(begin_, base_ + b * kBlock);
        const std::uintptr_t hi = std::min(end_, base_ + (b + 1) * kBlock);
        left_[b] = std::uint32_t(hi - lo);
      }
      page_ = std::uintptr_t(sysconf(_SC_PAGESIZE));
    }
#else
    (void)count;
    (void)on;
#endif
  }

  // Elements [first, first + n) have been read, each once.
  void read(std::size_t first, std::size_t n) {
    if (left_.empty() || n == 0) return;
    std::uintptr_t lo = begin_ + first * element_bytes_;
    const std::uintptr_t hi = lo + n * element_bytes_;
    while (lo < hi) {
      const std::size_t b = (lo - base_) / kBlock;
      const std::uintptr_t here = std::min(hi, base_ + (b + 1) * kBlock) - lo;
      assert(left_[b] >= here);
      left_[b] -= std::uint32_t(here);
      if (left_[b] == 0) release(b);
      lo += here;
    }
  }

 private:
  static constexpr std::uintptr_t kBlock = std::uintptr_t(2) << 20;  // a huge page
  static constexpr std::size_t kMinBytes = std::size_t(1) << 20;     // a set-aside scene has more

  // The pages of block b that hold the array and nothing else.
  void release(std::size_t b) const {
#if defined(__linux__) && defined(MADV_DONTNEED)
    const std::uintptr_t lo = (std::max(begin_, base_ + b * kBlock) + page_ - 1) & ~(page_ - 1);
    const std::uintptr_t hi = std::min(end_, base_ + (b + 1) * kBlock) & ~(page_ - 1);
    if (hi > lo) madvise(reinterpret_cast<void*>(lo), hi - lo, MADV_DONTNEED);  // a hint: errors ignored
#else
    (void)b;
#endif
  }

  std::uintptr_t begin_ = 0, end_ = 0;  // the array's bytes
  std::uintptr_t base_ = 0;             // the start of the block holding begin_
  std::size_t element_bytes_;
  std::uintptr_t page_ = 4096;
  std::vector<std::uint32_t> left_;  // per block, the array's bytes in it not read yet
};

}  // namespace

WideBvh collapse_to_wide(const Geometry& g, bool prims_read_once) {
  WideBvh w;
  const auto& nodes = g.nodes_;
  if (nodes.empty()) return w;
  // A leaf that its child reference describes (tri_leaf_ref: one block of spheres, or triangles
  // only) is never looked up in `leaves`, so it gets no WideLeaf record (20 bytes a leaf: 6 MB
  // of a scene of 1M spheres). Except in a tree of a few binary interior nodes, which may
  // collapse to one wide node: the records then keep telling is_flat that it is no flat layout
  // (a wide node takes at most seven binary interior nodes, so eight make two wide nodes).
  const std::size_t binary_leaves =
      std::size_t(std::count_if(nodes.begin(), nodes.end(), [](const auto& node) { return node.count > 0; }));
  const bool every_record = nodes.size() - binary_leaves < 8;
  // Exact sizes up front: growing these vectors by doubling copied and first-touched every block
  // twice. Leaves and blocks are counted from the binary leaves (a pass over the prims, which
  // are in leaf order); a wide node holds at least two binary interior nodes' children, so the
  // binary interior count bounds the wide count. The records are counted for the leaves whose
  // kind of content cannot be described by their reference (those whose first block lies past
  // what a reference can name, 2^26 blocks in, grow the array).
  {
    std::size_t records = 0, sphere_blocks = 0, triangle_blocks = 0, boxes = 0;
    for (const auto& node : nodes) {
      if (node.count == 0) continue;
      std::size_t ns = 0, nt = 0, nb = 0;
      for (std::uint32_t k = 0; k < node.count; ++k) {
        const ShapeType type = g.prims_[node.offset + k].type;
        ns += type == ShapeType::kSphere;
        nt += type == ShapeType::kTriangle;
        nb += type == ShapeType::kBox;
      }
      const std::size_t sb = (ns + kWidth - 1) / kWidth, tb = (nt + kWidth - 1) / kWidth;
      const bool described = nb == 0 && (sb != 0 ? sb == 1 && tb == 0 : tb != 0 && tb <= kTriLeafMaxBlocks);
      records += every_record || !described;
      sphere_blocks += sb;
      triangle_blocks += tb;
      boxes += nb;
    }
    w.nodes.reserve(nodes.size() - binary_leaves + 1);
    w.leaves.reserve(records);
    w.spheres.reserve(sphere_blocks);
    w.triangles.reserve(triangle_blocks);
    w.boxes.reserve(boxes);
    // First touches are costly page faults (util/huge_pages.h): with 4 KiB pages they took more
    // than half of the collapse of 1M spheres. Only pages that will be filled are advised, or a
    // huge page at the end of an array would hold up to 2 MiB that is never used: the arrays
    // reserved at their exact size whole, the nodes up to the fewest the collapse can make (a
    // wide node takes at most seven binary interior nodes: the first and six it opens).
    util::advise_huge_pages_for(w.leaves);
    util::advise_huge_pages_for(w.spheres);
    util::advise_huge_pages_for(w.triangles);
    util::advise_huge_pages_for(w.boxes);
    util::advise_huge_pages(w.nodes.data(), (nodes.size() - binary_leaves) / 7 * sizeof(WideNode));
  }
  // With prims_read_once nothing reads a prim after the collapse has, so the prims' pages go back
  // as the leaves are made: the prims and the wide tree are then never held whole together (the
  // 1M-sphere scene's build peaked there). Not for a tree that may collapse to one node (is_flat:
  // the build then keeps its prims).
  ReadOnce prims_read(g.prims_.data(), g.prims_.size(), sizeof(g.prims_[0]), prims_read_once && !every_record);

  auto make_leaf = [&](std::uint32_t bin_index) {
    const auto& node = nodes[bin_index];
    WideLeaf leaf;
    leaf.sphere_begin = std::uint32_t(w.spheres.size());
    leaf.triangle_begin = std::uint32_t(w.triangles.size());
    leaf.box_begin = std::uint32_t(w.boxes.size());
    int ns = 0, nt = 0;
    for (std::uint32_t k = 0; k < node.count; ++k) {
      const auto& prim = g.prims_[node.offset + k];
      switch (prim.type) {
        case ShapeType::kSphere: {
          // The prim holds the sphere (centre, radius), and prims are in leaf order: no random
          // access into shapes_.
          if (ns % kWidth == 0) w.spheres.push_back(empty_sphere_block());
          SphereBlock& b = w.spheres.back();
          const int lane = ns++ % kWidth;
          b.cx[lane] = prim.data[0];
          b.cy[lane] = prim.data[1];
          b.cz[lane] = prim.data[2];
          b.r[lane] = prim.data[3];
          b.id[lane] = prim.id;
          break;
        }
        case ShapeType::kTriangle: {
          const Shape& shape = g.shapes_[prim.id];
          w.has_triangles = true;
          if (nt % kWidth == 0) w.triangles.push_back(empty_triangle_block());
          TriangleBlock& b = w.triangles.back();
          const int lane = nt++ % kWidth;
          const Vec3f* v[3] = {&shape.triangle.v0, &shape.triangle.v1, &shape.triangle.v2};
          for (int vert = 0; vert < 3; ++vert)
            for (int axis = 0; axis < 3; ++axis) b.v[vert][axis][lane] = (*v[vert])[axis];
          b.id[lane] = prim.id;
          break;
        }
        default: {
          BoxPrim bp;
          std::copy(prim.data, prim.data + 6, bp.b);
          bp.id = prim.id;
          w.boxes.push_back(bp);
          ++leaf.box_count;
          break;
        }
      }
    }
    prims_read.read(node.offset, node.count);
    leaf.sphere_blocks = std::uint16_t((ns + kWidth - 1) / kWidth);
    leaf.triangle_blocks = std::uint16_t((nt + kWidth - 1) / kWidth);
    const std::uint32_t ref = tri_leaf_ref(leaf);
    if (ref != 0 && !every_record) return ref;
    w.leaves.push_back(leaf);
    if (ref != 0) return ref;
    // Plain leaf indices must stay below kTriLeaf (2^30 leaves: billions of prims).
    if (w.leaves.size() > kTriLeaf) std::abort();
    return kLeafBit | std::uint32_t(w.leaves.size() - 1);
  };

  auto children_of = [&](std::uint32_t bin_index) {
    return std::pair<std::uint32_t, std::uint32_t>{bin_index + 1, nodes[bin_index].offset};
  };

  // Recursion depth is bounded by the binary tree's depth (Geometry::kMaxDepth).
  auto build_node = [&](auto&& self, std::uint32_t bin_index) -> std::uint32_t {
    const std::uint32_t index = std::uint32_t(w.nodes.size());
    w.nodes.emplace_back();
    std::uint32_t slots[kNodeWidth];
    int n = 0;
    if (nodes[bin_index].count > 0) {
      slots[n++] = bin_index;  // a leaf root: one child
    } else {
      auto [a, b] = children_of(bin_index);
      slots[n++] = a;
      slots[n++] = b;
      while (n < kNodeWidth) {
        int open = -1;
        double best = -1.0;
        for (int i = 0; i < n; ++i) {
          if (nodes[slots[i]].count > 0) continue;
          const double area = node_area(nodes[slots[i]].bounds);
          if (area > best) {
            best = area;
            open = i;
          }
        }
        if (open < 0) break;
        auto [c0, c1] = children_of(slots[open]);
        slots[open] = c0;
        slots[n++] = c1;
      }
    }
    std::uint32_t child[kNodeWidth];
    for (int i = 0; i < kNodeWidth; ++i) {
      if (i < n) {
        child[i] = nodes[slots[i]].count > 0 ? make_leaf(slots[i]) : self(self, slots[i]);
      } else {
        child[i] = kEmptyChild;
      }
    }
    WideNode& wn = w.nodes[index];  // re-fetched: recursion may have grown the vector
    for (int i = 0; i < kNodeWidth; ++i) {
      wn.child[i] = child[i];
      for (int axis = 0; axis < 3; ++axis) {
        if (i < n) {
          wn.lo[axis][i] = nodes[slots[i]].bounds[axis];
          wn.hi[axis][i] = nodes[slots[i]].bounds[3 + axis];
        } else {
          wn.lo[axis][i] = std::numeric_limits<float>::infinity();
          wn.hi[axis][i] = -std::numeric_limits<float>::infinity();
        }
      }
    }
    for (std::uint32_t& p : wn.pad) p = 0;
    return index;
  };
  build_node(build_node, 0);
  return w;
}

}  // namespace dtraced::accel::detail
