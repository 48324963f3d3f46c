// Tests of dtraced::accel's single-shape arithmetic: far-sphere accuracy against an exact
// long-double reference, grazing rays, self-intersection after offset_ray_origin, and rays that
// start inside shapes, on flat boxes or with a t_min.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numbers>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "shape_builders.h"

using namespace dtraced::accel;
using namespace dtraced::testing;

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
  // cannot be represented well enough to be offset inward (floats near the centre are ~1.2e-7 |c|
  // apart, a good part of r); the test below reports that regime without asserting.
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
