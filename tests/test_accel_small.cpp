// Tests of dtraced::accel's small-scene layout and packet set-up: below 64 bounded shapes a SIMD
// geometry has no tree for packets (one flat node over the shapes and, apart, the huge ones; see
// Geometry::build), and its packets, single rays and any-hit queries must answer exactly as the
// scalar reference does (same shape, same t bits, same hit record) on every instruction set this
// machine runs. Also packets whose lanes differ in direction signs, have zero or negative-zero
// direction components or different dominant axes, which exercise the per-lane constants the
// packet kernels compute a vector at a time, on a flat and on a tree layout. And the encoding of
// triangle-only and one-sphere-block leaves in their child references (kTriLeaf), with a scene that
// mixes such leaves, mixed leaves and an oversized leaf of duplicates.
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "accel/wide_bvh.h"
#include "math/float_util.h"
#include "shape_builders.h"

using namespace dtraced::accel;
using namespace dtraced::testing;

namespace {

// `n` bounded shapes in a 20-unit cube (spheres, boxes and triangles in turn, so every leaf kind
// is there), an exact duplicate (a tie: the smaller id wins), and, if asked, a ground plane and a
// huge triangle pair (kept out of the tree, in the flat layout's second group).
std::vector<Shape> small_scene(TestRng& rng, int n, bool extras) {
  std::vector<Shape> shapes;
  for (int i = 0; i < n; ++i) {
    const Vec3d c = rng.in_cube(10.0);
    const double size = rng.log_uniform(0.2, 3.0);
    switch (i % 3) {
      case 0:
        shapes.push_back(sphere(to_f(c), float(size)));
        break;
      case 1: {
        const Vec3d h{size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0)};
        shapes.push_back(box(to_f(c - h), to_f(c + h)));
        break;
      }
      default:
        shapes.push_back(
            triangle(to_f(c + rng.unit() * size), to_f(c + rng.unit() * size), to_f(c + rng.unit() * size)));
        break;
    }
  }
  if (n > 0) shapes.push_back(shapes.front());
  if (extras) {
    shapes.push_back(plane({0, -12, 0}, {0, 1, 0}));
    shapes.push_back(triangle({-500, -11, -500}, {500, -11, -500}, {500, -11, 500}));
    shapes.push_back(triangle({-500, -11, -500}, {500, -11, 500}, {-500, -11, 500}));
  }
  return shapes;
}

// Rays from random points: random directions, axis-parallel ones, some with a zero or a negative
// zero component, and some with a finite interval.
std::vector<Ray> awkward_rays(TestRng& rng, int n) {
  std::vector<Ray> rays;
  for (int i = 0; i < n; ++i) {
    const Vec3f o = to_f(rng.in_cube(16.0));
    Vec3f d = unit_f(rng.unit());
    const int kind = rng.index(4);
    if (kind == 1) {
      d = {0, 0, 0};
      d[std::size_t(rng.index(3))] = rng.uniform() < 0.5 ? -1.0f : 1.0f;
    } else if (kind == 2) {
      d[std::size_t(rng.index(3))] = 0.0f;
      d = unit_f(to_d(d));
    }
    for (std::size_t k = 0; k < 3; ++k) {
      if (d[k] == 0.0f && rng.uniform() < 0.5) d[k] = -0.0f;
    }
    Ray r = make_ray(o, d);
    if (rng.uniform() < 0.2) {
      r.t_min = float(rng.uniform(0.0, 3.0));
      r.t_max = float(r.t_min + rng.uniform(0.0, 30.0));
    }
    rays.push_back(r);
  }
  return rays;
}

// Rays from random points aimed at a point of a random bounded shape (a sphere's centre, a box's
// corner, a triangle's vertex: edges and corners included), so that small scenes are hit often.
std::vector<Ray> aimed_rays(TestRng& rng, const std::vector<Shape>& shapes, int n) {
  std::vector<Ray> rays;
  for (int i = 0; i < n; ++i) {
    const Shape& s = shapes[std::size_t(rng.index(int(shapes.size())))];
    Vec3f target;
    switch (s.type) {
      case ShapeType::kSphere:
        target = s.sphere.center;
        break;
      case ShapeType::kBox:
        target = rng.uniform() < 0.5 ? s.box.lo : s.box.hi;
        break;
      case ShapeType::kTriangle:
        target = rng.uniform() < 0.5 ? s.triangle.v0 : s.triangle.v2;
        break;
      case ShapeType::kPlane:
        target = s.plane.point;
        break;
    }
    const Vec3f o = to_f(rng.in_cube(16.0));
    if (to_d(target) == to_d(o)) continue;
    rays.push_back(make_ray(o, unit_f(to_d(target) - to_d(o))));
  }
  return rays;
}

// Camera-like rays towards the scene from one point: coherent packets (4x2 pixels).
std::vector<Ray> camera_rays(int w, int h, const Vec3f& eye) {
  std::vector<Ray> rays;
  for (int by = 0; by < h; by += 2) {
    for (int bx = 0; bx < w; bx += 4) {
      for (int k = 0; k < 8; ++k) {
        const double x = (bx + k % 4 + 0.5) / w - 0.5, y = (by + k / 4 + 0.5) / h - 0.5;
        rays.push_back(make_ray(eye, unit_f(Vec3d{x * 1.6, y * 1.2, 1.0})));
      }
    }
  }
  return rays;
}

struct Counts {
  long rays = 0, hits = 0, mismatches = 0;
};

// Every query of `rays` (packets of N consecutive rays, with a lane mask that varies) through `geo`
// against the scalar reference `ref`.
template <int N>
Counts compare_n(const Geometry& ref, const Geometry& geo, const std::vector<Ray>& rays) {
  Counts c;
  for (std::size_t base = 0; base + N <= rays.size(); base += N) {
    const std::uint32_t all = (1u << N) - 1u;
    const std::uint32_t valid = (base / N) % 5 == 4                        ? 0xa5a5u & all
                                : (N > kPacketSize && (base / N) % 5 == 2) ? 0x0ff0u
                                                                           : all;
    Hit hits[N];
    const std::uint32_t found =
        N == kPacketSize ? geo.intersect8(&rays[base], valid, hits) : geo.intersect16(&rays[base], valid, hits);
    const std::uint32_t blocked =
        N == kPacketSize ? geo.occluded8(&rays[base], valid) : geo.occluded16(&rays[base], valid);
    for (std::uint32_t i = 0; i < std::uint32_t(N); ++i) {
      if (!(valid >> i & 1u)) {
        c.mismatches += (found >> i & 1u) + (blocked >> i & 1u);
        continue;
      }
      const Ray& r = rays[base + i];
      Hit want, got;
      const bool w = ref.intersect(r, want);
      const bool g = geo.intersect(r, got);
      const bool p = found >> i & 1u;
      c.hits += w;
      ++c.rays;
      const int bad = ((w != g) || (w && !same_hit(want, got))) + ((w != p) || (w && !same_hit(want, hits[i]))) +
                      (ref.occluded(r) != w) + (geo.occluded(r) != w) + (bool(blocked >> i & 1u) != w);
      if (bad != 0 && ++c.mismatches <= 3) {
        UNSCOPED_INFO("mismatch (packets of " << N << ") " << describe(r) << " ref=" << w << "/" << want.shape << "/"
                                              << want.t << " single=" << g << "/" << got.shape << " packet=" << p << "/"
                                              << hits[i].shape << "/" << hits[i].t);
      }
    }
  }
  return c;
}

// compare_n for packets of 8 and of 16 (rays and hits counted once, mismatches of both).
Counts compare(const Geometry& ref, const Geometry& geo, const std::vector<Ray>& rays) {
  Counts c = compare_n<kPacketSize>(ref, geo, rays);
  c.mismatches += compare_n<kPacketSize16>(ref, geo, rays).mismatches;
  return c;
}

// Every SIMD isa's geometry of `shapes` (a tree, not the flat layout) answers every query of `rays`
// as the scalar reference does, and more than 1 / `hit_share` of the rays hit.
void check_tree_matches_scalar(const std::vector<Shape>& shapes, const std::vector<Ray>& rays, long hit_share) {
  const Geometry ref = Geometry::build(shapes, Isa::kScalar);
  for (const Isa isa : supported_isas()) {
    if (isa == Isa::kScalar) continue;
    const Geometry geo = Geometry::build(shapes, isa);
    INFO("isa " << isa_name(isa));
    CHECK(geo.stats().wide_nodes > 1);
    const Counts c = compare(ref, geo, rays);
    CHECK(c.hits > c.rays / hit_share);
    CHECK(c.mismatches == 0);
  }
}

}  // namespace

TEST_CASE("small scenes: packets test every shape directly and answer as the scalar path", "[accel][small]") {
  for (const int n : {1, 2, 5, 10, 33, 62}) {
    for (const bool extras : {false, true}) {
      TestRng rng{std::uint64_t(100 + n * 2 + int(extras))};
      const std::vector<Shape> shapes = small_scene(rng, n, extras);
      std::vector<Ray> rays = camera_rays(64, 32, {0, 2, -30});
      const std::vector<Ray> more = awkward_rays(rng, 6000);
      rays.insert(rays.end(), more.begin(), more.end());
      const std::vector<Ray> aimed = aimed_rays(rng, shapes, 3000);
      rays.insert(rays.end(), aimed.begin(), aimed.end());
      const Geometry ref = Geometry::build(shapes, Isa::kScalar);
      for (const Isa isa : supported_isas()) {
        if (isa == Isa::kScalar) continue;
        const Geometry geo = Geometry::build(shapes, isa);
        INFO("isa " << isa_name(isa) << ", " << n << " shapes, extras " << extras);
        CHECK(geo.stats().wide_nodes == 1);  // the flat layout: one node, no tree
        const Counts c = compare(ref, geo, rays);
        CHECK(c.rays > 9000);
        CHECK(c.hits > c.rays / 10);
        CHECK(c.mismatches == 0);
      }
    }
  }
}

TEST_CASE("64 bounded shapes get the wide tree, and it answers as the scalar path", "[accel][small]") {
  TestRng rng{7};
  const std::vector<Shape> shapes = small_scene(rng, 64, true);  // 65 bounded with the duplicate
  std::vector<Ray> rays = camera_rays(64, 32, {0, 2, -30});
  const std::vector<Ray> more = awkward_rays(rng, 6000);
  rays.insert(rays.end(), more.begin(), more.end());
  check_tree_matches_scalar(shapes, rays, 20);
}

TEST_CASE("a scene of planes alone, or one shape, on every isa", "[accel][small]") {
  const std::vector<Shape> shapes = {plane({0, 0, 0}, {0, 1, 0}), sphere({0, 1, 5}, 1.0f)};
  const Ray down = make_ray({0, 3, 0}, {0, -1, 0});
  const Ray at_sphere = make_ray({0, 1, 0}, {0, 0, 1});
  for (const Isa isa : supported_isas()) {
    INFO("isa " << isa_name(isa));
    const Geometry planes = Geometry::build({shapes[0]}, isa);
    CHECK(planes.stats().wide_nodes == 0);
    Hit hits[kPacketSize];
    const Ray packet[kPacketSize] = {down, down, down, down, down, down, down, at_sphere};
    CHECK(planes.intersect8(packet, 0xffu, hits) == 0x7fu);
    CHECK(hits[0].shape == 0);
    CHECK(hits[0].t == 3.0f);
    const Geometry both = Geometry::build(shapes, isa);
    CHECK(both.intersect8(packet, 0xffu, hits) == 0xffu);
    CHECK(hits[7].shape == 1);
    CHECK(hits[7].t == 4.0f);
    CHECK(both.occluded8(packet, 0x80u) == 0x80u);
  }
}

TEST_CASE("triangle hit records from the kernels' own edge functions equal the scalar path's", "[accel][small]") {
  // The SIMD kernels keep the winning triangle test's edge functions and build the hit record from
  // them (finish_triangle_hit); the scalar path tests the triangle again. A bumpy grid of 800
  // triangles with inexact vertex coordinates (so float and double edge functions differ), and
  // rays through its vertices and edges (an edge function exactly zero: the double fallback) and
  // through interiors, straight down (packets with one set of shear axes), tilted (mixed axes
  // within a packet) and from random points: p, n, p_error must have the scalar path's bits.
  TestRng rng{21};
  constexpr int kSide = 20;
  constexpr float kStep = 0.37f;
  std::vector<Vec3f> grid;
  for (int y = 0; y <= kSide; ++y) {
    for (int x = 0; x <= kSide; ++x)
      grid.push_back({float(x) * kStep, float(y) * kStep, float(rng.uniform(-0.05, 0.05))});
  }
  auto at = [&](int x, int y) { return grid[std::size_t(y * (kSide + 1) + x)]; };
  std::vector<Shape> shapes;
  for (int y = 0; y < kSide; ++y) {
    for (int x = 0; x < kSide; ++x) {
      shapes.push_back(triangle(at(x, y), at(x + 1, y), at(x + 1, y + 1)));
      shapes.push_back(triangle(at(x, y), at(x + 1, y + 1), at(x, y + 1)));
    }
  }
  std::vector<Ray> rays;
  for (int y = 1; y < kSide; ++y) {
    for (int x = 1; x < kSide; ++x) {
      const Vec3f v = at(x, y);
      rays.push_back(make_ray({v.x, v.y, 3.0f}, {0, 0, -1}));  // through a vertex
      const Vec3f mid{v.x + 0.5f * kStep, v.y, 3.0f};
      rays.push_back(make_ray(mid, {0, 0, -1}));  // through an edge (x + 1/2 rounds, y is exact)
      rays.push_back(make_ray({v.x + 0.3f * kStep, v.y + 0.6f * kStep, 3.0f}, {0, 0, -1}));
      // Tilted towards the vertex: in x-major or z-major packets alternately.
      const double slope = (x + y) % 2 == 0 ? 0.3 : 3.0;
      const Vec3f dir = unit_f(Vec3d{slope, 0.1, -1.0});
      rays.push_back(make_ray(to_f(to_d(v) - to_d(dir) * 2.0), dir));
    }
  }
  const std::vector<Ray> aimed = aimed_rays(rng, shapes, 2000);
  rays.insert(rays.end(), aimed.begin(), aimed.end());
  check_tree_matches_scalar(shapes, rays, 2);
}

TEST_CASE("rays grazing a sphere's silhouette: packets answer as the scalar path", "[accel][small]") {
  // Rays a few float steps either side of a sphere's silhouette (discriminants near zero, where
  // any shortcut ahead of the exact double test would show), at several scales and distances,
  // with unit directions and with longer ones, must hit and miss exactly as the scalar reference
  // does, in packets of 8 on every instruction set, on the flat layout and on a tree.
  struct Case {
    Vec3d c;
    double r;
    Vec3d o;
  };
  // Apart from each other: no origin inside another sphere, no ray past one silhouette into
  // another sphere.
  const Case cases[] = {{{0, 0, 0}, 1.0, {0, 0, -5}},          {{0.3, -0.7, 12.1}, 1.7, {4, 1, 7}},
                        {{1e5, 0, 3e4}, 1.0, {0, -50, 0}},     {{1e3, 0, 0}, 1e-3, {999, 0.5, -0.3}},
                        {{0, 0, 8000}, 1e3, {0, 40, 6990}},    {{-20, 5, 40}, 0.05, {-20.3, 5.1, 39}},
                        {{7, 7, 7}, 3e-6, {7, 7.00001, 7.001}}};
  std::vector<Shape> shapes;
  std::vector<Ray> rays;
  for (const Case& k : cases) {
    shapes.push_back(sphere(to_f(k.c), float(k.r)));
    // The sphere and origin as the scene has them (rounded to float).
    const Vec3d c = to_d(to_f(k.c)), o = to_d(to_f(k.o));
    const double r = double(float(k.r));
    const Vec3d w = c - o;
    const double dist = length(w);
    const Vec3d side = normalize(cross(w, std::abs(w.x) < 0.9 * dist ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0}));
    for (const double step : {0x1p-22, 0x1p-16, 0x1p-10}) {
      for (int j = -32; j < 32; ++j) {
        // The line o + s (w + side t) passes the centre at m = t dist / sqrt(dist^2 + t^2).
        const double m = r * (1.0 + j * step);
        const double t = m * dist / std::sqrt(dist * dist - m * m);
        const Vec3d d = normalize(w + side * t);
        rays.push_back(make_ray(to_f(o), to_f(d)));
        rays.push_back(make_ray(to_f(o), to_f(d * 4.0)));  // |d|^2 = 16
      }
    }
  }
  // Unit directions only, 8 of a kind per packet (alternating with the longer ones above).
  std::vector<Ray> unit_only;
  for (std::size_t i = 0; i < rays.size(); i += 2) unit_only.push_back(rays[i]);
  rays.insert(rays.end(), unit_only.begin(), unit_only.end());

  const Geometry ref = Geometry::build(shapes, Isa::kScalar);
  for (const Isa isa : supported_isas()) {
    if (isa == Isa::kScalar) continue;
    INFO("isa " << isa_name(isa));
    const Geometry geo = Geometry::build(shapes, isa);
    CHECK(geo.stats().wide_nodes == 1);
    const Counts c = compare(ref, geo, rays);
    CHECK(c.hits > c.rays / 4);
    CHECK(c.hits < c.rays * 3 / 4);
    CHECK(c.mismatches == 0);
  }
  // The same rays through a tree: 80 more small spheres well away from the silhouettes.
  TestRng rng{16};
  for (int i = 0; i < 80; ++i) shapes.push_back(sphere(to_f(rng.in_cube(50.0) + Vec3d{0, -3000, 0}), 0.5f));
  check_tree_matches_scalar(shapes, rays, 4);
}

TEST_CASE("triangle-only and one-sphere-block leaves are described by their child reference, others by their record",
          "[accel][small]") {
  using namespace dtraced::accel::detail;
  SECTION("the kTriLeaf reference round-trips, and leaves it cannot describe get 0") {
    WideLeaf tri;
    tri.triangle_begin = 123456;
    tri.triangle_blocks = 3;
    const std::uint32_t ref = tri_leaf_ref(tri);
    CHECK((ref & kLeafBit) != 0);
    CHECK((ref & kTriLeaf) != 0);
    const WideLeaf back = tri_leaf_of(ref);
    CHECK(back.triangle_begin == 123456);
    CHECK(back.triangle_blocks == 3);
    CHECK(back.sphere_blocks == 0);
    CHECK(back.box_count == 0);
    WideLeaf most = tri;
    most.triangle_begin = kTriLeafBeginMask;
    most.triangle_blocks = std::uint16_t(kTriLeafMaxBlocks);
    CHECK(tri_leaf_of(tri_leaf_ref(most)).triangle_begin == kTriLeafBeginMask);
    CHECK(tri_leaf_of(tri_leaf_ref(most)).triangle_blocks == kTriLeafMaxBlocks);
    WideLeaf with_sphere = tri;
    with_sphere.sphere_blocks = 1;
    CHECK(tri_leaf_ref(with_sphere) == 0);
    WideLeaf with_box = tri;
    with_box.box_count = 1;
    CHECK(tri_leaf_ref(with_box) == 0);
    WideLeaf too_many = tri;
    too_many.triangle_blocks = std::uint16_t(kTriLeafMaxBlocks + 1);
    CHECK(tri_leaf_ref(too_many) == 0);
    WideLeaf too_far = tri;
    too_far.triangle_begin = kTriLeafBeginMask + 1;
    CHECK(tri_leaf_ref(too_far) == 0);
    CHECK(tri_leaf_ref(WideLeaf{}) == 0);  // no prims at all
  }
  SECTION("a leaf of one sphere block round-trips too, with a block count of 0; other sphere leaves get 0") {
    WideLeaf sph;
    sph.sphere_begin = 654321;
    sph.sphere_blocks = 1;
    const std::uint32_t ref = tri_leaf_ref(sph);
    CHECK((ref & kLeafBit) != 0);
    CHECK((ref & kTriLeaf) != 0);
    CHECK(tri_leaf_blocks(ref) == 0);
    const WideLeaf back = tri_leaf_of(ref);
    CHECK(back.sphere_begin == 654321);
    CHECK(back.sphere_blocks == 1);
    CHECK(back.triangle_blocks == 0);
    CHECK(back.box_count == 0);
    WideLeaf last = sph;
    last.sphere_begin = kTriLeafBeginMask;
    CHECK(tri_leaf_of(tri_leaf_ref(last)).sphere_begin == kTriLeafBeginMask);
    WideLeaf two = sph;
    two.sphere_blocks = 2;
    CHECK(tri_leaf_ref(two) == 0);
    WideLeaf too_far = sph;
    too_far.sphere_begin = kTriLeafBeginMask + 1;
    CHECK(tri_leaf_ref(too_far) == 0);
    WideLeaf with_box = sph;
    with_box.box_count = 1;
    CHECK(tri_leaf_ref(with_box) == 0);
  }
  SECTION("a mesh with spheres and boxes among its triangles and 80 copies of one triangle") {
    // Triangle-only leaves (the grid), mixed leaves (spheres and boxes resting on it) and a leaf the
    // build cannot split (identical triangles: more blocks than the word holds, unless the build
    // splits them by count) must all answer as the scalar path, nearest hits (ties to the smaller id)
    // and any-hit, single rays and packets of 8 and 16, on every SIMD isa.
    TestRng rng{33};
    constexpr int kSide = 16;
    constexpr float kStep = 0.5f;
    auto at = [&](int x, int y) {
      return Vec3f{float(x) * kStep, float(y) * kStep, float(0.05 * std::sin(x * 1.3) * std::cos(y * 0.7))};
    };
    std::vector<Shape> shapes;
    for (int y = 0; y < kSide; ++y) {
      for (int x = 0; x < kSide; ++x) {
        shapes.push_back(triangle(at(x, y), at(x + 1, y), at(x + 1, y + 1)));
        shapes.push_back(triangle(at(x, y), at(x + 1, y + 1), at(x, y + 1)));
        if ((x * 7 + y * 3) % 11 == 0) shapes.push_back(sphere(at(x, y) + Vec3f{0.2f, 0.2f, 0.1f}, 0.12f));
        if ((x * 5 + y) % 13 == 0) shapes.push_back(box(at(x, y), at(x, y) + Vec3f{0.15f, 0.1f, 0.2f}));
      }
    }
    for (int i = 0; i < 80; ++i) shapes.push_back(triangle({2, 2, 1}, {3, 2, 1}, {2, 3, 1.5f}));
    std::vector<Ray> rays = camera_rays(64, 32, {4, 4, 8});
    // Looking down at the grid.
    for (Ray& r : rays) r = make_ray(r.o, unit_f(Vec3d{r.d.x * 0.5, r.d.y * 0.5, -double(r.d.z)}));
    const std::vector<Ray> aimed = aimed_rays(rng, shapes, 4000);
    rays.insert(rays.end(), aimed.begin(), aimed.end());
    check_tree_matches_scalar(shapes, rays, 4);
  }
}

TEST_CASE("coherent packets (shared direction signs) answer as the scalar path", "[accel][small]") {
  // Packets whose lanes share their direction signs take a traversal of the packet as a
  // whole: a frustum of the lanes' origins and inverse directions bounds each child's entry and
  // exit distances, and a stack entry keeps one entry distance for all its lanes. Exercise the
  // bounds where they are loosest or degenerate: lanes from scattered origins with their own
  // t_min and t_max (shadow-like), a direction component exactly +0 or -0 in every lane (an
  // infinite inverse: that axis bounds nothing), lanes that start inside boxes, and the pinhole
  // camera's shared origin; nearest hits (ties to the smaller id) and any-hit, packets of 16 and
  // their halves as packets of 8, on every SIMD isa.
  TestRng rng{41};
  const std::vector<Shape> shapes = small_scene(rng, 1500, true);
  std::vector<Ray> rays = camera_rays(64, 32, {0, 2, -30});
  for (int packet = 0; packet < 400; ++packet) {
    const Vec3f light = to_f(rng.in_cube(14.0));
    const Vec3d centre = rng.in_cube(10.0);
    const double spread = rng.log_uniform(0.01, 4.0);
    const int zero_axis = packet % 4 == 3 ? rng.index(3) : -1;
    const bool neg_zero = rng.uniform() < 0.5;
    for (int k = 0; k < kPacketSize16; ++k) {
      const Vec3f o = to_f(centre + rng.unit() * (spread * rng.uniform()));
      Vec3d d = to_d(light) - to_d(o);
      if (zero_axis >= 0) d[std::size_t(zero_axis)] = 0.0;
      if (!(d.x != 0.0 || d.y != 0.0 || d.z != 0.0)) d = {1, 0, 0};
      Vec3f df = unit_f(d);
      if (zero_axis >= 0 && neg_zero) df[std::size_t(zero_axis)] = -0.0f;
      Ray r = make_ray(o, df);
      if (rng.uniform() < 0.5) {
        r.t_min = float(rng.uniform(0.0, 2.0));
        r.t_max = float(r.t_min + rng.uniform(0.0, 25.0));
      }
      rays.push_back(r);
    }
  }
  check_tree_matches_scalar(shapes, rays, 20);
}

TEST_CASE("planes beside a packet's shapes: ties, parallel rays and rays leaving a plane answer as the scalar path",
          "[accel][small]") {
  // The packet queries test the planes of a flat layout, and of a tree with only planes beside it,
  // a plane against all lanes at once (Geometry::outside_planes). Two coincident planes (a tie in
  // t: the smaller id wins), a plane given by a far-away point, a tilted one, rays parallel to the
  // ground (a zero denominator), rays starting on it (t = 0 = t_min) and rays with a finite
  // interval, in a flat scene (10 spheres) and a tree (80 spheres).
  for (const int n : {10, 80}) {
    TestRng rng{std::uint64_t(700 + n)};
    std::vector<Shape> shapes;
    for (int i = 0; i < n; ++i) shapes.push_back(sphere(to_f(rng.in_cube(10.0)), float(rng.log_uniform(0.2, 2.0))));
    shapes.push_back(plane({0, -3, 0}, {0, 1, 0}));
    shapes.push_back(plane({5, -3, 7}, {0, 1, 0}));  // the same plane: ties with the one before
    shapes.push_back(plane({1e6f, 4, 3}, unit_f(Vec3d{0.3, -1.0, 0.2})));
    shapes.push_back(plane({0, 0, 40}, {0, 0, -1}));
    std::vector<Ray> rays = camera_rays(64, 32, {0, 2, -30});
    const std::vector<Ray> more = awkward_rays(rng, 4000);
    rays.insert(rays.end(), more.begin(), more.end());
    for (int i = 0; i < 800; ++i) {
      const Vec3f o{float(rng.uniform(-8.0, 8.0)), i % 2 == 0 ? -3.0f : float(rng.uniform(-4.0, 4.0)),
                    float(rng.uniform(-8.0, 8.0))};
      Vec3f d = unit_f(rng.unit());
      if (i % 4 == 1) d.y = i % 8 == 1 ? 0.0f : -0.0f;  // parallel to the ground
      Ray r = make_ray(o, unit_f(to_d(d)));
      if (i % 5 == 0) r.t_max = float(rng.uniform(0.5, 20.0));
      rays.push_back(r);
    }
    const Geometry ref = Geometry::build(shapes, Isa::kScalar);
    for (const Isa isa : supported_isas()) {
      if (isa == Isa::kScalar) continue;
      const Geometry geo = Geometry::build(shapes, isa);
      INFO("isa " << isa_name(isa) << ", " << n << " spheres");
      CHECK((geo.stats().wide_nodes == 1) == (n < 64));
      const Counts c = compare(ref, geo, rays);
      CHECK(c.hits > c.rays / 3);
      CHECK(c.mismatches == 0);
    }
  }
}

// offset_ray_origin_to computes all three components at once with masks (SSE2): it must give the
// bits of pbrt-v4's branch-by-branch form, written out here, for every sign of the offset and
// every special sum (zeros of either sign, infinities, NaN, the largest and smallest floats).
TEST_CASE("offset_ray_origin_to gives the bits of the branch-by-branch form", "[accel][offset]") {
  using dtraced::math::next_float_down;
  using dtraced::math::next_float_up;
  const auto reference = [](const Vec3f& p, const Vec3f& e, const Vec3f& n, const Vec3f& w) {
    const float d = dot(abs(n), e);
    Vec3f offset = d * n;
    if (dot(w, n) < 0.0f) offset = -offset;
    const auto away = [](float v, float off) {
      if (off > 0.0f) return next_float_up(v);
      if (off < 0.0f) return next_float_down(v);
      return v;
    };
    return Vec3f{away(p.x + offset.x, offset.x), away(p.y + offset.y, offset.y), away(p.z + offset.z, offset.z)};
  };
  // NaNs compare as NaNs: which operand's NaN an addition passes on (and so its sign) is the
  // compiler's choice in either form, since it may swap the operands of a commutative operation.
  const auto same_bits = [](float a, float b) {
    return std::isnan(b) ? std::isnan(a) : std::bit_cast<std::uint32_t>(a) == std::bit_cast<std::uint32_t>(b);
  };
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const float special[] = {0.0f,  -0.0f,  1.0f,   -1.0f,   kInf,   -kInf, std::numeric_limits<float>::quiet_NaN(),
                           3e38f, -3e38f, 1e-45f, -1e-45f, 1e-38f, 0.5f,  -2.5f};
  const float normals[] = {0.0f, -0.0f, 1.0f, -1.0f, 0.6f, -0.8f, kInf};
  const auto at = [](Vec3f& v, int c) -> float& { return c == 0 ? v.x : c == 1 ? v.y : v.z; };
  TestRng rng{11};
  int checked = 0, stepped = 0;
  for (int trial = 0; trial < 4000; ++trial) {
    const auto pick = [&](const float* values, int count) { return values[rng.index(count)]; };
    Vec3f p, n;
    for (int c = 0; c < 3; ++c) {
      const bool random = rng.index(2) == 0;
      at(p, c) = random ? float(rng.uniform(-100.0, 100.0)) : pick(special, 14);
      at(n, c) = rng.index(3) == 0 ? pick(normals, 7) : float(rng.uniform(-1.0, 1.0));
    }
    const float err = rng.index(4) == 0 ? 0.0f : float(rng.log_uniform(1e-7, 1e-2));
    const Vec3f e{err, err * 0.5f, err * 2.0f};
    const Vec3f w{float(rng.uniform(-1.0, 1.0)), float(rng.uniform(-1.0, 1.0)), float(rng.uniform(-1.0, 1.0))};
    Vec3f got;
    offset_ray_origin_to(p, e, n, w, got);
    Vec3f want = reference(p, e, n, w);
    Vec3f ret = offset_ray_origin(p, e, n, w);
    for (int c = 0; c < 3; ++c) {
      const float g = at(got, c), r = at(ret, c), x = at(want, c);
      INFO("trial " << trial << " component " << c << ": got " << g << ", want " << x);
      CHECK(same_bits(g, x));
      CHECK(same_bits(r, x));
      ++checked;
      if (!same_bits(x, at(p, c))) ++stepped;
    }
  }
  CHECK(checked == 12000);
  CHECK(stepped > 1000);  // most components do step away from p
}
