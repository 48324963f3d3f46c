// dtraced::accel: collapsing the binary BVH into the 8-wide SoA tree of wide_bvh.h.
//
// Which binary interior nodes become wide nodes is chosen by the least SAH cost, the sum of their
// areas, by dynamic programming over the binary tree (Ylitie, Karras and Laine, HPG 2017; Planner
// below). The binary tree's leaves stay the wide tree's leaves (same prims, same blocks), so every
// hit is the same; only which binary nodes become wide nodes changes. The usual greedy collapse
// (each wide node takes a binary node's two children and opens the interior child with the largest
// surface area until it has eight: Wald et al., "Getting rid of packets", 2008) made 108,163 wide
// nodes with 4.1 children each for the 1M-triangle mesh (23,393 full, 41,947 with two; SAH cost of
// the nodes, root area 1: 31.95); the SAH collapse makes 67,543 with 6.0 (28,421 full, 7,877 with
// two; 28.91; Embree's BVH8 has 60,646). One binary building either tree, alternated
// (`dtraced-bench-rays --isa avx512 --threads 1 --runs 5`, load 4-6.3), medians of per-pair ratios
// of the ratios to Embree: mesh (10 pairs) camera x16 1.06, shadow x16 1.03, secondary 1.10, camera
// x8 / scalar 1.09; spheres (8 pairs) 0.97, 1.02, 0.97, 0.99 (noise of +-10 % a pair). The plan
// takes 8 bytes a binary node while the collapse runs (1M spheres: peak 131 -> 134 MiB) and no
// measurable time (collapse 0.071 -> 0.061 s on 1 thread: fewer nodes).
//
// On several threads: the wide nodes near the root are walked first to cut the tree into dozens of
// subtrees per thread (tasks); the threads count what each task makes (nodes, leaf records,
// blocks, boxes), the counts give each task its place in every array, and the threads then fill
// the tasks at those places. Every pass walks the nodes in the one-thread order, so the tree, its
// leaf order and its block order are the same on any number of threads. The passes run on the
// build's threads (util::ThreadPool, started once in Geometry::build): each of the three loops
// started its own threads before (util::parallel_for), and the collapse of 1M spheres on 2
// threads took 24.9 ms against 22.7 on the pool (medians of 15 alternated builds in one process).
#if defined(__linux__)
#include <sys/mman.h>
#include <unistd.h>
#endif

#include <algorithm>
#include <array>
#include <atomic>
#include <cassert>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <memory>
#include <vector>

#include "accel/geometry.h"
#include "accel/kernels.h"
#include "util/huge_pages.h"
#include "util/thread_pool.h"

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
      left_ = std::vector<std::atomic<std::uint32_t>>((end_ - 1 - base_) / kBlock + 1);
      for (std::size_t b = 0; b < left_.size(); ++b) {
        const std::uintptr_t lo = std::max(begin_, base_ + b * kBlock);
        const std::uintptr_t hi = std::min(end_, base_ + (b + 1) * kBlock);
        left_[b].store(std::uint32_t(hi - lo), std::memory_order_relaxed);
      }
      page_ = std::uintptr_t(sysconf(_SC_PAGESIZE));
    }
#else
    (void)count;
    (void)on;
#endif
  }

  // Reads counted off together: a thread that reads runs of elements in order (a task of the
  // collapse, leaf after leaf) counts off each run once, when the next read leaves the run's block
  // or at flush, instead of each read at once. Counting off every leaf (1M spheres: 298k leaves)
  // on the counter of the block the other thread also reads made both threads of the collapse's
  // write pass take about as long as one thread took for all of it. Pages go back as late as the
  // last read of their block, as without it.
  class Batch {
   public:
    explicit Batch(ReadOnce& r) : r_(r) {}
    Batch(const Batch&) = delete;
    Batch& operator=(const Batch&) = delete;
    ~Batch() { flush(); }

    void read(std::size_t first, std::size_t n) {
      if (r_.left_.empty() || n == 0) return;
      if (n_ != 0 && first == first_ + n_ && r_.block_of(first + n - 1) == r_.block_of(first_)) {
        n_ += n;
        return;
      }
      flush();
      first_ = first;
      n_ = n;
    }
    void flush() {
      r_.read(first_, n_);
      n_ = 0;
    }

   private:
    ReadOnce& r_;
    std::size_t first_ = 0, n_ = 0;  // the run not counted off yet
  };

  // Elements [first, first + n) have been read, each once. Threads may call it at once for
  // different elements: the block whose last bytes a thread counts off is the one it gives back.
  void read(std::size_t first, std::size_t n) {
    if (left_.empty() || n == 0) return;
    std::uintptr_t lo = begin_ + first * element_bytes_;
    const std::uintptr_t hi = lo + n * element_bytes_;
    while (lo < hi) {
      const std::size_t b = (lo - base_) / kBlock;
      const std::uintptr_t here = std::min(hi, base_ + (b + 1) * kBlock) - lo;
      const std::uint32_t before = left_[b].fetch_sub(std::uint32_t(here), std::memory_order_acq_rel);
      assert(before >= here);
      if (before == here) release(b);
      lo += here;
    }
  }

 private:
  static constexpr std::uintptr_t kBlock = std::uintptr_t(2) << 20;  // a huge page
  // Smaller arrays are not worth it. A set-aside scene's ids (4 bytes a sphere) reach it from
  // 262,144 spheres on.
  static constexpr std::size_t kMinBytes = std::size_t(1) << 20;

  // The block holding element i's first byte.
  std::size_t block_of(std::size_t i) const { return (begin_ + i * element_bytes_ - base_) / kBlock; }

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
  std::vector<std::atomic<std::uint32_t>> left_;  // per block, the array's bytes in it not read yet
};

// Prims below which the collapse stays on the calling thread.
constexpr std::size_t kParallelPrims = std::size_t(1) << 15;
// A task's fewest binary nodes, and how many tasks each thread gets (about).
constexpr std::size_t kMinTaskNodes = 2048;
constexpr std::size_t kTasksPerThread = 32;

// Where the collapse writes next in each output array; counted from zero, what a subtree takes.
struct Cursor {
  std::size_t node = 0, leaf = 0, sphere = 0, triangle = 0, box = 0;
  Cursor& operator+=(const Cursor& o) {
    node += o.node;
    leaf += o.leaf;
    sphere += o.sphere;
    triangle += o.triangle;
    box += o.box;
    return *this;
  }
};

// A subtree collapsed by one thread: the binary node at its root (which becomes a wide node), the
// room its output takes and where that starts in each array.
// The binary nodes a wide node takes its children from (Collapse::slots_of).
struct NodeSlots {
  std::uint32_t slot[kNodeWidth];
  int n;
};

struct Task {
  std::uint32_t bin = 0;
  Cursor size;                   // counted from zero
  Cursor at, end;                // in the arrays
  std::vector<NodeSlots> slots;  // its wide nodes' slots, in order, kept from the count for the write
};

// kPlan: finds the tasks below the top; kCount: moves the cursor as a write would, writing
// nothing; kWrite: writes at the cursor into arrays already sized.
enum class Pass { kPlan, kCount, kWrite };

// The SAH collapse (Ylitie, Karras and Laine, "Efficient incoherent ray traversal on GPUs through
// compressed wide BVHs", HPG 2017, without their leaf merging: the binary leaves stay as they are).
// Every binary leaf is a slot of some wide node whatever the collapse, so the collapse's SAH cost
// is the sum of the areas of the binary interior nodes that become wide nodes (the root always
// does). For binary node n and j = 1..8, g(n, j) is the least cost of covering n's subtree with at
// most j slots: a slot of n itself (a leaf: 0; an interior node: area(n) + f(n, 8), n a wide node)
// or, for j >= 2, f(n, j) = min over k of g(left, k) + g(right, j - k), n opened. plan[n][j - 1]
// (j = 2..8) holds that k, or 0 where n is better kept as one slot (for j = 8: n's own wide node).
using Plan = std::array<std::uint8_t, kNodeWidth>;

template <typename Node>
class Planner {
 public:
  Planner(const Node* nodes, Plan* plan, util::ThreadPool& pool) : nodes_(nodes), plan_(plan), pool_(pool) {}

  // Fills the plan of the whole tree on up to `threads` of the pool's threads: the subtrees of at most `grain`
  // binary nodes each on one thread, then the nodes above them. Per node the same arithmetic in
  // the same order whatever the split, so the same plan on any number of threads.
  void plan_tree(unsigned threads, std::size_t grain) {
    float g[kNodeWidth];
    if (threads <= 1) {
      plan(0, g);
      return;
    }
    split(0, grain);
    done_.resize(roots_.size());
    pool_.parallel_for(roots_.size(), threads, [&](std::size_t t) { plan(roots_[t], done_[t].data()); });
    plan_top(0, g);
  }

 private:
  // Fills plan[n] for the subtree of `bin`, children first; g[j - 1] = g(bin, j).
  void plan(std::uint32_t bin, float* g) const {
    const Node& node = nodes_[bin];
    if (node.count > 0) {
      plan_[bin].fill(0);
      std::fill(g, g + kNodeWidth, 0.0f);
      return;
    }
    float gl[kNodeWidth], gr[kNodeWidth];
    plan(bin + 1, gl);
    plan(node.offset, gr);
    combine(bin, gl, gr, g);
  }

  // The same above the subtrees that split found (their g in done_).
  void plan_top(std::uint32_t bin, float* g) const {
    const auto it = std::lower_bound(roots_.begin(), roots_.end(), bin);
    if (it != roots_.end() && *it == bin) {
      std::copy_n(done_[std::size_t(it - roots_.begin())].data(), kNodeWidth, g);
      return;
    }
    float gl[kNodeWidth], gr[kNodeWidth];
    plan_top(bin + 1, gl);
    plan_top(nodes_[bin].offset, gr);
    combine(bin, gl, gr, g);
  }

  // Binary interior node `bin`'s plan and g from its children's.
  void combine(std::uint32_t bin, const float* gl, const float* gr, float* g) const {
    Plan& p = plan_[bin];
    p[0] = 0;
    float f[kNodeWidth + 1];
    for (int j = 2; j <= kNodeWidth; ++j) {
      float best = std::numeric_limits<float>::infinity();
      int best_k = 1;
      for (int k = 1; k < j; ++k) {
        const float c = gl[k - 1] + gr[j - k - 1];
        if (c < best) {
          best = c;
          best_k = k;
        }
      }
      f[j] = best;
      p[j - 1] = std::uint8_t(best_k);
    }
    const float own = float(node_area(nodes_[bin].bounds)) + f[kNodeWidth];  // bin as a wide node
    g[0] = own;
    for (int j = 2; j < kNodeWidth; ++j) {
      if (f[j] <= own) {  // ties open bin: one wide node fewer
        g[j - 1] = f[j];
      } else {
        g[j - 1] = own;
        p[j - 1] = 0;
      }
    }
    g[kNodeWidth - 1] = std::min(f[kNodeWidth], own);
  }

  // The roots of subtrees of at most `grain` binary nodes (or leaves) below `bin`, depth first.
  void split(std::uint32_t bin, std::size_t grain) {
    std::uint32_t last = bin;
    while (nodes_[last].count == 0) last = nodes_[last].offset;
    if (std::size_t(last) - bin + 1 <= grain) {
      roots_.push_back(bin);
      return;
    }
    split(bin + 1, grain);
    split(nodes_[bin].offset, grain);
  }

  const Node* nodes_;
  Plan* plan_;
  util::ThreadPool& pool_;
  std::vector<std::uint32_t> roots_;                 // increasing: depth-first order
  std::vector<std::array<float, kNodeWidth>> done_;  // g of each root
};

// Sphere `ns` of a leaf's blocks (centre, radius, shape id), a fresh block begun at each kWidth-th;
// counts it in ns.
void put_sphere(SphereBlock* spheres, std::uint32_t& ns, float x, float y, float z, float r, std::uint32_t id) {
  if (ns % kWidth == 0) spheres[ns / kWidth] = empty_sphere_block();
  SphereBlock& b = spheres[ns / kWidth];
  const std::uint32_t lane = ns++ % kWidth;
  b.cx[lane] = x;
  b.cy[lane] = y;
  b.cz[lane] = z;
  b.r[lane] = r;
  b.id[lane] = id;
}

// The collapse of one binary tree (Node and Prim: Geometry's, private to it). Every pass walks the same wide nodes in
// the same order (depth first, children in slot order), so the cursor reaches each node, leaf and block at the index
// the one-pass collapse would have appended it at: the tree is the same whatever the tasks and threads.
// Prim i is prims[i], or where `aside_order` is given (a set-aside scene, whose prims are all
// spheres) the sphere aside_spheres[aside_order[i]].sphere with id aside_order[i].
template <typename Node, typename Prim, typename Aside>
class Collapse {
 public:
  Collapse(const Node* nodes, const Prim* prims, const Aside* aside_spheres, const std::uint32_t* aside_order,
           const std::vector<Shape>& shapes, WideBvh& w, bool spheres_only, bool every_record, ReadOnce& prims_read,
           const Plan* plan)
      : nodes_(nodes),
        plan_(plan),
        prims_(prims),
        aside_spheres_(aside_spheres),
        aside_order_(aside_order),
        shapes_(shapes),
        w_(w),
        spheres_only_(spheres_only),
        every_record_(every_record),
        prims_read_(prims_read) {}

  // The wide subtree whose root takes binary node `bin`, from cursor `at` (kCount or kWrite);
  // returns the root's index. `made`, where given: the subtree's slots, which kCount appends and
  // kWrite reads instead of opening the binary nodes again (its node `index` at made[index - first]).
  // `read`, where given, counts off the prims kWrite reads (else ReadOnce::read, leaf by leaf).
  template <Pass P>
  std::uint32_t node(std::uint32_t bin, Cursor& at, std::vector<NodeSlots>* made = nullptr, std::size_t first = 0,
                     ReadOnce::Batch* read = nullptr) const {
    const auto index = std::uint32_t(at.node++);
    NodeSlots own;
    const NodeSlots* ns = &own;
    if (P == Pass::kWrite && made != nullptr) {
      ns = &(*made)[index - first];
    } else {
      own.n = slots_of(bin, own.slot);
      if (P == Pass::kCount && made != nullptr) made->push_back(own);
    }
    const std::uint32_t* slots = ns->slot;
    const int n = ns->n;
    std::uint32_t child[kNodeWidth];
    for (int i = 0; i < n; ++i) {
      child[i] = nodes_[slots[i]].count > 0 ? leaf<P>(slots[i], at, read) : node<P>(slots[i], at, made, first, read);
    }
    if constexpr (P == Pass::kWrite) write_node(index, slots, n, child);
    return index;
  }

  // The wide nodes above the tasks (the root's among them), in the same order. kPlan appends to
  // `tasks` the subtrees of at most `grain` binary nodes below them; kCount sets each task's place
  // (and its size where `counted_apart` is false); kWrite writes the top's nodes and leaves. `next`
  // is the next task to meet.
  template <Pass P>
  std::uint32_t top(std::uint32_t bin, Cursor& at, std::vector<Task>& tasks, std::size_t& next, std::size_t grain,
                    bool counted_apart = true) const {
    const auto index = std::uint32_t(at.node++);
    std::uint32_t slots[kNodeWidth];
    const int n = slots_of(bin, slots);
    std::uint32_t child[kNodeWidth] = {};
    for (int i = 0; i < n; ++i) {
      const std::uint32_t s = slots[i];
      if (nodes_[s].count > 0) {
        if constexpr (P != Pass::kPlan) child[i] = leaf<P>(s, at);
        continue;
      }
      const bool task = P == Pass::kPlan ? subtree_nodes(s) <= grain : next < tasks.size() && tasks[next].bin == s;
      if (!task) {
        child[i] = top<P>(s, at, tasks, next, grain, counted_apart);
        continue;
      }
      if constexpr (P == Pass::kPlan) {
        tasks.push_back({s, {}, {}, {}, {}});
      } else {
        Task& t = tasks[next];
        if constexpr (P == Pass::kCount) {
          t.at = at;
          if (counted_apart) {
            at += t.size;
          } else {
            node<Pass::kCount>(s, at);
          }
          t.end = at;
        } else {
          child[i] = std::uint32_t(t.at.node);
          at = t.end;
        }
      }
      ++next;
    }
    if constexpr (P == Pass::kWrite) write_node(index, slots, n, child);
    return index;
  }

 private:
  // The binary nodes a wide node takes its children from, as the plan chose (a leaf root: one).
  int slots_of(std::uint32_t bin, std::uint32_t* slots) const {
    int n = 0;
    if (nodes_[bin].count > 0) {
      slots[n++] = bin;  // a leaf root: one child
      return n;
    }
    const int left = plan_[bin][kNodeWidth - 1];
    cover(bin + 1, left, slots, n);
    cover(nodes_[bin].offset, kNodeWidth - left, slots, n);
    return n;
  }

  // Appends the slots that cover the subtree of `bin` with at most `j` of them, as the plan chose.
  void cover(std::uint32_t bin, int j, std::uint32_t* slots, int& n) const {
    const int left = j >= 2 && nodes_[bin].count == 0 ? plan_[bin][j - 1] : 0;
    if (left == 0) {
      slots[n++] = bin;
      return;
    }
    cover(bin + 1, left, slots, n);
    cover(nodes_[bin].offset, j - left, slots, n);
  }

  // Binary nodes in the subtree of `bin` (depth first: they follow it up to its last leaf).
  std::size_t subtree_nodes(std::uint32_t bin) const {
    std::uint32_t last = bin;
    while (nodes_[last].count == 0) last = nodes_[last].offset;
    return std::size_t(last) - bin + 1;
  }

  void write_node(std::uint32_t index, const std::uint32_t* slots, int n, const std::uint32_t* child) const {
    WideNode& wn = w_.nodes[index];
    for (int i = 0; i < kNodeWidth; ++i) {
      wn.child[i] = i < n ? child[i] : kEmptyChild;
      for (int axis = 0; axis < 3; ++axis) {
        if (i < n) {
          wn.lo[axis][i] = nodes_[slots[i]].bounds[axis];
          wn.hi[axis][i] = nodes_[slots[i]].bounds[3 + axis];
        } else {
          wn.lo[axis][i] = std::numeric_limits<float>::infinity();
          wn.hi[axis][i] = -std::numeric_limits<float>::infinity();
        }
      }
    }
    for (std::uint32_t& p : wn.pad) p = 0;
  }

  // The leaf of binary leaf `bin`: its blocks and boxes at the cursor, and its child reference.
  template <Pass P>
  std::uint32_t leaf(std::uint32_t bin, Cursor& at, ReadOnce::Batch* read = nullptr) const {
    const auto& node = nodes_[bin];
    const Prim* prims = aside_order_ == nullptr ? prims_ + node.offset : nullptr;
    std::uint32_t ns = 0, nt = 0, nb = 0;
    if constexpr (P == Pass::kWrite) {
      SphereBlock* spheres = w_.spheres.data() + at.sphere;
      TriangleBlock* triangles = w_.triangles.data() + at.triangle;
      BoxPrim* boxes = w_.boxes.data() + at.box;
      if (aside_order_ != nullptr) {
        // Each sphere read by id (a random access, as making the prims in leaf order took) instead
        // of from a prims array of 32 bytes a sphere written and read once.
        const std::uint32_t* ids = aside_order_ + node.offset;
        for (std::uint32_t k = 0; k < node.count; ++k) {
          const SphereShape& sphere = aside_spheres_[ids[k]].sphere;
          put_sphere(spheres, ns, sphere.center.x, sphere.center.y, sphere.center.z, sphere.radius, ids[k]);
        }
      }
      for (std::uint32_t k = 0; aside_order_ == nullptr && k < node.count; ++k) {
        const auto& prim = prims[k];
        assert(!spheres_only_ || prim.type == ShapeType::kSphere);
        switch (prim.type) {
          case ShapeType::kSphere: {
            // The prim holds the sphere (centre, radius), and prims are in leaf order: no random
            // access into shapes_.
            put_sphere(spheres, ns, prim.data[0], prim.data[1], prim.data[2], prim.data[3], prim.id);
            break;
          }
          case ShapeType::kTriangle: {
            const Shape& shape = shapes_[prim.id];
            if (nt % kWidth == 0) triangles[nt / kWidth] = empty_triangle_block();
            TriangleBlock& b = triangles[nt / kWidth];
            const std::uint32_t lane = nt++ % kWidth;
            const Vec3f* v[3] = {&shape.triangle.v0, &shape.triangle.v1, &shape.triangle.v2};
            for (int vert = 0; vert < 3; ++vert)
              for (int axis = 0; axis < 3; ++axis) b.v[vert][axis][lane] = (*v[vert])[axis];
            b.id[lane] = prim.id;
            break;
          }
          default: {
            BoxPrim& bp = boxes[nb++];
            std::copy(prim.data, prim.data + 6, bp.b);
            bp.id = prim.id;
            break;
          }
        }
      }
      if (read != nullptr) {
        read->read(node.offset, node.count);
      } else {
        prims_read_.read(node.offset, node.count);
      }
    } else if (spheres_only_) {
      ns = node.count;  // no prim read: a pass over the prims' types cost half the count pass
    } else {
      for (std::uint32_t k = 0; k < node.count; ++k) {
        const ShapeType type = prims[k].type;
        ns += type == ShapeType::kSphere;
        nt += type == ShapeType::kTriangle;
        nb += type != ShapeType::kSphere && type != ShapeType::kTriangle;
      }
    }
    WideLeaf leaf;
    leaf.sphere_begin = std::uint32_t(at.sphere);
    leaf.triangle_begin = std::uint32_t(at.triangle);
    leaf.box_begin = std::uint32_t(at.box);
    leaf.sphere_blocks = std::uint16_t((ns + kWidth - 1) / kWidth);
    leaf.triangle_blocks = std::uint16_t((nt + kWidth - 1) / kWidth);
    leaf.box_count = nb;
    at.sphere += leaf.sphere_blocks;
    at.triangle += leaf.triangle_blocks;
    at.box += nb;
    const std::uint32_t ref = tri_leaf_ref(leaf);
    if (ref != 0 && !every_record_) return ref;
    const std::size_t record = at.leaf++;
    if constexpr (P == Pass::kWrite) w_.leaves[record] = leaf;
    if (ref != 0) return ref;
    return kLeafBit | std::uint32_t(record);
  }

  const Node* nodes_;
  const Plan* plan_;  // the SAH collapse's choices per binary node (Planner)
  const Prim* prims_;
  const Aside* aside_spheres_;
  const std::uint32_t* aside_order_;
  const std::vector<Shape>& shapes_;
  WideBvh& w_;
  bool spheres_only_;
  bool every_record_;
  ReadOnce& prims_read_;
};

}  // namespace

WideBvh collapse_to_wide(const Geometry& g, bool prims_read_once, bool spheres_only, util::ThreadPool& pool,
                         unsigned threads, const AsideSpheres* aside_spheres) {
  WideBvh w;
  if (g.nodes_.empty()) return w;
  // A leaf that its child reference describes (tri_leaf_ref: one block of spheres, or triangles
  // only) is never looked up in `leaves`, so it gets no WideLeaf record (20 bytes a leaf: 6 MB
  // of a scene of 1M spheres). Except in a tree of a few binary interior nodes, which may
  // collapse to one wide node: the records then keep telling is_flat that it is no flat layout
  // (a wide node takes at most seven binary interior nodes, so eight make two wide nodes). Every
  // interior node of the binary tree has two children: n nodes hold (n - 1) / 2 interior ones.
  const bool every_record = (g.nodes_.size() - 1) / 2 < 8;
  // With prims_read_once nothing reads a prim after the collapse has, so the prims' pages go back
  // as the leaves are made: the prims and the wide tree are then never held whole together (the
  // 1M-sphere scene's build peaked there). Not for a tree that may collapse to one node (is_flat:
  // the build then keeps its prims).
  // A set-aside scene's prims are its spheres by id in leaf order (`aside_spheres`): then the ids'
  // pages go back.
  const bool aside = aside_spheres != nullptr;
  const std::uint32_t* const aside_order = aside ? aside_spheres->order : nullptr;
  const std::size_t prim_count = aside ? aside_spheres->count : g.prims_.size();
  ReadOnce prims_read(aside ? static_cast<const void*>(aside_order) : g.prims_.data(), prim_count,
                      aside ? sizeof(aside_order[0]) : sizeof(g.prims_[0]), prims_read_once && !every_record);
  // The SAH collapse's choices, 8 bytes a binary node, each written by the Planner below (not
  // zeroed here: the planning threads touch their subtrees' pages first).
  const std::unique_ptr<Plan[]> plan(new Plan[g.nodes_.size()]);
  Collapse c(g.nodes_.data(), g.prims_.data(), aside ? aside_spheres->spheres : nullptr, aside_order, g.shapes_, w,
             spheres_only || aside, every_record, prims_read, plan.get());
  // Threads for trees large enough to pay for starting them; the result does not depend on it.
  if (prim_count < kParallelPrims) threads = 1;
  // Tasks: subtrees of at most `grain` binary nodes under the top, dozens per thread so that the
  // threads finish together (on one thread, every subtree below the root: the same passes).
  const std::size_t grain =
      threads <= 1 ? std::numeric_limits<std::size_t>::max()
                   : std::max<std::size_t>(kMinTaskNodes, g.nodes_.size() / (std::size_t(threads) * kTasksPerThread));
  Planner(g.nodes_.data(), plan.get(), pool).plan_tree(threads, grain);
  std::vector<Task> tasks;
  {
    Cursor at;
    std::size_t next = 0;
    c.top<Pass::kPlan>(0, at, tasks, next, grain);
  }
  // Counting each task from zero gives the sizes its output takes wherever it lands, unless a
  // leaf's first block may lie past what a child reference can name (then whether it needs a
  // record depends on where it lands, and the tasks are counted in place, in order).
  const bool counted_apart = prim_count <= kTriLeafBeginMask;
  if (counted_apart) {
    pool.parallel_for(tasks.size(), threads, [&](std::size_t t) {
      Cursor size;
      c.node<Pass::kCount>(tasks[t].bin, size, &tasks[t].slots);
      tasks[t].size = size;
    });
  }
  Cursor total;
  {
    std::size_t next = 0;
    c.top<Pass::kCount>(0, total, tasks, next, grain, counted_apart);
  }
  if (total.leaf > kTriLeaf) std::abort();  // plain leaf indices must stay below kTriLeaf
  // Exact sizes, and no memory written by sizing the arrays but the few leaf records and boxes
  // (WideNode and the blocks write nothing when made): each task's thread touches the pages of its
  // own part first. First touches are costly page faults (util/huge_pages.h): with 4 KiB pages
  // they took more than half of the collapse of 1M spheres.
  const auto size = [](auto& v, std::size_t n) {
    v.reserve(n);
    util::advise_huge_pages_for(v);
    v.resize(n);
  };
  size(w.nodes, total.node);
  size(w.leaves, total.leaf);
  size(w.spheres, total.sphere);
  size(w.triangles, total.triangle);
  size(w.boxes, total.box);
  w.has_triangles = total.triangle > 0;
  pool.parallel_for(tasks.size(), threads, [&](std::size_t t) {
    Task& task = tasks[t];
    Cursor at = task.at;
    ReadOnce::Batch read(prims_read);  // the task's prims: one run, counted off per block
    c.node<Pass::kWrite>(task.bin, at, task.slots.empty() ? nullptr : &task.slots, task.at.node, &read);
    std::vector<NodeSlots>().swap(task.slots);
  });
  {
    Cursor at;
    std::size_t next = 0;
    c.top<Pass::kWrite>(0, at, tasks, next, grain);
  }
  return w;
}

}  // namespace dtraced::accel::detail
