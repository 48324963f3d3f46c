// math::det: the elementary functions that reach pixels. Accuracy against the C library (which
// may itself be off by an ulp, hence the few-ulp bounds), the special values, and the exact bits
// of chosen inputs: those bits are the promise (the same on every host and compiler), so a
// change that alters any of them must be a deliberate one, with a new pixel version.
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <catch2/catch.hpp>

#include "math/det_math.h"

namespace dtraced {
namespace {

namespace det = math::det;

// |a - b| in units of b's last place (b finite and nonzero).
double ulps(double a, double b) {
  const double ulp = std::nextafter(std::fabs(b), std::numeric_limits<double>::infinity()) - std::fabs(b);
  return std::fabs(a - b) / ulp;
}

// A deterministic spread of doubles: 2^e times a mantissa from a fixed sequence.
double spread(int i, int n, double lo_exp, double hi_exp) {
  const double e = lo_exp + (hi_exp - lo_exp) * (static_cast<double>(i) / n);
  const double frac = 1.0 + 0.6180339887498949 * static_cast<double>((i * 7919) % 1000) / 1000.0;
  return std::ldexp(frac, static_cast<int>(std::floor(e)));
}

TEST_CASE("det::log2 and det::exp2 are within a few ulps of the C library", "[math][det]") {
  double worst_log = 0.0, worst_exp = 0.0;
  for (int i = 0; i < 20000; ++i) {
    const double x = spread(i, 20000, -1070, 1020);
    const double ref = std::log2(x);
    if (std::fabs(ref) > 1e-3) worst_log = std::max(worst_log, ulps(det::log2(x), ref));
    const double y = -1070.0 + 2090.0 * (static_cast<double>(i) + 0.37) / 20000.0;
    worst_exp = std::max(worst_exp, ulps(det::exp2(y), std::exp2(y)));
  }
  // Near x = 1 log2 is small: an absolute bound there.
  double worst_near_one = 0.0;
  for (int i = 1; i < 2000; ++i) {
    const double x = 1.0 + (i - 1000) * 1e-6;
    worst_near_one = std::max(worst_near_one, std::fabs(det::log2(x) - std::log2(x)));
  }
  INFO("log2 " << worst_log << " ulp, exp2 " << worst_exp << " ulp, log2 near 1 " << worst_near_one);
  CHECK(worst_log <= 4.0);
  CHECK(worst_exp <= 4.0);
  CHECK(worst_near_one <= 1e-18);
  CHECK(det::exp2(0.0) == 1.0);
  CHECK(det::exp2(10.0) == 1024.0);
  CHECK(det::exp2(-3.0) == 0.125);
  CHECK(det::exp2(-1074.0) == std::numeric_limits<double>::denorm_min());
  CHECK(det::exp2(1023.0) == std::ldexp(1.0, 1023));
  CHECK(det::log2(1.0) == 0.0);
  CHECK(det::log2(1024.0) == 10.0);
  CHECK(det::log2(0.0) == -std::numeric_limits<double>::infinity());
  CHECK(std::isnan(det::log2(-1.0)));
  CHECK(det::exp2(2000.0) == std::numeric_limits<double>::infinity());
  CHECK(det::exp2(-2000.0) == 0.0);
}

TEST_CASE("det::pow and det::powf follow the C library and its special values", "[math][det]") {
  double worst = 0.0;
  int float_diffs = 0, float_far = 0;
  for (int i = 0; i < 20000; ++i) {
    const double x = (static_cast<double>(i) + 0.5) / 20000.0;                             // (0, 1): cosines
    const double y = 0.25 + 2000.0 * static_cast<double>((i * 104729) % 20000) / 20000.0;  // exponents
    const double ref = std::pow(x, y);
    if (ref > 1e-300) worst = std::max(worst, ulps(det::pow(x, y), ref) / std::max(1.0, std::fabs(y * std::log2(x))));
    const float fx = static_cast<float>(x), fy = static_cast<float>(y);
    const float a = det::powf(fx, fy), b = static_cast<float>(std::pow(double(fx), double(fy)));
    if (a != b) {
      ++float_diffs;
      if (std::nextafter(a, b) != b) ++float_far;  // more than one float ulp apart
    }
  }
  INFO("pow: worst " << worst << " ulp per unit of |y log2 x|; powf: " << float_diffs << " of 20000 differ by an ulp");
  CHECK(worst <= 8.0);
  CHECK(float_far == 0);
  CHECK(float_diffs <= 20);  // a double result a hair from a float tie rounds either way
  CHECK(det::pow(0.0, 0.0) == 1.0);
  CHECK(det::pow(0.0, 2.0) == 0.0);
  CHECK(det::pow(0.0, -1.0) == std::numeric_limits<double>::infinity());
  CHECK(det::pow(1.0, 1e300) == 1.0);
  CHECK(det::pow(2.0, 10.0) == 1024.0);
  CHECK(det::pow(4.0, 0.5) == 2.0);
  CHECK(std::isnan(det::pow(-2.0, 2.0)));
  CHECK(det::powf(0.0f, 64.0f) == 0.0f);
  CHECK(det::powf(1.0f, 512.0f) == 1.0f);
}

// The packet path's specular lobes go through the array form: it must be powf, bit for bit,
// ordinary cosines and every special case alike, also in place.
TEST_CASE("det::powf over arrays gives each entry det::powf's bits", "[math][det]") {
  constexpr float kInfF = std::numeric_limits<float>::infinity();
  const float special_x[] = {0.0f,
                             -0.0f,
                             1.0f,
                             -0.5f,
                             kInfF,
                             std::numeric_limits<float>::quiet_NaN(),
                             std::numeric_limits<float>::denorm_min(),
                             1e-30f,
                             0.999999f,
                             3.0f};
  const float special_y[] = {0.0f, 1.0f, 16.0f, 512.0f, -2.0f, kInfF, -kInfF, std::numeric_limits<float>::quiet_NaN()};
  std::vector<float> x, y;
  for (const float a : special_x) {
    for (const float b : special_y) x.push_back(a), y.push_back(b);
  }
  for (int i = 0; i < 5000; ++i) {
    x.push_back((static_cast<float>(i) + 0.5f) / 5000.0f);
    y.push_back(1.0f + static_cast<float>((i * 7919) % 1024));
  }
  // Bases above 1 and exponents of either sign, next to each other (the array form takes two
  // entries at a time): results past 2^160 (+inf) and below 2^-160 (0) as well as in between.
  for (int i = 0; i < 2000; ++i) {
    x.push_back(1.0f + static_cast<float>(i) / 500.0f);
    y.push_back(static_cast<float>((i * 613) % 401) - 200.0f);
  }
  std::vector<float> out(x.size()), in_place = x;
  det::powf(x.data(), y.data(), out.data(), static_cast<int>(x.size()));
  det::powf(in_place.data(), y.data(), in_place.data(), static_cast<int>(x.size()));
  int differ = 0;
  for (std::size_t i = 0; i < x.size(); ++i) {
    const auto want = std::bit_cast<std::uint32_t>(det::powf(x[i], y[i]));
    if (std::bit_cast<std::uint32_t>(out[i]) != want || std::bit_cast<std::uint32_t>(in_place[i]) != want) {
      FAIL_CHECK("x " << x[i] << ", y " << y[i]);
      ++differ;
    }
  }
  CHECK(differ == 0);
  det::powf(x.data(), y.data(), out.data(), 0);  // nothing to do
}

TEST_CASE("det::pow_fast is within 1e-12 of x^y over float's range, and keeps pow's special values", "[math][det]") {
  // x across [2^-20, 2^20] (every table entry, both sides of 1), y of either sign up to
  // exponents where x^y leaves float's range; the sRGB exponent over the encoded range.
  double worst = 0.0;
  int compared = 0;
  for (int i = 0; i < 40000; ++i) {
    const double x = std::ldexp(1.0 + static_cast<double>((i * 7919ll) % 40000) / 40000.0, (i % 41) - 20);
    const double y =
        (static_cast<double>((i * 104729ll) % 40000) / 40000.0 - 0.5) * 600.0 / (1 + std::abs(i % 41 - 20));
    if (std::fabs(y * std::log2(x)) > 125.0) continue;  // only results inside float's range
    // The reference in long double through exp2 and log2 (powl takes milliseconds a call for
    // large exponents): a relative error near 1e-17 at these exponents.
    const long double ref = std::exp2(static_cast<long double>(y) * std::log2(static_cast<long double>(x)));
    worst = std::max(worst, static_cast<double>(std::fabs((det::pow_fast(x, y) - ref) / ref)));
    ++compared;
  }
  for (int i = 0; i <= 20000; ++i) {
    const double v = 0.0031308 + (1.0 - 0.0031308) * static_cast<double>(i) / 20000.0;
    const long double ref = std::exp2(std::log2(static_cast<long double>(v)) / 2.4L);
    worst = std::max(worst, static_cast<double>(std::fabs((det::pow_fast(v, 1.0 / 2.4) - ref) / ref)));
  }
  INFO("worst relative error " << worst << " over " << compared << " + 20001 values");
  CHECK(compared > 20000);
  CHECK(worst < 1e-12);
  CHECK(det::pow_fast(0.0, 0.0) == 1.0);
  CHECK(det::pow_fast(0.0, 3.0) == 0.0);
  CHECK(det::pow_fast(0.0, -3.0) == std::numeric_limits<double>::infinity());
  CHECK(det::pow_fast(1.0, 1e300) == 1.0);
  CHECK(std::isnan(det::pow_fast(-0.5, 2.0)));
  CHECK(std::isnan(det::pow_fast(std::numeric_limits<double>::quiet_NaN(), 2.0)));
  CHECK(det::pow_fast(0.5, std::numeric_limits<double>::infinity()) == 0.0);
  CHECK(det::pow_fast(2.0, std::numeric_limits<double>::infinity()) == std::numeric_limits<double>::infinity());
  CHECK(det::pow_fast(0.5, 1e6) == 0.0);
  CHECK(det::pow_fast(3.0, 1e6) == std::numeric_limits<double>::infinity());
  CHECK(det::pow_fast(std::numeric_limits<double>::denorm_min(), 0.01) ==
        det::pow(std::numeric_limits<double>::denorm_min(), 0.01));
}

TEST_CASE("det::sincos and det::tan are within a few ulps of the C library", "[math][det]") {
  double worst = 0.0;
  for (int i = 0; i < 40000; ++i) {
    // Angles of light sampling and mesh rotations ([0, 2 pi)), then up to 2^20 radians.
    const double x = i < 20000 ? 6.283185307179586 * (static_cast<double>(i) + 0.31) / 20000.0
                               : -1048576.0 + 2097152.0 * (static_cast<double>(i - 20000) + 0.77) / 20000.0;
    const det::SinCos sc = det::sincos(x);
    worst = std::max({worst, std::fabs(sc.sin - std::sin(x)), std::fabs(sc.cos - std::cos(x))});
  }
  INFO("worst absolute error " << worst);
  CHECK(worst <= 4e-16);
  CHECK(det::sincos(0.0).sin == 0.0);
  CHECK(det::sincos(0.0).cos == 1.0);
  CHECK(std::isnan(det::sincos(1e7).sin));
  CHECK(std::isnan(det::sincos(std::numeric_limits<double>::quiet_NaN()).cos));
  for (const double deg : {1.0, 20.0, 45.0, 60.0, 89.0}) {
    const double rad = deg * 3.141592653589793 / 180.0;
    CHECK(ulps(det::tan(rad), std::tan(rad)) <= 4.0);
  }
}

TEST_CASE("det functions give these exact bits (the same on every host)", "[math][det]") {
  // Recorded from this implementation; -ffp-contract=off and plain double arithmetic make them
  // a fixed function of the input. If one changes, something reordered the arithmetic: that
  // changes pixels, which needs a new pixel version (tests/test_pixel_version.cpp).
  const auto bits = [](double v) { return std::bit_cast<std::uint64_t>(v); };
  const auto fbits = [](float v) { return std::bit_cast<std::uint32_t>(v); };
  CHECK(bits(det::log2(0.7)) == 0xbfe0776228967d12ull);
  CHECK(bits(det::exp2(-7.3)) == 0x3f79fdf8bcce533eull);
  CHECK(bits(det::pow(0.5, 1.0 / 2.4)) == 0x3fe7f910d768cfb0ull);
  CHECK(fbits(det::powf(0.93f, 64.0f)) == 0x3c1d847cu);
  CHECK(bits(det::sincos(2.5).sin) == 0x3fe326af0dcfcab0ull);
  CHECK(bits(det::sincos(2.5).cos) == 0xbfe9a2f7ef858b7dull);
  CHECK(bits(det::tan(0.36)) == 0x3fd816fbfc7b1d04ull);
}

}  // namespace
}  // namespace dtraced
