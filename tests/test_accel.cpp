// Tests of dtraced::accel: BVH against brute force (same shape, same t bits), far-sphere accuracy
// against an exact long-double reference, grazing rays, self-intersection after
// offset_ray_origin, inside/flat/t_min cases, build statistics, and a timing report.
// Pass/fail only on correctness; timings are printed, never asserted.
#include <algorithm>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "math/float_util.h"
#include "math/rng.h"
#include "math/vec.h"

using namespace dtraced::accel;
using dtraced::math::next_float_down;
using dtraced::math::next_float_up;
using dtraced::math::Vec3d;

namespace {

constexpr float kInf = std::numeric_limits<float>::infinity();

// Counter-based test random numbers (a local object per test: no shared state). Draw at most one
// number per full expression: the order operands and arguments are evaluated in is unspecified,
// and the scenes must not depend on the compiler or the optimisation level.
struct TestRng {
  std::uint64_t state;
  std::uint64_t next() { return dtraced::math::mix64(state += 0x9e3779b97f4a7c15ULL); }
  double uniform() { return double(next() >> 11) * 0x1p-53; }  // [0, 1)
  double uniform(double a, double b) { return a + (b - a) * uniform(); }
  double log_uniform(double a, double b) { return std::exp(uniform(std::log(a), std::log(b))); }
  int index(int n) { return int(uniform() * n); }
  Vec3d unit() {
    const double z = uniform(-1.0, 1.0);
    const double phi = uniform(0.0, 2.0 * std::numbers::pi);
    const double s = std::sqrt(std::max(0.0, 1.0 - z * z));
    return {s * std::cos(phi), s * std::sin(phi), z};
  }
  Vec3d in_cube(double h) { return {uniform(-h, h), uniform(-h, h), uniform(-h, h)}; }
};

Vec3f to_f(const Vec3d& v) { return Vec3f(v); }
Vec3d to_d(const Vec3f& v) { return Vec3d(v); }
Vec3f unit_f(const Vec3d& v) { return to_f(normalize(v)); }

Shape sphere(const Vec3f& c, float r) {
  Shape s;
  s.type = ShapeType::kSphere;
  s.sphere = {c, r};
  return s;
}
Shape box(const Vec3f& lo, const Vec3f& hi) {
  Shape s;
  s.type = ShapeType::kBox;
  s.box = {lo, hi};
  return s;
}
Shape plane(const Vec3f& p, const Vec3f& n) {
  Shape s;
  s.type = ShapeType::kPlane;
  s.plane = {p, n};
  return s;
}
Ray make_ray(const Vec3f& o, const Vec3f& d, float t_min = 0.0f, float t_max = kInf) {
  Ray r;
  r.o = o;
  r.d = d;
  r.t_min = t_min;
  r.t_max = t_max;
  return r;
}

// Reference: every shape in id order, keeping strictly nearer hits (so ties go to the smaller id).
bool brute_force(const std::vector<Shape>& shapes, Ray ray, Hit& hit) {
  bool found = false;
  for (std::uint32_t id = 0; id < shapes.size(); ++id) {
    Hit h;
    if (intersect_shape(shapes[id], id, ray, h)) {
      hit = h;
      ray.t_max = h.t;
      found = true;
    }
  }
  return found;
}

bool same_bits(float a, float b) { return std::bit_cast<std::uint32_t>(a) == std::bit_cast<std::uint32_t>(b); }
bool same_bits(const Vec3f& a, const Vec3f& b) {
  return same_bits(a.x, b.x) && same_bits(a.y, b.y) && same_bits(a.z, b.z);
}
bool same_hit(const Hit& a, const Hit& b) {
  return a.shape == b.shape && same_bits(a.t, b.t) && same_bits(a.p, b.p) && same_bits(a.n, b.n) &&
         same_bits(a.p_error, b.p_error);
}

std::string describe(const Ray& r) {
  std::ostringstream s;
  s.precision(9);
  s << "o=(" << r.o.x << "," << r.o.y << "," << r.o.z << ") d=(" << r.d.x << "," << r.d.y << "," << r.d.z << ") t=("
    << r.t_min << "," << r.t_max << ")";
  return s.str();
}

bool hit_is_finite(const Hit& h) {
  return std::isfinite(h.t) && dtraced::math::is_finite(h.p) && dtraced::math::is_finite(h.n) &&
         dtraced::math::is_finite(h.p_error);
}

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

TEST_CASE("Far sphere: hit/miss and normals agree with an exact reference", "[accel][sphere]") {
  // Unit sphere at the origin, camera on the +z axis at distance D. For float o and d the
  // long-double cross products below are exact (o is an integer of <= 24 bits, d has 24 bits) and
  // their squares carry 2^-64 relative error, so the reference decides hit/miss by the distance of
  // the float ray from the centre to ~1e-19: independent of the float/double rounding under test.
  const Geometry geo = Geometry::build({sphere({0, 0, 0}, 1.0f)});
  for (const double dist : {1e5, 1e6, 1e7}) {
    TestRng rng{std::uint64_t(dist)};
    const Vec3f o{0, 0, float(dist)};
    long rays = 0, agree = 0, hits = 0, worst_count = 0;
    double worst_angle = 0.0;
    auto test_ray = [&](double x, double y) {
      const Vec3f d = unit_f(Vec3d{x, y, -dist});
      using LD = long double;
      const LD dx = d.x, dy = d.y, dz = d.z, oz = o.z;
      const LD cx = -oz * dy, cy = oz * dx;  // (o - c) x d with o - c = (0, 0, oz)
      const LD a = dx * dx + dy * dy + dz * dz;
      const LD disc = a - (cx * cx + cy * cy);  // a r^2 - |f x d|^2
      const bool ref_hit = disc >= 0;
      Hit h;
      const bool got = geo.intersect(make_ray(o, d), h);
      ++rays;
      hits += ref_hit;
      if (got != ref_hit) return;
      if (got) {
        const LD b = oz * dz;
        const LD t = (-b - std::sqrt(disc)) / a;
        const LD px = t * dx, py = t * dy, pz = oz + t * dz;
        // atan2 of |p x n| and p . n: acos near 1 would turn the ~6e-8 length error of a float
        // unit vector into a fake 3e-4 rad.
        const LD nx = h.n.x, ny = h.n.y, nz = h.n.z;
        const LD qx = py * nz - pz * ny, qy = pz * nx - px * nz, qz = px * ny - py * nx;
        const double angle = double(std::atan2(std::sqrt(qx * qx + qy * qy + qz * qz), px * nx + py * ny + pz * nz));
        worst_angle = std::max(worst_angle, angle);
        if (!(angle < 1e-3)) {
          ++worst_count;
          return;
        }
      }
      ++agree;
    };
    // A grid across the whole disc and its surroundings, then a dense band at the silhouette.
    constexpr int kGrid = 300;
    for (int j = 0; j < kGrid; ++j) {
      for (int i = 0; i < kGrid; ++i) test_ray(-1.2 + 2.4 * (i + 0.5) / kGrid, -1.2 + 2.4 * (j + 0.5) / kGrid);
    }
    for (int i = 0; i < 100000; ++i) {
      const double rad = rng.uniform(0.999, 1.001);
      const double phi = rng.uniform(0.0, 2.0 * std::numbers::pi);
      test_ray(rad * std::cos(phi), rad * std::sin(phi));
    }
    INFO("D = " << dist << ": " << agree << " of " << rays << " agree (" << hits << " reference hits), " << worst_count
                << " normals off by >= 1e-3 rad, worst normal error " << worst_angle << " rad");
    CHECK(double(agree) >= 0.9995 * double(rays));
    CHECK(hits > rays / 3);
    WARN("far sphere D=" << dist << ": " << rays - agree << " disagreements in " << rays << " rays, worst normal error "
                         << worst_angle << " rad");
  }
}

TEST_CASE("Grazing rays: no NaN and one hit/miss switch across the tangent", "[accel][sphere]") {
  struct Sweep {
    const char* name;
    Shape s;
    Vec3f o;  // origin at the tangent offset
    Vec3f d;
    std::size_t k;  // the origin coordinate swept in ulp steps
  };
  const Vec3f diag = unit_f({1, 1, 0});  // equal components: the xy line passes the centre exactly
  const std::vector<Sweep> sweeps = {
      {"axis ray, unit sphere", sphere({0, 0, 0}, 1), {-10, 1, 0}, {1, 0, 0}, 1},
      {"diagonal ray, unit sphere", sphere({0, 0, 0}, 1), {-10, -10, 1}, diag, 2},
      {"r=250 sphere at 1e4", sphere({1e4f, 2e3f, -5e3f}, 250), {9e3f, 2250, -5e3f}, {1, 0, 0}, 1},
      {"unit sphere from 1e6", sphere({0, 0, 0}, 1), {-1e6f, 1, 0}, {1, 0, 0}, 1},
      {"r=1e-3 sphere from 10", sphere({0.5f, 0, 0}, 1e-3f), {-10, 1e-3f, 0}, {1, 0, 0}, 1},
  };
  for (const Sweep& sw : sweeps) {
    const Geometry geo = Geometry::build({sw.s});
    float v = sw.o[sw.k];
    for (int i = 0; i < 400; ++i) v = next_float_down(v);
    int switches = 0, hits = 0, nan_hits = 0;
    bool prev = true;
    for (int i = 0; i < 800; ++i, v = next_float_up(v)) {
      Vec3f o = sw.o;
      o[sw.k] = v;
      Hit h;
      const bool hit = geo.intersect(make_ray(o, sw.d), h);
      if (hit) {
        ++hits;
        nan_hits += !hit_is_finite(h);
      }
      if (i > 0 && hit != prev) ++switches;
      prev = hit;
    }
    INFO(sw.name << ": " << hits << " hits, " << switches << " switches");
    CHECK(nan_hits == 0);
    CHECK(switches == 1);
    CHECK(hits > 0);
    CHECK(hits < 800);
  }
}

namespace {

// A ray that really hits shape `s` (from outside), for the self-intersection trials.
struct SurfacePoint {
  Hit hit;
  bool ok = false;
};

SurfacePoint hit_from_outside(const Geometry& geo, const Vec3d& from, const Vec3d& toward) {
  SurfacePoint sp;
  const Vec3f o = to_f(from);
  sp.ok = geo.intersect(make_ray(o, unit_f(toward - to_d(o))), sp.hit);
  return sp;
}

Vec3f in_hemisphere(TestRng& rng, const Vec3f& n, float sign) {
  Vec3d w = rng.unit();
  if (dot(w, to_d(n)) * sign < 0) w = -w;
  return to_f(w);
}

struct SelfHitCounts {
  long trials = 0;    // surface points
  long rehits = 0;    // outward rays that hit the same surface again
  long lost = 0;      // inward rays (closed shapes) that miss the far side
  long backside = 0;  // inward rays whose hit is not an exit (normal facing the ray)
};

// From a real hit point, one outward ray and one inward ray, both from offset_ray_origin.
void self_hit_trial(const Geometry& geo, const Hit& hit, TestRng& rng, bool closed, SelfHitCounts& c) {
  ++c.trials;
  const Vec3f out = in_hemisphere(rng, hit.n, 1.0f);
  Hit h;
  if (geo.intersect(make_ray(offset_ray_origin(hit.p, hit.p_error, hit.n, out), out), h)) ++c.rehits;
  const Vec3f in = in_hemisphere(rng, hit.n, -1.0f);
  const bool got = geo.intersect(make_ray(offset_ray_origin(hit.p, hit.p_error, hit.n, in), in), h);
  if (closed) {
    if (!got) {
      ++c.lost;
    } else if (!(dot(h.n, in) > 0.0f)) {
      ++c.backside;
    }
  } else if (got) {
    ++c.rehits;  // a plane has no far side: the ray into the back half-space must not re-hit it
  }
}

// Spheres with radius log-uniform in [r_lo, r_hi] and centre uniform in a ball of radius
// min(c_max, r * max_ratio).
SelfHitCounts sphere_trials(TestRng& rng, int n, double r_lo, double r_hi, double c_max, double max_ratio) {
  SelfHitCounts c;
  for (int i = 0; i < n; ++i) {
    const double r = rng.log_uniform(r_lo, r_hi);
    const Vec3d dir = rng.unit();
    const Vec3d centre = dir * (std::min(c_max, r * max_ratio) * std::cbrt(rng.uniform()));
    const Geometry geo = Geometry::build({sphere(to_f(centre), float(r))});
    const Vec3d cf = to_d(geo.shapes()[0].sphere.center);
    const Vec3d from_dir = rng.unit();
    const Vec3d from = cf + from_dir * (r * rng.uniform(1.5, 20.0));
    const Vec3d to_dir = rng.unit();
    const Vec3d toward = cf + to_dir * (0.9 * r * rng.uniform());
    const SurfacePoint sp = hit_from_outside(geo, from, toward);
    if (sp.ok) self_hit_trial(geo, sp.hit, rng, /* closed = */ true, c);
  }
  return c;
}

// Boxes with edges in [0.2, 3] * scale, centred within c_max of the origin.
SelfHitCounts box_trials(TestRng& rng, int n, double scale, double c_max) {
  SelfHitCounts c;
  for (int i = 0; i < n; ++i) {
    const Vec3d dir = rng.unit();
    const Vec3d centre = dir * (c_max * rng.uniform());
    const Vec3d h{scale * rng.uniform(0.1, 1.5), scale * rng.uniform(0.1, 1.5), scale * rng.uniform(0.1, 1.5)};
    const Geometry geo = Geometry::build({box(to_f(centre - h), to_f(centre + h))});
    const Vec3d inside{centre.x + h.x * rng.uniform(-0.9, 0.9), centre.y + h.y * rng.uniform(-0.9, 0.9),
                       centre.z + h.z * rng.uniform(-0.9, 0.9)};
    const Vec3d from_dir = rng.unit();
    const Vec3d from = centre + from_dir * (scale * rng.uniform(4.0, 40.0));
    const SurfacePoint sp = hit_from_outside(geo, from, inside);
    if (sp.ok) self_hit_trial(geo, sp.hit, rng, /* closed = */ true, c);
  }
  return c;
}

// Planes with a random normal through a point within 10 * scale of the origin, hit within
// 10 * scale of that point from up to 10 * scale away.
SelfHitCounts plane_trials(TestRng& rng, int n, double scale) {
  SelfHitCounts c;
  for (int i = 0; i < n; ++i) {
    const Vec3d point_dir = rng.unit();
    const Vec3f point = to_f(point_dir * (10.0 * scale * rng.uniform()));
    const Vec3f n = unit_f(rng.unit());
    const Geometry geo = Geometry::build({plane(point, n)});
    const Vec3d target_dir = rng.unit();
    Vec3d target = to_d(point) + target_dir * (10.0 * scale * rng.uniform());
    target = target - to_d(n) * dot(target - to_d(point), to_d(n));  // onto the plane
    const Vec3d from_dir = rng.unit();
    const Vec3d from = target + from_dir * (scale * rng.uniform(0.1, 10.0));
    const SurfacePoint sp = hit_from_outside(geo, from, target);
    if (sp.ok) self_hit_trial(geo, sp.hit, rng, /* closed = */ false, c);
  }
  return c;
}

}  // namespace

TEST_CASE("Self-intersection: offset origins never re-hit, inward rays always exit", "[accel][offset]") {
  TestRng rng{99};
  long total = 0;
  auto report = [&](const char* what, const SelfHitCounts& c, long min_trials) {
    total += c.trials;
    INFO(what << ": " << c.trials << " surface points, " << c.rehits << " re-hits, " << c.lost << " lost, "
              << c.backside << " inward hits not at an exit");
    CHECK(c.trials >= min_trials);
    CHECK(c.rehits == 0);
    CHECK(c.lost == 0);
    CHECK(c.backside == 0);
  };
  // Radius 1e-3..1e3, centres up to 1e4 away, as long as the sphere spans >= 2^-20 of its
  // distance from the origin (>= ~8 float ulps of its centre): below that a float point on it
  // cannot be represented well enough to be offset inward (accuracy notes 1.11); the test below
  // reports that regime without asserting.
  report("spheres r 1e-3..1e3, |c| <= min(1e4, 2^20 r)", sphere_trials(rng, 60000, 1e-3, 1e3, 1e4, 0x1p20), 59000);
  report("spheres r 1e-3..1e3, |c| <= 1e4 with r/|c| >= 1e-3", sphere_trials(rng, 10000, 1e-3, 1e3, 1e4, 1e3), 9900);
  report("boxes at scale 1e-3, |c| <= 1", box_trials(rng, 15000, 1e-3, 1.0), 14900);
  report("boxes at scale 1e-3, |c| <= 10", box_trials(rng, 5000, 1e-3, 10.0), 4900);
  report("boxes at scale 1e3, |c| <= 1e4", box_trials(rng, 15000, 1e3, 1e4), 14900);
  report("planes at scale 1e-3", plane_trials(rng, 15000, 1e-3), 14500);
  report("planes at scale 1e3", plane_trials(rng, 15000, 1e3), 14500);
  CHECK(total >= 100000);
}

TEST_CASE("Self-intersection at the float precision floor (reported, not asserted)", "[accel][offset]") {
  TestRng rng{2024};
  const SelfHitCounts s = sphere_trials(rng, 20000, 1e-3, 1e-2, 1e4, 1e12);
  const SelfHitCounts b = box_trials(rng, 20000, 1e-3, 1e4);
  WARN("precision floor: spheres r 1e-3..1e-2 at |c| <= 1e4 (r ~ 1..10 ulps of c): "
       << s.rehits << " re-hits, " << s.lost << " lost of " << s.trials << "; boxes of 1e-3 at |c| <= 1e4: " << b.rehits
       << " re-hits, " << b.lost << " lost of " << b.trials);
  // Outward rays stay clean even here: the offset is always past the error bound.
  CHECK(s.rehits == 0);
  CHECK(b.rehits == 0);
}

TEST_CASE("Rays starting inside, flat boxes, and t_min", "[accel][shapes]") {
  SECTION("inside a box: the far face") {
    const Geometry geo = Geometry::build({box({-1, -2, -3}, {1, 2, 3})});
    Hit h;
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}), h));
    CHECK(h.t == 3.0f);
    CHECK(h.p == Vec3f{0, 0, 3});
    CHECK(h.n == Vec3f{0, 0, 1});
    REQUIRE(geo.intersect(make_ray({0.5f, 0, 0}, {-1, 0, 0}), h));
    CHECK(h.t == 1.5f);
    CHECK(h.n == Vec3f{-1, 0, 0});
    CHECK(h.p.x == -1.0f);
  }
  SECTION("inside a sphere: the far side") {
    const Geometry geo = Geometry::build({sphere({10, 0, 0}, 2)});
    Hit h;
    REQUIRE(geo.intersect(make_ray({10.5f, 0, 0}, {1, 0, 0}), h));
    CHECK(h.t == 1.5f);
    CHECK(h.n == Vec3f{1, 0, 0});
    REQUIRE(geo.intersect(make_ray({10, 0, 0}, unit_f({1, 1, 1})), h));
    CHECK(h.t == Approx(2.0f).epsilon(1e-6));
    CHECK(dot(h.n, unit_f({1, 1, 1})) == Approx(1.0f).epsilon(1e-6));
    CHECK(length(h.p - Vec3f{10, 0, 0}) == Approx(2.0f).epsilon(1e-6));
  }
  SECTION("flat box hit by a perpendicular ray, from both sides") {
    const Geometry geo = Geometry::build({box({-1, 5, -1}, {1, 5, 1})});
    Hit h;
    REQUIRE(geo.intersect(make_ray({0.25f, 0, 0.5f}, {0, 1, 0}), h));
    CHECK(h.t == 5.0f);
    CHECK(h.p == Vec3f{0.25f, 5, 0.5f});
    CHECK(h.n == Vec3f{0, -1, 0});
    REQUIRE(geo.intersect(make_ray({0.25f, 9, 0.5f}, {0, -1, 0}), h));
    CHECK(h.t == 4.0f);
    CHECK(h.n == Vec3f{0, 1, 0});
    // Aimed at its edges and corners.
    CHECK(geo.intersect(make_ray({1, 0, 1}, {0, 1, 0}), h));
    CHECK(geo.intersect(make_ray({-1, 0, 0.3f}, {0, 1, 0}), h));
    CHECK_FALSE(geo.intersect(make_ray({next_float_up(1.0f), 0, 0}, {0, 1, 0}), h));
  }
  SECTION("t_min past a hit skips it; t_max before a hit excludes it") {
    const Geometry geo = Geometry::build({sphere({0, 0, 10}, 1), sphere({0, 0, 20}, 1), box({-1, -1, 30}, {1, 1, 32})});
    Hit h;
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}), h));
    CHECK(h.shape == 0);
    CHECK(h.t == 9.0f);
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 9.0f), h));  // open interval: 9 is excluded
    CHECK(h.shape == 0);
    CHECK(h.t == 11.0f);  // the far root of the first sphere
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 11.0f), h));
    CHECK(h.shape == 1);
    CHECK(h.t == 19.0f);
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 25.0f), h));
    CHECK(h.shape == 2);
    CHECK(h.t == 30.0f);
    REQUIRE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 30.0f), h));
    CHECK(h.t == 32.0f);
    CHECK_FALSE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 32.0f), h));
    CHECK_FALSE(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 0.0f, 9.0f), h));
    CHECK(geo.intersect(make_ray({0, 0, 0}, {0, 0, 1}, 0.0f, next_float_up(9.0f)), h));
    CHECK_FALSE(geo.occluded(make_ray({0, 0, 0}, {0, 0, 1}, 0.0f, 9.0f)));
    CHECK(geo.occluded(make_ray({0, 0, 0}, {0, 0, 1}, 0.0f, 9.5f)));
  }
  SECTION("planes: both sides, parallel rays, normals as given") {
    const Geometry geo = Geometry::build({plane({0, -1, 0}, {0, 1, 0})});
    Hit h;
    REQUIRE(geo.intersect(make_ray({3, 4, 5}, {0, -1, 0}), h));
    CHECK(h.t == 5.0f);
    CHECK(h.p == Vec3f{3, -1, 5});
    CHECK(h.n == Vec3f{0, 1, 0});
    REQUIRE(geo.intersect(make_ray({3, -4, 5}, {0, 1, 0}), h));
    CHECK(h.t == 3.0f);
    CHECK(h.n == Vec3f{0, 1, 0});                                    // not flipped toward the ray
    CHECK_FALSE(geo.intersect(make_ray({3, 4, 5}, {1, 0, 0}), h));   // parallel
    CHECK_FALSE(geo.intersect(make_ray({3, -1, 5}, {1, 0, 0}), h));  // in the plane
    CHECK_FALSE(geo.intersect(make_ray({3, 4, 5}, {0, 1, 0}), h));   // behind
  }
  SECTION("ties: coincident shapes report the smaller index") {
    const Geometry geo = Geometry::build({box({0, 0, 5}, {1, 1, 6}), sphere({0, 0, 0}, 1), box({0, 0, 5}, {1, 1, 6})});
    Hit h;
    REQUIRE(geo.intersect(make_ray({0.5f, 0.5f, 10}, {0, 0, -1}), h));
    CHECK(h.shape == 0);
    CHECK(h.t == 4.0f);
  }
  SECTION("invalid shapes are never hit; bad rays never hit") {
    const float nan = std::numeric_limits<float>::quiet_NaN();
    const Geometry geo =
        Geometry::build({sphere({0, 0, 0}, 0), sphere({0, 0, 0}, -1), sphere({nan, 0, 0}, 1), box({1, 0, 0}, {0, 1, 1}),
                         plane({0, 0, 0}, {0, 0, 0}), sphere({0, 0, 0}, kInf)});
    Hit h;
    CHECK_FALSE(geo.intersect(make_ray({-5, 0.5f, 0.5f}, {1, 0, 0}), h));
    CHECK_FALSE(geo.intersect(make_ray({0.5f, 0.5f, 5}, {0, 0, -1}), h));
    const Geometry ok = Geometry::build({sphere({0, 0, 0}, 1)});
    CHECK_FALSE(ok.intersect(make_ray({nan, 0, -5}, {0, 0, 1}), h));
    CHECK_FALSE(ok.intersect(make_ray({0, 0, -5}, {nan, 0, 1}), h));
    CHECK_FALSE(ok.intersect(make_ray({0, 0, -5}, {0, 0, 1}, nan), h));
    CHECK_FALSE(ok.intersect(make_ray({0, 0, -5}, {0, 0, 1}, 0.0f, nan), h));
    CHECK_FALSE(ok.intersect(make_ray({0, 0, -5}, {0, 0, 0}), h));
    CHECK_FALSE(ok.intersect(make_ray({0, 0, -5}, {0, 0, 1}, 3.0f, 2.0f), h));
    CHECK(ok.intersect(make_ray({0, 0, -5}, {0, 0, 1}), h));
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

TEST_CASE("offset_ray_origin follows pbrt-v4", "[accel][offset]") {
  const Vec3f p{1, 2, 3};
  const Vec3f err{0.5f, 0.25f, 0.125f};
  const Vec3f n = unit_f({1, -1, 0});
  const float d = std::abs(n.x) * err.x + std::abs(n.y) * err.y + std::abs(n.z) * err.z;
  const Vec3f out = offset_ray_origin(p, err, n, {1, 0, 0});  // dot(w, n) > 0: along +n
  CHECK(out.x == next_float_up(p.x + d * n.x));
  CHECK(out.y == next_float_down(p.y + d * n.y));
  CHECK(out.z == p.z);  // zero offset component: left alone
  const Vec3f in = offset_ray_origin(p, err, n, {-1, 0, 0});
  CHECK(in.x == next_float_down(p.x - d * n.x));
  CHECK(in.y == next_float_up(p.y - d * n.y));
  CHECK(in.z == p.z);
  // A zero error bound (a box face) leaves the point exactly where it is.
  CHECK(offset_ray_origin(p, {0, 0, 0}, {0, 0, 1}, {0, 0, 1}) == p);
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
