#include "math/det_math.h"

#include <array>
#include <cmath>
#include <limits>

namespace dtraced::math::det {

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kLn2 = 6.93147180559945286227e-01;
constexpr double kInvLn2 = 1.44269504088896338700e+00;
constexpr double kSqrtHalf = 7.07106781186547572737e-01;
constexpr double kTwoOverPi = 6.36619772367581382433e-01;
// pi/2 in two parts: the first has 33 significant bits, so k * kPio2Hi is exact for |k| < 2^20.
constexpr double kPio2Hi = 1.57079632673412561417e+00;
constexpr double kPio2Lo = 6.07710050650619224932e-11;

// 1/(2i + 1): the series of atanh.
constexpr std::array<double, 13> kOddInverses = [] {
  std::array<double, 13> a{};
  for (std::size_t i = 0; i < a.size(); ++i) a[i] = 1.0 / static_cast<double>(2 * i + 1);
  return a;
}();

// 1/n for the nested Taylor series of e^t.
constexpr int kExpTerms = 18;
constexpr std::array<double, kExpTerms + 1> kInverses = [] {
  std::array<double, kExpTerms + 1> a{};
  for (std::size_t n = 1; n < a.size(); ++n) a[n] = 1.0 / static_cast<double>(n);
  return a;
}();

// 1/((2n)(2n+1)) and 1/((2n-1)(2n)): the nested series of sin and cos.
constexpr int kTrigTerms = 9;
constexpr std::array<double, kTrigTerms + 1> kSinFactors = [] {
  std::array<double, kTrigTerms + 1> a{};
  for (std::size_t n = 1; n < a.size(); ++n) a[n] = 1.0 / static_cast<double>((2 * n) * (2 * n + 1));
  return a;
}();
constexpr std::array<double, kTrigTerms + 1> kCosFactors = [] {
  std::array<double, kTrigTerms + 1> a{};
  for (std::size_t n = 1; n < a.size(); ++n) a[n] = 1.0 / static_cast<double>((2 * n - 1) * (2 * n));
  return a;
}();

}  // namespace

double log2(double x) {
  if (std::isnan(x) || x < 0.0) return kNaN;
  if (x == 0.0) return -kInf;
  if (std::isinf(x)) return kInf;
  // x = m 2^k exactly, m in [sqrt(1/2), sqrt(2)).
  int k = 0;
  double m = std::frexp(x, &k);
  if (m < kSqrtHalf) {
    m *= 2.0;
    --k;
  }
  // ln m = 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.1716: the terms to s^25 leave < 1e-20.
  const double s = (m - 1.0) / (m + 1.0);
  const double s2 = s * s;
  double p = kOddInverses.back();
  for (std::size_t i = kOddInverses.size() - 1; i-- > 0;) p = p * s2 + kOddInverses[i];
  const double ln_m = 2.0 * s * p;
  return static_cast<double>(k) + ln_m * kInvLn2;
}

double exp2(double y) {
  if (std::isnan(y)) return y;
  if (y > 1024.0) return kInf;
  if (y < -1075.0) return 0.0;
  // 2^y = 2^k e^(f ln 2), k the nearest integer, |f| <= 1/2 (y - k is exact).
  const double k = std::floor(y + 0.5);
  const double t = (y - k) * kLn2;
  // e^t = 1 + t (1 + t/2 (1 + t/3 (...))), |t| <= 0.347: the terms to t^18 leave < 1e-25.
  double p = 1.0;
  for (int n = kExpTerms; n >= 1; --n) p = 1.0 + p * t * kInverses[static_cast<std::size_t>(n)];
  return std::ldexp(p, static_cast<int>(k));
}

double pow(double x, double y) {
  if (std::isnan(x) || std::isnan(y) || x < 0.0) return kNaN;
  if (y == 0.0 || x == 1.0) return 1.0;
  if (x == 0.0) return y > 0.0 ? 0.0 : kInf;
  if (std::isinf(x)) return y > 0.0 ? kInf : 0.0;
  return exp2(y * log2(x));
}

float powf(float x, float y) { return static_cast<float>(pow(static_cast<double>(x), static_cast<double>(y))); }

SinCos sincos(double x) {
  if (!(std::fabs(x) <= 1048576.0)) return {kNaN, kNaN};
  // x = k pi/2 + r, |r| <= pi/4 (plus rounding); k * kPio2Hi is exact.
  const double k = std::floor(x * kTwoOverPi + 0.5);
  const double r = (x - k * kPio2Hi) - k * kPio2Lo;
  const double r2 = r * r;
  // sin r = r (1 - r^2/(2*3) (1 - r^2/(4*5) (...))), cos r = 1 - r^2/(1*2) (1 - r^2/(3*4) (...)):
  // the terms to r^19 and r^18 leave < 1e-18 for |r| <= pi/4.
  double s = 1.0;
  double c = 1.0;
  for (int n = kTrigTerms; n >= 1; --n) {
    s = 1.0 - s * r2 * kSinFactors[static_cast<std::size_t>(n)];
    c = 1.0 - c * r2 * kCosFactors[static_cast<std::size_t>(n)];
  }
  s *= r;
  switch (static_cast<long long>(k) & 3) {  // k mod 4, also for negative k (two's complement)
    case 0:
      return {s, c};
    case 1:
      return {c, -s};
    case 2:
      return {-s, -c};
    default:
      return {-c, s};
  }
}

double tan(double x) {
  const SinCos sc = sincos(x);
  return sc.sin / sc.cos;
}

}  // namespace dtraced::math::det
