// Tests of dtraced::accel's BVH: traversal equals brute force over every shape (same shape, same
// t bits), also where a sphere's extreme point meets a box face; hit records on the surface
// within their error bound; build statistics and degenerate inputs; the same tree on any number
// of threads and as recorded; std::bad_alloc from a build that runs out of memory; a timing
// report. Pass/fail only on correctness; timings are printed, never asserted.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <numbers>
#include <stdexcept>
#include <string>
#include <vector>

#if defined(__linux__)
#include <dlfcn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <fstream>
#include <new>
#endif

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "shape_builders.h"
#include "util/thread_pool.h"

using namespace dtraced::accel;
using namespace dtraced::testing;

namespace {

// Spheres and boxes of mixed sizes (1e-2..5) in a 40-unit cube, some flat boxes, exact duplicates
// (ties in t: the smaller id must win) and two planes.
std::vector<Shape> random_scene(TestRng& rng, int n) {
  std::vector<Shape> shapes;
  for (int i = 0; i < n; ++i) {
    const Vec3d c = rng.in_cube(20.0);
    const double size = rng.log_uniform(0.01, 5.0);
    if (rng.uniform() < 0.55) {
      shapes.push_back(sphere(to_f(c), float(size)));
    } else {
      Vec3d h{size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0)};
      if (rng.uniform() < 0.1) h[std::size_t(rng.index(3))] = 0.0;  // flat box
      shapes.push_back(box(to_f(c - h), to_f(c + h)));
    }
  }
  for (int i = 0; i < 6; ++i) {
    const Shape copy = shapes[std::size_t(rng.index(n))];  // exact duplicates
    shapes.push_back(copy);
  }
  shapes.push_back(plane({0, -25, 0}, {0, 1, 0}));
  shapes.push_back(plane({30, 0, 0}, unit_f({1, 2, 3})));
  return shapes;
}

// `rays` random rays from inside a cube of half-size 30 through `geo`, each against the brute-force
// answer over `shapes`: how many hit, and how many differ (a hit on another shape or another t).
struct Agreement {
  long hits = 0, mismatches = 0;
};
Agreement agree_with_brute_force(const Geometry& geo, const std::vector<Shape>& shapes, TestRng& rng, int rays) {
  Agreement out;
  for (int i = 0; i < rays; ++i) {
    const Ray ray = make_ray(to_f(rng.in_cube(30.0)), unit_f(rng.unit()));
    Hit a, b;
    const bool fa = geo.intersect(ray, a), fb = brute_force(shapes, ray, b);
    out.hits += fb;
    out.mismatches += fa != fb || (fa && !same_hit(a, b));
  }
  return out;
}

// A build gives back the very shapes it was given (every byte), and `rays` random rays through it
// answer as brute force does, more than `min_hits` of them hitting.
void check_shapes_back_and_exact(const Geometry& geo, const std::vector<Shape>& shapes, TestRng& rng, int rays,
                                 long min_hits) {
  REQUIRE(geo.shapes().size() == shapes.size());
  CHECK(std::memcmp(geo.shapes().data(), shapes.data(), shapes.size() * sizeof(Shape)) == 0);
  const Agreement agreed = agree_with_brute_force(geo, shapes, rng, rays);
  CHECK(agreed.hits > min_hits);
  CHECK(agreed.mismatches == 0);
}

}  // namespace

TEST_CASE("BVH equals brute force: same shape, same t bits", "[accel][bvh]") {
  TestRng rng{1};
  const std::vector<Shape> shapes = random_scene(rng, 400);
  const Geometry geo = Geometry::build(shapes);
  REQUIRE(geo.shapes().size() == shapes.size());

  std::vector<std::uint32_t> spheres, boxes;
  for (std::uint32_t i = 0; i < shapes.size(); ++i) {
    if (shapes[i].type == ShapeType::kSphere) spheres.push_back(i);
    if (shapes[i].type == ShapeType::kBox) boxes.push_back(i);
  }

  long rays = 0, hits = 0, mismatches = 0, occluded_mismatches = 0;
  auto check = [&](const Ray& ray) {
    ++rays;
    Hit a, b;
    const bool fa = geo.intersect(ray, a);
    const bool fb = brute_force(shapes, ray, b);
    hits += fb;
    if (fa != fb || (fa && !same_hit(a, b))) {
      if (++mismatches <= 5) {
        UNSCOPED_INFO("mismatch " << describe(ray) << " bvh=" << fa << "/" << a.shape << "/" << a.t << " brute=" << fb
                                  << "/" << b.shape << "/" << b.t);
      }
    }
    if ((rays & 7) == 0 && geo.occluded(ray) != fb) ++occluded_mismatches;
  };

  SECTION("random rays, some with a finite interval") {
    for (int i = 0; i < 200000; ++i) {
      const Vec3f o = to_f(rng.in_cube(30.0));
      Ray ray = make_ray(o, unit_f(rng.unit()));
      if (rng.uniform() < 0.2) {
        ray.t_min = float(rng.uniform(0.0, 5.0));
        ray.t_max = float(ray.t_min + rng.uniform(0.0, 60.0));
      }
      check(ray);
    }
    CHECK(hits > rays / 4);
  }
  SECTION("rays aimed at box edges and corners") {
    for (int i = 0; i < 40000; ++i) {
      const BoxShape& b = shapes[boxes[std::size_t(rng.index(int(boxes.size())))]].box;
      Vec3f target;
      const int free_axis = rng.index(4);  // 3: a corner; otherwise a point on an edge along that axis
      for (int k = 0; k < 3; ++k) {
        target[std::size_t(k)] = k == free_axis ? float(rng.uniform(b.lo[std::size_t(k)], b.hi[std::size_t(k)]))
                                                : (rng.uniform() < 0.5 ? b.lo : b.hi)[std::size_t(k)];
      }
      const Vec3f o = to_f(rng.in_cube(30.0));
      check(make_ray(o, unit_f(to_d(target) - to_d(o))));
    }
    CHECK(hits > rays / 2);
  }
  SECTION("rays tangent to spheres, jittered by a few ulps") {
    for (int i = 0; i < 40000; ++i) {
      const SphereShape& s = shapes[spheres[std::size_t(rng.index(int(spheres.size())))]].sphere;
      const Vec3f o = to_f(rng.in_cube(30.0));
      const Vec3d w = to_d(s.center) - to_d(o);
      const double dist = length(w);
      if (dist <= s.radius * 1.01) continue;
      const Vec3d wn = w / dist;
      const Vec3d u = normalize(cross(wn, rng.unit()));
      const double sin_t = s.radius / dist;
      Vec3f d = to_f(wn * std::sqrt(1.0 - sin_t * sin_t) + u * sin_t);
      const auto k = std::size_t(rng.index(3));
      for (int step = rng.index(7) - 3; step != 0; step += step > 0 ? -1 : 1) {
        d[k] = step > 0 ? next_float_up(d[k]) : next_float_down(d[k]);
      }
      check(make_ray(o, d));
    }
    CHECK(hits > rays / 4);
  }
  SECTION("axis-parallel rays, also lying in face planes (0 * inf in the slab test)") {
    for (int i = 0; i < 40000; ++i) {
      Vec3f o = to_f(rng.in_cube(30.0));
      Vec3f d{0, 0, 0};
      const auto axis = std::size_t(rng.index(3));
      if (rng.uniform() < 0.7) {
        d[axis] = rng.uniform() < 0.5 ? -1.0f : 1.0f;
      } else {  // one zero component
        const auto other = (axis + 1) % 3;
        d[axis] = float(rng.uniform(-1.0, 1.0));
        d[other] = float(rng.uniform(-1.0, 1.0));
        d = unit_f(to_d(d));
      }
      // Signed zeros matter for 1/d: use both.
      for (std::size_t k = 0; k < 3; ++k) {
        if (d[k] == 0.0f && rng.uniform() < 0.5) d[k] = -0.0f;
      }
      if (rng.uniform() < 0.6) {
        // Put the origin on a face plane of a box (or on a sphere's extreme point) on every axis
        // the ray does not move along, and usually in line with the shape.
        const Shape& s = shapes[std::size_t(rng.index(int(shapes.size()) - 2))];
        for (std::size_t k = 0; k < 3; ++k) {
          if (d[k] != 0.0f) continue;
          if (s.type == ShapeType::kBox) {
            o[k] = rng.uniform() < 0.5 ? s.box.lo[k] : s.box.hi[k];
          } else {
            o[k] = s.sphere.center[k] + (rng.uniform() < 0.5 ? -s.sphere.radius : s.sphere.radius);
          }
        }
      }
      check(make_ray(o, d));
    }
    CHECK(hits > rays / 10);
  }
  INFO("rays " << rays << ", hits " << hits);
  CHECK(mismatches == 0);
  CHECK(occluded_mismatches == 0);
}

TEST_CASE("BVH equals brute force where a sphere's extreme point meets a box face", "[accel][bvh]") {
  // The hardest case for culling: the ray enters the sphere's bounding box (float slab test) at
  // the same t as the sphere itself (double kernel), and another shape is hit within an ulp of
  // it, so node culling against the best t so far must not be stricter than the kernels.
  TestRng rng{4};
  long mismatches = 0, rays = 0;
  for (int trial = 0; trial < 4000; ++trial) {
    const Vec3f c = to_f(rng.in_cube(rng.log_uniform(1.0, 1e4)));
    const float r = float(rng.log_uniform(1e-2, 1e2));
    const auto axis = std::size_t(rng.index(3));
    const float sign = rng.uniform() < 0.5 ? -1.0f : 1.0f;
    Vec3f e = c;  // the sphere's extreme point on `axis`, as a float
    e[axis] = c[axis] + sign * r;
    // A box with a face through e on another axis, extending away from the sphere.
    const std::size_t other = (axis + 1 + std::size_t(rng.index(2))) % 3;
    Vec3f lo = e - Vec3f{r, r, r}, hi = e + Vec3f{r, r, r};
    if (rng.uniform() < 0.5)
      lo[other] = e[other];
    else
      hi[other] = e[other];
    if (sign > 0)
      lo[axis] = e[axis];
    else
      hi[axis] = e[axis];
    std::vector<Shape> shapes = {sphere(c, r), box(lo, hi)};
    if (rng.uniform() < 0.5) std::swap(shapes[0], shapes[1]);
    const Geometry geo = Geometry::build(shapes);
    for (int i = 0; i < 50; ++i) {
      const Vec3d dir = rng.unit();
      Vec3d from = to_d(e) + dir * (double(r) * rng.uniform(2.0, 50.0));
      from[axis] = e[axis] + sign * std::abs(from[axis] - e[axis]);  // on the sphere's outer side
      const Vec3f o = to_f(from);
      Vec3f d = unit_f(to_d(e) - to_d(o));
      const auto k = std::size_t(rng.index(3));
      for (int step = rng.index(5) - 2; step != 0; step += step > 0 ? -1 : 1) {
        d[k] = step > 0 ? next_float_up(d[k]) : next_float_down(d[k]);
      }
      const Ray ray = make_ray(o, d);
      Hit a, b;
      const bool fa = geo.intersect(ray, a), fb = brute_force(shapes, ray, b);
      ++rays;
      if (fa != fb || (fa && !same_hit(a, b))) {
        if (++mismatches <= 5)
          UNSCOPED_INFO("mismatch " << describe(ray) << " bvh " << a.shape << " brute " << b.shape);
      }
    }
  }
  INFO(rays << " rays");
  CHECK(mismatches == 0);
}

TEST_CASE("Triangle hit records of every scale: packets and single rays give the scalar bits", "[accel][bvh][shapes]") {
  // The SIMD kernels build a triangle hit's record themselves (finish_triangles for packets, a
  // vector of lanes at a time; finish_triangle_hit for single rays), from the winning test's edge
  // functions and the leaf block's vertices; the scalar path tests the triangle again. Meshes at
  // scales from 1e-6 to 1e6, at the origin or far from it, with slivers (a vertex a few float steps
  // off the line of the other two), tiny triangles beside large ones, and zero-area triangles (not
  // prims: they must not shift the others' slots). Rays aimed at every triangle, in 16-ray packets
  // from one eye (the coherent walk) and from scattered origins (the per-lane walk), through
  // intersect, intersect8 and intersect16 on every SIMD isa: every hit record (point, its error
  // bound, normal) must have the scalar path's bits.
  TestRng rng{1616};
  for (const double scale : {1e-6, 1e-3, 1.0, 1e3, 1e6}) {
    for (const double offset : {0.0, 1e3}) {
      INFO("scale " << scale << " offset " << offset);
      const Vec3d base{offset * scale, -0.5 * offset * scale, 0.25 * offset * scale};
      std::vector<Shape> shapes;
      std::vector<Vec3d> aims;  // a point inside each valid triangle
      for (int y = 0; y < 12; ++y) {
        for (int x = 0; x < 12; ++x) {
          const Vec3d corner = base + Vec3d{x * scale, y * scale, rng.uniform(-0.1, 0.1) * scale};
          const double size = scale * (rng.uniform() < 0.3 ? rng.log_uniform(1e-4, 1e-1) : rng.uniform(0.5, 0.9));
          const Vec3f a = to_f(corner), b = to_f(corner + Vec3d{size, rng.uniform(-0.2, 0.2) * size, 0.0});
          Vec3f c = to_f(corner + Vec3d{rng.uniform(-0.2, 0.2) * size, size, rng.uniform(-0.3, 0.3) * size});
          const int kind = (x + 5 * y) % 7;
          if (kind == 3) {
            // A sliver: c a few float steps off the midpoint of a and b.
            const Vec3f mid = to_f((to_d(a) + to_d(b)) * 0.5);
            c = {std::nextafter(std::nextafter(mid.x, kInf), kInf), mid.y, std::nextafter(mid.z, kInf)};
          } else if (kind == 5) {
            shapes.push_back(triangle(a, b, to_f((to_d(a) + to_d(b)) * 0.5)));  // zero area: never hit
          }
          shapes.push_back(triangle(a, b, c));
          aims.push_back((to_d(a) + to_d(b) + to_d(c)) / 3.0);
        }
      }
      const Vec3d eye = base + Vec3d{6.0 * scale, 6.0 * scale, 8.0 * scale};
      std::vector<Ray> rays;
      for (const Vec3d& aim : aims) {
        rays.push_back(make_ray(to_f(eye), unit_f(aim - to_d(to_f(eye)))));
        const Vec3f o = to_f(aim + Vec3d{rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(1, 4)} * scale);
        rays.push_back(make_ray(o, unit_f(aim - to_d(o))));
      }
      // The eye's rays first, then the scattered ones: packets of one kind each.
      std::stable_partition(rays.begin(), rays.end(), [&](const Ray& r) { return r.o == to_f(eye); });
      while (rays.size() % 16 != 0) rays.push_back(rays.front());
      const Geometry ref = Geometry::build(shapes, Isa::kScalar);
      for (const Isa isa : supported_isas()) {
        if (isa == Isa::kScalar) continue;
        INFO("isa " << isa_name(isa));
        const Geometry geo = Geometry::build(shapes, isa);
        long hits = 0, mismatches = 0;
        for (std::size_t at = 0; at < rays.size(); at += 16) {
          Hit h16[16], h8[16];
          const std::uint32_t f16 = geo.intersect16(&rays[at], 0xffffu, h16);
          const std::uint32_t f8_lo = geo.intersect8(&rays[at], 0xffu, h8);
          const std::uint32_t f8 = f8_lo | geo.intersect8(&rays[at + 8], 0xffu, h8 + 8) << 8;
          for (int i = 0; i < 16; ++i) {
            Hit want, one;
            const bool w = ref.intersect(rays[at + std::size_t(i)], want);
            const bool g = geo.intersect(rays[at + std::size_t(i)], one);
            hits += w;
            const bool bad = g != w || bool(f16 >> i & 1u) != w || bool(f8 >> i & 1u) != w ||
                             (w && (!same_hit(want, one) || !same_hit(want, h16[i]) || !same_hit(want, h8[i])));
            if (bad && ++mismatches <= 3) UNSCOPED_INFO("mismatch " << describe(rays[at + std::size_t(i)]));
          }
        }
        CHECK(hits > long(rays.size()) * 3 / 4);
        CHECK(mismatches == 0);
      }
    }
  }
}

TEST_CASE("Hit records: on the surface within p_error, unit normals", "[accel][shapes]") {
  TestRng rng{5};
  const std::vector<Shape> shapes = random_scene(rng, 300);
  const Geometry geo = Geometry::build(shapes);
  long hits = 0, bad = 0;
  for (int i = 0; i < 20000; ++i) {
    Hit h;
    const Vec3f o = to_f(rng.in_cube(30.0));
    if (!geo.intersect(make_ray(o, unit_f(rng.unit())), h)) continue;
    ++hits;
    const Shape& s = shapes[h.shape];
    // Distance of p from the exact surface (double), against the error bound projected on n.
    double dist = 0.0;
    if (s.type == ShapeType::kSphere) {
      dist = std::abs(length(to_d(h.p) - to_d(s.sphere.center)) - s.sphere.radius);
    } else if (s.type == ShapeType::kPlane) {
      dist = std::abs(dot(to_d(h.p) - to_d(s.plane.point), to_d(s.plane.normal))) / length(to_d(s.plane.normal));
    } else {
      // p must lie on the box surface exactly: inside on every axis, on a face on the normal's.
      bool inside = true;
      for (std::size_t k = 0; k < 3; ++k) inside = inside && h.p[k] >= s.box.lo[k] && h.p[k] <= s.box.hi[k];
      const std::size_t axis = std::abs(h.n.x) == 1 ? 0 : (std::abs(h.n.y) == 1 ? 1 : 2);
      const float face = h.n[axis] > 0 ? s.box.hi[axis] : s.box.lo[axis];
      dist = inside && h.p[axis] == face ? 0.0 : 1.0;
    }
    const double bound = dot(to_d(abs(h.n)), to_d(h.p_error));
    const bool ok = hit_is_finite(h) && std::abs(length(to_d(h.n)) - 1.0) < 1e-6 && dist <= bound;
    if (!ok && ++bad <= 5) UNSCOPED_INFO("shape " << h.shape << " dist " << dist << " bound " << bound);
  }
  CHECK(hits > 5000);
  CHECK(bad == 0);
}

TEST_CASE("BVH build: stats, degenerate inputs, depth cap", "[accel][bvh]") {
  SECTION("empty scene") {
    const Geometry geo = Geometry::build({});
    Hit h;
    CHECK_FALSE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}), h));
    CHECK_FALSE(geo.occluded(make_ray({0, 0, 0}, {0, 0, 1})));
    CHECK(geo.stats().nodes == 0);
    CHECK(geo.stats().leaves == 0);
  }
  SECTION("planes only") {
    const Geometry geo = Geometry::build({plane({0, 0, 0}, {0, 1, 0}), plane({0, 10, 0}, {0, -1, 0})});
    CHECK(geo.stats().nodes == 0);
    Hit h;
    REQUIRE(geo.intersect(make_ray({0, 3, 0}, {0, 1, 0}), h));
    CHECK(h.shape == 1);
    CHECK(h.t == 7.0f);
    REQUIRE(geo.intersect(make_ray({0, 3, 0}, {0, -1, 0}), h));
    CHECK(h.shape == 0);
  }
  SECTION("random spheres: sane shape of the tree") {
    TestRng rng{3};
    std::vector<Shape> shapes;
    const std::uint32_t n = 20000;
    for (std::uint32_t i = 0; i < n; ++i) {
      const Vec3f c = to_f(rng.in_cube(100.0));
      shapes.push_back(sphere(c, float(rng.uniform(0.1, 1.0))));
    }
    const Geometry geo = Geometry::build(shapes);
    const BuildStats& st = geo.stats();
    INFO("nodes " << st.nodes << " leaves " << st.leaves << " depth " << st.max_depth << " build " << st.seconds
                  << " s");
    CHECK(st.nodes == 2 * st.leaves - 1);
    CHECK(st.leaves >= n / 4);
    CHECK(st.leaves <= n);
    CHECK(st.max_depth >= 12);  // log2(n / 4)
    CHECK(st.max_depth < 40);
    CHECK(st.seconds >= 0.0);
  }
  SECTION("coincident centroids: median split, still correct") {
    std::vector<Shape> shapes;
    for (int i = 0; i < 1000; ++i) shapes.push_back(sphere({1, 2, 3}, 0.5f + 0.001f * float(i % 17)));
    const Geometry geo = Geometry::build(shapes);
    CHECK(geo.stats().max_depth <= 12);
    CHECK(geo.stats().leaves >= 250);
    Hit a, b;
    for (const Vec3f d : {Vec3f{0, 0, 1}, Vec3f{0, 0, -1}, unit_f({1, 1, 1})}) {
      const Ray ray = make_ray(to_f(to_d(Vec3f{1, 2, 3}) - to_d(d) * 10.0), d);
      REQUIRE(geo.intersect(ray, a));
      REQUIRE(brute_force(shapes, ray, b));
      CHECK(same_hit(a, b));
    }
  }
  SECTION("geometric clustering: depth stays capped, results still exact") {
    // Centres at 0.7^i: every level of the tree sees the same relative layout, so the SAH peels a
    // few shapes per level and the tree would be ~100 levels deep without the cap.
    std::vector<Shape> shapes;
    double x = 1.0;
    for (int i = 0; i < 240; ++i, x *= 0.7) shapes.push_back(sphere({float(x), 0, 0}, float(0.01 * x)));
    const Geometry geo = Geometry::build(shapes);
    INFO("depth " << geo.stats().max_depth);
    CHECK(geo.stats().max_depth <= Geometry::kMaxDepth - 1);
    TestRng rng{8};
    long mismatches = 0;
    for (int i = 0; i < 5000; ++i) {
      const Shape& s = shapes[std::size_t(rng.index(240))];
      const Vec3f o = to_f(to_d(s.sphere.center) + rng.unit() * (s.sphere.radius * 3.0));
      const Ray ray = make_ray(o, unit_f(to_d(s.sphere.center) + rng.unit() * (s.sphere.radius * 0.5) - to_d(o)));
      Hit a, b;
      const bool fa = geo.intersect(ray, a), fb = brute_force(shapes, ray, b);
      mismatches += fa != fb || (fa && !same_hit(a, b));
    }
    CHECK(mismatches == 0);
  }
}

TEST_CASE("BVH build's thread pool: every item once, loop after loop, and its exceptions", "[accel][bvh][threads]") {
  // The build hands its pool a few hundred short loops (util/thread_pool.h); a worker that wakes
  // late must neither miss a loop's item nor run one twice, nor look at a loop that has returned.
  for (const unsigned size : {1u, 2u, 4u}) {
    dtraced::util::ThreadPool pool(size);
    INFO("pool of " << size);
    CHECK(pool.size() >= 1);
    CHECK(pool.size() <= size);
    std::vector<int> runs(1000);
    for (int loop = 0; loop < 300; ++loop) {
      const std::size_t count = std::size_t(loop % 7 == 0 ? 1 : 1 + loop * 3);
      pool.parallel_for(count, loop % 5 == 0 ? 1u : size, [&](std::size_t i) { ++runs[i]; });
      bool each_once = true;
      for (std::size_t i = 0; i < runs.size(); ++i) each_once = each_once && runs[i] == (i < count ? 1 : 0);
      INFO("loop " << loop << ", items " << count);
      REQUIRE(each_once);
      std::fill(runs.begin(), runs.end(), 0);
    }
    pool.parallel_for(0, size, [&](std::size_t) { FAIL("no item"); });
    // An exception stops the loop and is thrown to the caller; the pool runs the next loop whole.
    CHECK_THROWS_AS(pool.parallel_for(500, size,
                                      [](std::size_t i) {
                                        if (i == 37) throw std::runtime_error("item 37");
                                      }),
                    std::runtime_error);
    std::vector<int> after(500);
    pool.parallel_for(after.size(), size, [&](std::size_t i) { after[i] = int(i); });
    bool whole = true;
    for (std::size_t i = 0; i < after.size(); ++i) whole = whole && after[i] == int(i);
    CHECK(whole);
  }
}

TEST_CASE("BVH build: the same tree on any number of threads", "[accel][bvh][threads]") {
  // Large enough that the top level is split by all threads, the ranges of 2^15 prims or more
  // (bvh.cpp's kParallelGrain) and at most a thread's share each by one thread, and the rest by one
  // thread per subtree: mixed shapes, duplicates, a cluster of coincident centres and a geometric
  // cluster that drives one subtree deep.
  TestRng rng{16};
  std::vector<Shape> shapes = random_scene(rng, 120000);
  for (int i = 0; i < 5000; ++i) shapes.push_back(sphere({3, 4, 5}, 0.25f + 0.001f * float(i % 7)));
  double x = 1.0;
  for (int i = 0; i < 200; ++i, x *= 0.7) shapes.push_back(sphere({float(x) - 10, 0, 0}, float(0.01 * x)));
  std::uint64_t scalar_two_threads_hash = 0;
  for (const Isa isa : {Isa::kScalar, best_isa()}) {
    const Geometry one = Geometry::build(shapes, isa, 1);
    INFO("isa " << isa_name(isa) << ", nodes " << one.stats().nodes << ", depth " << one.stats().max_depth);
    CHECK(one.stats().nodes == 2 * one.stats().leaves - 1);
    CHECK(one.stats().nodes > 2 * (1u << 15) / 4);
    // 0 is "every CPU": on a 2-core machine the same as 2, elsewhere a count of its own.
    for (const unsigned threads : {3u, 0u}) {
      const Geometry many = Geometry::build(shapes, isa, threads);
      INFO("threads " << threads);
      CHECK(many.stats().tree_hash == one.stats().tree_hash);
      CHECK(many.stats().nodes == one.stats().nodes);
      CHECK(many.stats().leaves == one.stats().leaves);
      CHECK(many.stats().max_depth == one.stats().max_depth);
      CHECK(many.stats().outside == one.stats().outside);
      CHECK(many.stats().wide_nodes == one.stats().wide_nodes);
    }
    // Two threads, and the tree answers as brute force does (1,000 rays against 125,000 shapes:
    // the brute force is what makes this test slow under the sanitizers; the smaller scenes
    // above test the tree against it with many more rays).
    const Geometry two = Geometry::build(shapes, isa, 2);
    CHECK(two.stats().tree_hash == one.stats().tree_hash);
    CHECK(two.stats().nodes == one.stats().nodes);
    CHECK(two.stats().wide_nodes == one.stats().wide_nodes);
    if (isa == Isa::kScalar) scalar_two_threads_hash = two.stats().tree_hash;
    const Agreement agreed = agree_with_brute_force(two, shapes, rng, 1000);
    CHECK(agreed.hits > 100);
    CHECK(agreed.mismatches == 0);
  }
  // A different tree gives a different hash (the hash can fail).
  std::vector<Shape> fewer(shapes.begin(), shapes.end() - 1);
  CHECK(Geometry::build(fewer, Isa::kScalar, 2).stats().tree_hash != scalar_two_threads_hash);
}

#if defined(__linux__)
namespace {
// The address space this process has mapped (VmSize), in bytes; 0 if /proc has none.
std::size_t mapped_bytes() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmSize:", 0) == 0) return std::size_t(std::stoull(line.substr(7))) * 1024;  // "VmSize: 123 kB"
  }
  return 0;
}

// The shapes of the memory test below, the same in its process and in the children it starts.
std::vector<Shape> memory_test_shapes() {
  TestRng rng{5};
  std::vector<Shape> shapes;
  for (int i = 0; i < 100000; ++i) shapes.push_back(sphere(to_f(rng.in_cube(20.0)), float(rng.log_uniform(0.01, 1.0))));
  return shapes;
}

// Geometry::build(shapes, kScalar, 2) in a process of its own whose address space may grow by
// `extra` bytes at most: 0 if it built `hash`'s tree, 2 if it threw std::bad_alloc, and anything
// else (another exit code, or a signal such as the alarm that ends a build stuck waiting) as
// `status` shows it. The child executes this test binary again (the hidden test case below), not
// a fork of this process: after the tests before it in the same process, glibc's heap held freed
// memory and cached thread stacks that the build reused without mapping anything, out of the
// cap's reach (the whole binary in one process: the build succeeded with 64 KiB of room, and no
// run threw).
int build_within(std::size_t extra, std::uint64_t hash) {
  // Everything the child needs is made before the fork: it only calls execve (no allocation or
  // environment lock between fork and exec).
  std::vector<std::string> env_text = {"DTRACED_TEST_BUILD_ROOM=" + std::to_string(extra),
                                       "DTRACED_TEST_BUILD_HASH=" + std::to_string(hash)};
  for (char** e = environ; *e != nullptr; ++e) env_text.emplace_back(*e);
  std::vector<char*> env;
  for (std::string& e : env_text) env.push_back(e.data());
  env.push_back(nullptr);
  std::string arg0 = "test_accel", arg1 = "[build-within-child]", arg2 = "--out", arg3 = "/dev/null";
  char* const argv[] = {arg0.data(), arg1.data(), arg2.data(), arg3.data(), nullptr};
  const pid_t pid = fork();
  if (pid == 0) {
    execve("/proc/self/exe", argv, env.data());
    _exit(7);  // exec failed
  }
  int status = 0;
  if (pid < 0 || waitpid(pid, &status, 0) != pid) return -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + (WIFSIGNALED(status) ? WTERMSIG(status) : 0);
}
}  // namespace

TEST_CASE("BVH build: memory running out anywhere in a 2-thread build throws std::bad_alloc", "[accel][bvh][threads]") {
  // Every allocation of the build may fail: on a worker of the pool, in the queue of ranges the
  // threads split and build (bvh.cpp's split_pending: the failing thread wakes the others, they
  // stop, the pool throws), or on the calling thread. Whatever fails, the build must throw
  // std::bad_alloc, neither hang (a thread left waiting for a range), nor end the process, nor hand
  // back a wrong tree. Each build runs in a child process whose address space is capped a little
  // further each time, from where the first allocations fail up to where the build succeeds.
  // AddressSanitizer's allocator aborts instead of throwing when it runs out: not under it.
  if (dlsym(RTLD_DEFAULT, "__asan_init") != nullptr) {
    WARN("skipped: AddressSanitizer aborts when an allocation fails");
    return;
  }
  const std::uint64_t hash = Geometry::build(memory_test_shapes(), Isa::kScalar, 1).stats().tree_hash;
  // The least room in which the build succeeds, to within 64 KiB (a thread's stack alone is 8 MiB).
  std::size_t low = 0, high = std::size_t(1) << 30;
  REQUIRE(build_within(high, hash) == 0);
  while (high - low > (std::size_t(64) << 10)) {
    const std::size_t mid = low + (high - low) / 2;
    const int code = build_within(mid, hash);
    INFO("room " << mid << ", exit " << code);
    REQUIRE((code == 0 || code == 2));
    (code == 0 ? high : low) = mid;
  }
  // Below it, in steps of 128 KiB down to 12 MiB less, each allocation the build makes fails in
  // some run (in the queue's, about 80 of the 96 runs while this test was written): each run must
  // build the tree or throw. (A run with less room may still succeed: its pool may have started
  // no worker, whose stack is the largest mapping of all.)
  const std::size_t step = std::size_t(128) << 10;
  int runs = 0, threw = 0;
  for (std::size_t below = step; below < high && below <= (std::size_t(12) << 20); below += step) {
    const std::size_t room = high - below;
    const int code = build_within(room, hash);
    INFO("room " << room << ", exit " << code);
    REQUIRE((code == 0 || code == 2));
    ++runs;
    threw += code == 2;
  }
  CHECK(runs > 0);
  CHECK(threw > 0);
}

// The child of build_within (hidden: run only by that tag): caps its own address space at what it
// has mapped plus DTRACED_TEST_BUILD_ROOM bytes and builds; the exit code is the answer.
TEST_CASE("BVH build: one build under an address-space cap (build_within's child)", "[.][build-within-child]") {
  const char* room = std::getenv("DTRACED_TEST_BUILD_ROOM");
  const char* hash = std::getenv("DTRACED_TEST_BUILD_HASH");
  if (room == nullptr || hash == nullptr) _exit(8);
  alarm(60);  // a build that waits forever is killed (SIGALRM)
  const std::vector<Shape> shapes = memory_test_shapes();
  const std::size_t limit = mapped_bytes() + std::size_t(std::stoull(room));
  const rlimit r{limit, limit};
  int code = 6;
  if (setrlimit(RLIMIT_AS, &r) == 0) {
    try {
      code = Geometry::build(shapes, Isa::kScalar, 2).stats().tree_hash == std::stoull(hash) ? 0 : 4;
    } catch (const std::bad_alloc&) {
      code = 2;
    } catch (...) {
      code = 5;
    }
  }
  _exit(code);
}
#endif

TEST_CASE("BVH build: the 8-wide collapse fills its nodes on any number of threads", "[accel][bvh][threads]") {
  // wide_build.cpp picks the binary nodes that become 8-wide nodes by the least sum of their areas
  // (a dynamic program over the binary tree); the binary leaves stay the wide tree's leaves. The
  // greedy collapse before it (open the largest child until 8) made 9,411 wide nodes for these
  // 35,005 leaves, the SAH one 8,875 (on the benchmark's 1M-triangle mesh 108,163 against 67,543):
  // the bound fails for the greedy collapse.
  TestRng rng{23};
  const std::vector<Shape> shapes = random_scene(rng, 60000);
  int built = 0;
  for (const Isa isa : supported_isas()) {
    if (isa == Isa::kScalar) continue;  // no wide tree
    ++built;
    INFO("isa " << isa_name(isa));
    const Geometry one = Geometry::build(shapes, isa, 1);
    INFO("wide nodes " << one.stats().wide_nodes << ", leaves " << one.stats().leaves);
    CHECK(std::uint64_t(one.stats().wide_nodes) * 100 < std::uint64_t(one.stats().leaves) * 26);
    CHECK(std::uint64_t(one.stats().wide_nodes) * 7 >= one.stats().leaves - 1);  // 8 children at most
    for (const unsigned threads : {2u, 3u}) {
      const Geometry many = Geometry::build(shapes, isa, threads);
      CHECK(many.stats().tree_hash == one.stats().tree_hash);
      CHECK(many.stats().wide_nodes == one.stats().wide_nodes);
    }
    const Agreement agreed = agree_with_brute_force(one, shapes, rng, 1000);
    CHECK(agreed.hits > 100);
    CHECK(agreed.mismatches == 0);
  }
  // Every x86-64 CPU since 2008 has SSE4.1; one without builds no wide tree, and this test then
  // checks nothing: it says so instead of passing quietly.
  if (built == 0) FAIL("no SIMD instruction set on this CPU: the 8-wide collapse is never built");
}

TEST_CASE("BVH build: the same tree as recorded, signed zeros too", "[accel][bvh][threads]") {
  // The order the build leaves the prims in and the bits of its node bounds are the tree (and the
  // images follow from it): a change to how the build moves prims or gathers bounds must give the
  // same tree, which the thread-count test cannot see when every thread count changes alike.
  // These trees were recorded before the build's partition and its bounds passes were rewritten
  // (std::partition, scalar minima and maxima), as 0x101739fc48683614 and 0xdbaa80ccc0138861 under
  // the first tree hash (one serial chain); the hashes below are the same trees' under the hash of
  // pieces, checked against those when it replaced it.
  // Besides mixed shapes it has boxes whose faces and centres lie on +0 or -0: extending bounds
  // keeps the first of equal values it meets, so their bits depend on the order of extension.
  // Only uniform numbers and + - * make the scene: the same on every C library.
  TestRng rng{2026};
  std::vector<Shape> shapes;
  const auto signed_zero = [&rng] { return rng.uniform() < 0.5 ? -0.0f : 0.0f; };
  for (int i = 0; i < 36000; ++i) {
    const Vec3d c = rng.in_cube(20.0);
    const double size = 0.01 + 4.0 * rng.uniform() * rng.uniform() * rng.uniform();
    if (rng.uniform() < 0.55) {
      shapes.push_back(sphere(to_f(c), float(size)));
    } else {
      const Vec3d h{size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0), size * rng.uniform(0.2, 1.0)};
      shapes.push_back(box(to_f(c - h), to_f(c + h)));
    }
  }
  for (int i = 0; i < 4000; ++i) {
    const Vec3d extent{rng.uniform(0.1, 2.0), rng.uniform(0.1, 2.0), rng.uniform(0.1, 2.0)};
    Vec3f lo = to_f(rng.in_cube(20.0));
    Vec3f hi = to_f(to_d(lo) + extent);
    const auto a = std::size_t(rng.index(3));
    // Resting on a plane through the origin, or flat on it (then its centre is +-0 too).
    lo[a] = signed_zero();
    hi[a] = rng.uniform() < 0.5 ? signed_zero() : float(extent[a]);
    shapes.push_back(box(lo, hi));
  }
  for (int i = 0; i < 300; ++i) shapes.push_back(sphere({-0.0f, 0.0f, -0.0f}, 0.5f + 0.01f * float(i % 5)));
  const std::uint64_t scalar_hash = 0x101ac2a522844e8d, simd_hash = 0x766d8e0bf008fb68;
  for (const Isa isa : supported_isas()) {
    for (const unsigned threads : {1u, 2u}) {
      const Geometry geo = Geometry::build(shapes, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads << ", tree " << std::hex << geo.stats().tree_hash);
      CHECK(geo.stats().nodes > 2 * (1u << 15) / 4);  // large enough for the top levels' split by all threads
      // The SAH's leaf cost differs between the scalar and the SIMD kernels; all SIMD sets share it.
      CHECK(geo.stats().tree_hash == (isa == Isa::kScalar ? scalar_hash : simd_hash));
    }
  }
}

TEST_CASE("BVH build: the recorded trees with shapes that are not prims between the prims", "[accel][bvh][threads]") {
  // The root's bounds come from the pass that makes the prims, gathered per chunk of shapes, while
  // the splits gather them per chunk of prims: planes and invalid shapes between the prims shift
  // the one against the other. Both keep the first of equal values in prim order (+0 and -0 here),
  // so the same bits and the same tree. Hashes recorded before the root's bounds were taken from
  // that pass; scene (a) holds boxes, whose bounds are their faces, (b) only spheres and planes,
  // which a SIMD build sets aside.
  TestRng rng{2027};
  std::vector<Shape> mixed, spheres;
  const auto signed_zero = [&rng] { return rng.uniform() < 0.5 ? -0.0f : 0.0f; };
  for (int i = 0; i < 37000; ++i) {
    const Vec3d c = rng.in_cube(20.0);
    const double size = 0.01 + 2.0 * rng.uniform() * rng.uniform();
    if (i % 4 == 0) {
      Vec3f lo = to_f(c), hi = to_f(c + Vec3d{size, size, size});
      const auto a = std::size_t(rng.index(3));
      lo[a] = signed_zero();  // a face on a plane through the origin
      mixed.push_back(box(lo, hi));
    } else {
      mixed.push_back(sphere(to_f(c), float(size)));
    }
    spheres.push_back(sphere(to_f(rng.in_cube(20.0)), float(size)));
    if (i % 5003 == 7) {
      for (std::vector<Shape>* v : {&mixed, &spheres})
        v->push_back(plane({0, -30.0f - float(i) * 1e-3f, 0}, {0, 1, 0}));
    }
    if (i % 7919 == 3) {
      for (std::vector<Shape>* v : {&mixed, &spheres}) v->push_back(sphere(to_f(rng.in_cube(20.0)), -1.0f));  // invalid
    }
  }
  const std::uint64_t mixed_scalar = 0x7467db524bd55cc8, mixed_simd = 0x9df9b655f773d901;
  const std::uint64_t spheres_scalar = 0x716fe557bf17b10a, spheres_simd = 0x15e6171c65ecb5c8;
  for (const Isa isa : supported_isas()) {
    for (const unsigned threads : {1u, 2u}) {
      const Geometry a = Geometry::build(mixed, isa, threads);
      const Geometry b = Geometry::build(spheres, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads << ", trees " << std::hex << a.stats().tree_hash << " "
                  << b.stats().tree_hash);
      CHECK(a.stats().outside == 8);  // the planes (the invalid spheres are nowhere)
      CHECK(a.stats().tree_hash == (isa == Isa::kScalar ? mixed_scalar : mixed_simd));
      CHECK(b.stats().tree_hash == (isa == Isa::kScalar ? spheres_scalar : spheres_simd));
    }
  }
}

TEST_CASE("BVH build: a large sphere scene gets back its very shapes, and the recorded tree", "[accel][bvh][threads]") {
  // A SIMD build of 2^15 spheres or more holds no Shape array while it builds (bvh.cpp's SetAside):
  // the spheres are put back from the wide tree's blocks, the planes, invalid spheres and huge
  // spheres from what was set aside, and the collapse reads the spheres by id (no prims; the ids'
  // pages are given back only from 262,144 spheres on: the next test). Every byte of every shape
  // must come back, the queries must be exact, and the tree must be the one recorded before the
  // build's memory was reordered (this hash; 0x0911f182e5874ac5 under the first, serial tree
  // hash).
  TestRng rng{7};
  std::vector<Shape> shapes;
  for (int i = 0; i < 36000; ++i) {
    shapes.push_back(sphere(to_f(rng.in_cube(20.0)), float(rng.log_uniform(0.01, 1.5))));
    if (i % 9000 == 17) shapes.push_back(plane({0, float(i) * -1e-3f - 25.0f, 0}, {0, 1, 0}));
    if (i % 12000 == 5) shapes.push_back(sphere(to_f(rng.in_cube(20.0)), i % 2 == 0 ? 0.0f : -1.0f));  // invalid
    if (i % 18000 == 11) shapes.push_back(sphere(to_f(rng.in_cube(5.0)), 400.0f));  // huge: beside the tree
  }
  std::vector<Shape> with_box = shapes;  // a box: no set-aside, the shapes are held as they are
  with_box.push_back(box({-1, -1, -1}, {1, 1, 1}));
  const std::uint64_t simd_hash = 0x9d379940ae153d72;
  for (const Isa isa : supported_isas()) {
    if (isa == Isa::kScalar) continue;
    for (const unsigned threads : {1u, 2u}) {
      const Geometry geo = Geometry::build(shapes, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads << ", tree " << std::hex << geo.stats().tree_hash);
      CHECK(geo.stats().tree_hash == simd_hash);
      CHECK(geo.stats().outside == 4 + 2);  // the planes and the huge spheres
      check_shapes_back_and_exact(geo, shapes, rng, 500, 100);
    }
    // Collapsed on two threads with prims of two kinds (the box takes a leaf record): the shapes
    // back, exact queries, and as many wide nodes as on one thread.
    const Geometry held = Geometry::build(with_box, isa, 2);
    check_shapes_back_and_exact(held, with_box, rng, 300, 50);
    CHECK(held.stats().wide_nodes == Geometry::build(with_box, isa, 1).stats().wide_nodes);
    // More planes than a scene may set aside (4096): held too, and the tree is the same one (the
    // planes, last, are beside it; the spheres keep their ids).
    std::vector<Shape> many_planes = shapes;
    for (int i = 0; i < 4097; ++i) many_planes.push_back(plane({0, -30.0f - float(i) * 1e-3f, 0}, {0, 1, 0}));
    for (const unsigned threads : {1u, 2u}) {
      const Geometry planes_held = Geometry::build(many_planes, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads << ", tree " << std::hex
                  << planes_held.stats().tree_hash);
      CHECK(planes_held.stats().tree_hash == simd_hash);
      CHECK(planes_held.stats().outside == 4 + 2 + 4097);
      REQUIRE(planes_held.shapes().size() == many_planes.size());
      CHECK(std::memcmp(planes_held.shapes().data(), many_planes.data(), many_planes.size() * sizeof(Shape)) == 0);
    }
  }
}

TEST_CASE("BVH build: a set-aside scene large enough to give its ids' pages back", "[accel][bvh][threads]") {
  // From 262,144 set-aside spheres on, the collapse's ids (4 bytes a sphere) reach ReadOnce's 1 MiB
  // (wide_build.cpp), and it gives their pages back as it reads them, on every collapse thread. The
  // tree must be the one the same spheres get when the scene keeps its shapes (more planes than a
  // scene may set aside: the spheres keep their ids, the planes lie beside the tree), every shape
  // must come back byte for byte, and the queries must be exact. One isa: the collapse is the same
  // code for all of them.
  TestRng rng{23};
  std::vector<Shape> shapes;
  shapes.reserve(300000 + 4097);
  for (int i = 0; i < 300000; ++i)
    shapes.push_back(sphere(to_f(rng.in_cube(25.0)), float(rng.log_uniform(0.005, 0.5))));
  std::vector<Shape> kept = shapes;
  for (int i = 0; i < 4097; ++i) kept.push_back(plane({0, -40.0f - float(i) * 1e-3f, 0}, {0, 1, 0}));
  const Isa isa = best_isa();
  REQUIRE(isa != Isa::kScalar);
  for (const unsigned threads : {1u, 2u}) {
    INFO("isa " << isa_name(isa) << ", threads " << threads);
    const Geometry aside = Geometry::build(shapes, isa, threads);
    const Geometry held = Geometry::build(kept, isa, threads);
    CHECK(aside.stats().tree_hash == held.stats().tree_hash);
    CHECK(aside.stats().wide_nodes == held.stats().wide_nodes);
    check_shapes_back_and_exact(aside, shapes, rng, 100, 20);
  }
}

TEST_CASE("BVH build: a set-aside sphere scene whose spheres all coincide", "[accel][bvh][threads]") {
  // 2^15 spheres or more are set aside (bvh.cpp's SetAside) and collapsed from the spheres by id,
  // with no prims. Spheres that all coincide give the binned splits nothing to separate (the build
  // falls back to splitting the ids in halves): the shapes still come back byte for byte and every
  // query answers as brute force does, ties between equal spheres to the smallest id.
  std::vector<Shape> shapes(33000, sphere({1.0f, 2.0f, 3.0f}, 20.0f));
  TestRng rng{11};
  for (const Isa isa : supported_isas()) {
    if (isa == Isa::kScalar) continue;
    for (const unsigned threads : {1u, 2u}) {
      const Geometry geo = Geometry::build(shapes, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads);
      CHECK(geo.stats().wide_nodes > 1);
      check_shapes_back_and_exact(geo, shapes, rng, 200, 20);
    }
  }
}

TEST_CASE("BVH build: huge shapes leave the tree from whichever chunk holds them", "[accel][bvh][threads]") {
  // The build looks for huge shapes (surface area above a quarter of the scene's) only in the
  // chunks of 2^14 shapes whose largest extents could give one; this scene has them in several
  // chunks, huge by two long axes or by three, beside boxes long on one axis only (not huge) and
  // boxes just below the limit, and the test counts the huge ones itself.
  TestRng rng{23};
  std::vector<Shape> shapes;
  for (int i = 0; i < 40000; ++i) {
    shapes.push_back(sphere(to_f(rng.in_cube(50.0)), float(rng.log_uniform(0.01, 0.5))));
    switch (i) {
      case 3:      // huge by two axes
      case 20001:  // the second chunk
        shapes.push_back(box({-60, -60, 0}, {60, 60, 0.01f}));
        break;
      case 37000:  // the third chunk: huge by three axes
        shapes.push_back(box({-45, -45, -45}, {45, 45, 45}));
        break;
      case 9000:  // long on one axis only
      case 30000:
        shapes.push_back(box({-100, 0, 0}, {100, 0.01f, 0.01f}));
        break;
      case 25000:  // about half the limit
        shapes.push_back(box({-41, -41, 0}, {41, 41, 0.01f}));
        break;
      default:
        break;
    }
  }
  const auto area = [](const Bounds3f& b) {
    const double ex = double(b.hi.x) - b.lo.x, ey = double(b.hi.y) - b.lo.y, ez = double(b.hi.z) - b.lo.z;
    return 2.0 * (ex * ey + ey * ez + ez * ex);
  };
  Bounds3f all;
  for (const Shape& s : shapes) all.extend(shape_bounds(s));
  std::uint32_t huge = 0;
  for (const Shape& s : shapes) huge += area(shape_bounds(s)) > 0.25 * area(all);
  REQUIRE(huge == 3);
  for (const Isa isa : {Isa::kScalar, best_isa()}) {
    for (const unsigned threads : {1u, 2u}) {
      const Geometry geo = Geometry::build(shapes, isa, threads);
      INFO("isa " << isa_name(isa) << ", threads " << threads);
      CHECK(geo.stats().outside == huge);
      const Agreement agreed = agree_with_brute_force(geo, shapes, rng, 300);
      CHECK(agreed.hits > 50);
      CHECK(agreed.mismatches == 0);
    }
  }
}

TEST_CASE("Timing: 1280x720 camera rays into 100,000 spheres (reported, not asserted)", "[accel][timing]") {
  TestRng rng{11};
  std::vector<Shape> shapes;
  for (int i = 0; i < 100000; ++i) {
    const Vec3f c = to_f(rng.in_cube(100.0));
    shapes.push_back(sphere(c, float(rng.uniform(0.2, 1.0))));
  }
  const Geometry geo = Geometry::build(shapes);
  const BuildStats& st = geo.stats();

  constexpr int kW = 1280, kH = 720;
  const Vec3f eye{0, 0, -160};
  const double tan_half = std::tan(30.0 * std::numbers::pi / 180.0);
  const auto start = std::chrono::steady_clock::now();
  long hits = 0;
  double t_sum = 0.0;
  for (int y = 0; y < kH; ++y) {
    for (int x = 0; x < kW; ++x) {
      const double u = (2.0 * (x + 0.5) / kW - 1.0) * tan_half * kW / kH;
      const double v = (1.0 - 2.0 * (y + 0.5) / kH) * tan_half;
      Hit h;
      if (geo.intersect(make_ray(eye, unit_f({u, v, 1.0})), h)) {
        ++hits;
        t_sum += h.t;
      }
    }
  }
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  WARN("BVH over 100000 spheres: build " << st.seconds * 1e3 << " ms, " << st.nodes << " nodes, " << st.leaves
                                         << " leaves, depth " << st.max_depth << "; " << kW * kH
                                         << " camera rays traced in " << seconds << " s (" << kW * kH / seconds / 1e6
                                         << " Mrays/s single-threaded), " << hits << " hits, mean t "
                                         << t_sum / double(std::max(1L, hits)));
  CHECK(hits > kW * kH / 2);
}
