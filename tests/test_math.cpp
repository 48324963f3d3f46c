// Tests of dtraced::math: vectors, float helpers (ulp steps, gamma), counter-based RNG, boxes.
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <set>

#include <catch2/catch.hpp>

#include "math/float_util.h"
#include "math/ray.h"
#include "math/rng.h"
#include "math/vec.h"

using namespace dtraced::math;

namespace {
constexpr float kInf = std::numeric_limits<float>::infinity();
}

TEST_CASE("vec: arithmetic, dot, cross, length", "[math][vec]") {
  const Vec3f a{1, 2, 3};
  const Vec3f b{-4, 5, 0.5f};
  CHECK(a + b == Vec3f{-3, 7, 3.5f});
  CHECK(a - b == Vec3f{5, -3, 2.5f});
  CHECK(a * 2.0f == Vec3f{2, 4, 6});
  CHECK(2.0f * a == Vec3f{2, 4, 6});
  CHECK(a / 2.0f == Vec3f{0.5f, 1, 1.5f});
  CHECK(-a == Vec3f{-1, -2, -3});
  CHECK(mul(a, b) == Vec3f{-4, 10, 1.5f});
  CHECK(dot(a, b) == -4.0f + 10.0f + 1.5f);
  const Vec3f c = cross(a, b);
  CHECK(c == Vec3f{2 * 0.5f - 3 * 5, 3 * -4 - 1 * 0.5f, 1 * 5 - 2 * -4});
  CHECK(dot(c, a) == 0.0f);  // small integers and halves: exact
  CHECK(dot(c, b) == 0.0f);
  CHECK(cross(Vec3f{1, 0, 0}, Vec3f{0, 1, 0}) == Vec3f{0, 0, 1});
  CHECK(length_squared(a) == 14.0f);
  CHECK(length(Vec3f{3, 4, 0}) == 5.0f);
  CHECK(length(normalize(Vec3f{1, 2, -7})) == Approx(1.0f).epsilon(1e-6));
  CHECK(abs(Vec3f{-1, 2, -0.0f}) == Vec3f{1, 2, 0});
  CHECK(min(a, b) == Vec3f{-4, 2, 0.5f});
  CHECK(max(a, b) == Vec3f{1, 5, 3});
  CHECK(max_component(b) == 5.0f);
  CHECK(max_dimension(Vec3f{1, 3, 2}) == 1);
  CHECK(max_dimension(Vec3f{1, 2, 3}) == 2);
  CHECK(max_dimension(Vec3f{4, 2, 3}) == 0);
  Vec3f m = a;
  m[1] = 9.0f;
  CHECK(m[0] == 1.0f);
  CHECK(m[1] == 9.0f);
  CHECK(m[2] == 3.0f);
  m += a;
  m -= Vec3f{1, 1, 1};
  m *= 0.5f;
  CHECK(m == Vec3f{0.5f, 5, 2.5f});
  CHECK(Vec3d(a) == Vec3d{1, 2, 3});
  CHECK(is_finite(a));
  CHECK_FALSE(is_finite(Vec3f{1, kInf, 0}));
  CHECK_FALSE(is_finite(Vec3f{std::numeric_limits<float>::quiet_NaN(), 0, 0}));
}

TEST_CASE("float_util: next_float_up/down step exactly one ulp", "[math][float]") {
  for (const float v : {1.0f, -1.0f, 0.1f, -3.5e7f, 1e-40f, -1e-40f, 3.4e38f}) {
    const float up = next_float_up(v);
    const float down = next_float_down(v);
    CHECK(up > v);
    CHECK(down < v);
    CHECK(next_float_down(up) == v);
    CHECK(next_float_up(down) == v);
    CHECK(std::nextafter(v, kInf) == up);
    CHECK(std::nextafter(v, -kInf) == down);
  }
  // Both zeros step to the smallest subnormal of the right sign.
  CHECK(next_float_up(0.0f) == std::numeric_limits<float>::denorm_min());
  CHECK(next_float_up(-0.0f) == std::numeric_limits<float>::denorm_min());
  CHECK(next_float_down(0.0f) == -std::numeric_limits<float>::denorm_min());
  CHECK(next_float_down(-0.0f) == -std::numeric_limits<float>::denorm_min());
  CHECK(next_float_up(kInf) == kInf);
  CHECK(next_float_down(-kInf) == -kInf);
  CHECK(next_float_up(std::numeric_limits<float>::max()) == kInf);
  CHECK(next_float_down(-std::numeric_limits<float>::max()) == -kInf);
  CHECK(next_float_up(-std::numeric_limits<float>::denorm_min()) == -0.0f);
}

TEST_CASE("float_util: gamma bounds n roundings", "[math][float]") {
  CHECK(kMachineEpsilon == 0x1p-24f);
  CHECK(gamma(0) == 0.0f);
  CHECK(gamma(1) > kMachineEpsilon);
  for (int n = 1; n < 20; ++n) {
    CHECK(gamma(n + 1) > gamma(n));
    const double e = 0x1p-24;
    CHECK(double(gamma(n)) == Approx(n * e / (1 - n * e)).epsilon(1e-6));
  }
  // gamma(n) really bounds n chained roundings: the product of n float multiplications against
  // the exact product (in long double, exact for these few 24-bit factors).
  std::uint64_t s = 12345;
  auto next = [&] { return to_unit_float(s = mix64(s + 0x9e3779b97f4a7c15ULL)) + 0.5f; };
  for (int trial = 0; trial < 10000; ++trial) {
    float pf = next();
    long double pe = pf;
    for (int i = 0; i < 3; ++i) {
      const float x = next();
      pf *= x;
      pe *= x;
    }
    CHECK(std::abs((long double)pf - pe) <= (long double)gamma(3) * pe);
  }
}

TEST_CASE("float_util: gamma_d is gamma for double's unit roundoff", "[math][float]") {
  CHECK(kMachineEpsilonD == 0x1p-53);
  CHECK(gamma_d(0) == 0.0);
  for (int n = 1; n < 20; ++n) {
    CHECK(gamma_d(n + 1) > gamma_d(n));
    CHECK(gamma_d(n) == Approx(n * 0x1p-53).epsilon(1e-12));
    CHECK(gamma_d(n) < double(gamma(n)) * 1e-8);  // 2^-29 of the float bound
  }
}

TEST_CASE("rng: deterministic, key-sensitive, in the unit interval below 1", "[math][rng]") {
  const SampleKey k{42, 1, 10, 20, 3};
  CHECK(sample_hash(k, 0) == sample_hash(k, 0));
  CHECK(sample_uniform(k, 5) == sample_uniform(SampleKey{42, 1, 10, 20, 3}, 5));
  // Changing any word of the key changes the output.
  std::set<std::uint64_t> seen{sample_hash(k, 0),
                               sample_hash(k, 1),
                               sample_hash({43, 1, 10, 20, 3}, 0),
                               sample_hash({42, 2, 10, 20, 3}, 0),
                               sample_hash({42, 1, 11, 20, 3}, 0),
                               sample_hash({42, 1, 10, 21, 3}, 0),
                               sample_hash({42, 1, 10, 20, 4}, 0),
                               sample_hash({42, 1, 20, 10, 3}, 0)};
  CHECK(seen.size() == 8);
  static_assert(sample_hash(SampleKey{1, 2, 3, 4, 5}, 6) == sample_hash(SampleKey{1, 2, 3, 4, 5}, 6));
  CHECK(to_unit_float(0) == 0.0f);
  CHECK(to_unit_float(~0ULL) < 1.0f);
  CHECK(to_unit_float(~0ULL) == 1.0f - 0x1p-24f);
}

TEST_CASE("rng: uniformity of 1e5 samples", "[math][rng]") {
  constexpr int kN = 100000;
  constexpr int kBuckets = 16;
  int buckets[kBuckets] = {};
  double sum = 0.0;
  bool all_in_range = true;
  for (int i = 0; i < kN; ++i) {
    const SampleKey key{7, 0, std::uint32_t(i % 317), std::uint32_t(i / 317), std::uint32_t(i % 5)};
    const float u = sample_uniform(key, std::uint32_t(i % 3));
    all_in_range = all_in_range && u >= 0.0f && u < 1.0f;
    sum += u;
    ++buckets[std::min(kBuckets - 1, int(u * kBuckets))];
  }
  CHECK(all_in_range);
  // Standard error of the mean of U(0,1) over 1e5 samples is 0.29 / 316 = 9e-4: allow ~5 sigma.
  CHECK(sum / kN == Approx(0.5).margin(0.005));
  // Chi-square with 15 degrees of freedom; 37.7 is the 0.1 % tail.
  double chi2 = 0.0;
  for (const int b : buckets) {
    const double e = double(kN) / kBuckets;
    chi2 += (b - e) * (b - e) / e;
  }
  INFO("chi2 = " << chi2);
  CHECK(chi2 < 37.7);
}

TEST_CASE("Bounds3f: extend, empty, centroid, area", "[math][bounds]") {
  Bounds3f b;
  CHECK(b.empty());
  CHECK(b.surface_area() == 0.0f);
  b.extend(Vec3f{1, 2, 3});
  CHECK_FALSE(b.empty());  // a single point is a (degenerate) box
  CHECK(b.lo == b.hi);
  CHECK(b.surface_area() == 0.0f);
  b.extend(Vec3f{-1, 4, 3});
  CHECK(b.lo == Vec3f{-1, 2, 3});
  CHECK(b.hi == Vec3f{1, 4, 3});
  CHECK(b.surface_area() == 2.0f * (2 * 2));  // flat in z: one face pair only
  Bounds3f c;
  c.extend(Vec3f{0, 0, 0});
  c.extend(Vec3f{2, 3, 4});
  CHECK(c.extent() == Vec3f{2, 3, 4});
  CHECK(c.centroid() == Vec3f{1, 1.5f, 2});
  CHECK(c.surface_area() == 2.0f * (6 + 12 + 8));
  Bounds3f u = b;
  u.extend(c);
  CHECK(u.lo == Vec3f{-1, 0, 0});
  CHECK(u.hi == Vec3f{2, 4, 4});
  Bounds3f e;
  e.extend(Bounds3f{});  // empty into empty stays empty
  CHECK(e.empty());
  const Ray r;
  CHECK(r.t_min == 0.0f);
  CHECK(r.t_max == kInf);
}
