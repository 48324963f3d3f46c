#include "math/det_math.h"

#include <array>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

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

// floor(v) as an integer, for |v| < 2^62, without a call into the C library (baseline x86-64
// has no rounding instruction, so std::floor is a call there): truncation, then one step down for
// negative non-integers. Exact.
long long floor_int(double v) {
  const auto t = static_cast<long long>(v);
  return static_cast<double>(t) > v ? t - 1 : t;
}

// p * 2^k, exactly (one rounding only where the result is subnormal), without ldexp's call.
double scale2(double p, long long k) {
  const auto power = [](long long e) { return std::bit_cast<double>(static_cast<std::uint64_t>(e + 1023) << 52); };
  if (k > 1023) return p * power(1023) * power(k - 1023 > 1023 ? 1023 : k - 1023);
  if (k < -1022) return p * power(-1022) * power(k + 1022 < -1022 ? -1022 : k + 1022);
  return p * power(k);
}

// x = m 2^k exactly with m in [sqrt(1/2), sqrt(2)), for finite x > 0 (subnormals too).
double split(double x, int& k) {
  int bias = 0;
  if (x < 2.2250738585072014e-308) {  // subnormal: make it normal first (exact)
    x *= 18014398509481984.0;         // 2^54
    bias = -54;
  }
  const auto bits = std::bit_cast<std::uint64_t>(x);
  k = static_cast<int>((bits >> 52) & 0x7ff) - 1023 + bias;
  double m = std::bit_cast<double>((bits & 0x000fffffffffffffull) | 0x3ff0000000000000ull);  // [1, 2)
  if (m >= 2.0 * kSqrtHalf) {
    m *= 0.5;
    ++k;
  }
  return m;
}

// ln m for m in [sqrt(1/2), sqrt(2)): 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.1716, the odd
// series to s^(2 terms - 1).
constexpr double ln_reduced(double m, std::size_t terms) {
  const double s = (m - 1.0) / (m + 1.0);
  const double s2 = s * s;
  double p = kOddInverses[terms - 1];
  for (std::size_t i = terms - 1; i-- > 0;) p = p * s2 + kOddInverses[i];
  return 2.0 * s * p;
}

// e^t for |t| <= 0.347 by the nested Taylor series to t^terms.
constexpr double exp_reduced(double t, int terms) {
  double p = 1.0;
  for (int n = terms; n >= 1; --n) p = 1.0 + p * t * kInverses[static_cast<std::size_t>(n)];
  return p;
}

// The terms of the full-precision functions: below 1e-18 truncation error.
constexpr std::size_t kLnTerms = 13;

// pow_fast: tables instead of long series and without a division (the atanh series needs one).
// log2 x = k + log2 c + ln(1 + u) / ln 2 with x = m 2^k, m in [1, 2), c the centre of m's
// 1/128-wide interval and u = (m - c) / c, |u| < 2^-8 (m - c is exact; the product by 1/c rounds
// once), ln(1 + u) to u^5 (truncation below 1e-15). 2^e = 2^(N/64) 2^g with N the nearest integer
// to 64 e, |g| <= 1/128 (e - N/64 is exact), 2^(j/64) from a table, e^(g ln 2) to the 4th power
// (below 1e-13). The tables are computed by the compiler with the full-precision series
// (ln_reduced, exp_reduced) in IEEE double arithmetic, so every build holds the same bits.
constexpr int kPowLogBits = 7;
constexpr int kPowLogSize = 1 << kPowLogBits;
constexpr int kPowExpBits = 6;
constexpr int kPowExpSize = 1 << kPowExpBits;

// c_i = 1 + (i + 1/2) / 128 and, for it, 1/c_i and log2 c_i.
struct PowLogEntry {
  double centre, inverse, log2;
};
constexpr std::array<PowLogEntry, kPowLogSize> kPowLog = [] {
  std::array<PowLogEntry, kPowLogSize> a{};
  for (int i = 0; i < kPowLogSize; ++i) {
    const double c = 1.0 + (static_cast<double>(i) + 0.5) / static_cast<double>(kPowLogSize);
    const double l =
        c >= 2.0 * kSqrtHalf ? 1.0 + ln_reduced(0.5 * c, kLnTerms) * kInvLn2 : ln_reduced(c, kLnTerms) * kInvLn2;
    a[static_cast<std::size_t>(i)] = {c, 1.0 / c, l};
  }
  return a;
}();

// 2^(j/64), j = 0..63, by exp_reduced (t < 0.69 here: its 18 terms still leave < 1e-19).
constexpr std::array<double, kPowExpSize> kPowExp = [] {
  std::array<double, kPowExpSize> a{};
  for (int j = 0; j < kPowExpSize; ++j)
    a[static_cast<std::size_t>(j)] =
        exp_reduced(static_cast<double>(j) / static_cast<double>(kPowExpSize) * kLn2, kExpTerms);
  return a;
}();

// pow_fast for normal x > 0, x != 1, y finite and non-zero.
double pow_fast_normal(double x, double y) {
  const auto bits = std::bit_cast<std::uint64_t>(x);
  const auto k = static_cast<double>(static_cast<int>((bits >> 52) & 0x7ff) - 1023);
  const double m = std::bit_cast<double>((bits & 0x000fffffffffffffull) | 0x3ff0000000000000ull);
  const PowLogEntry& entry = kPowLog[(bits >> (52 - kPowLogBits)) & (kPowLogSize - 1)];
  const double u = (m - entry.centre) * entry.inverse;
  const double u2 = u * u;
  const double ln1p = u + u2 * ((-0.5 + u * (1.0 / 3.0)) + u2 * (-0.25 + u * 0.2));
  const double e = y * ((k + entry.log2) + ln1p * kInvLn2);
  // Beyond float's range either way (2^-150 rounds to 0, 2^129 to infinity).
  if (!(e > -160.0)) return 0.0;
  if (!(e < 160.0)) return kInf;
  // N = 64 e rounded to the nearest integer (ties to even): adding 1.5 * 2^52 leaves it in the
  // low bits of the sum's significand, exactly and without a branch.
  constexpr double kShift = 6755399441055744.0;
  const double shifted = e * static_cast<double>(kPowExpSize) + kShift;
  const auto n = static_cast<long long>(std::bit_cast<std::uint64_t>(shifted) & 0x000fffffffffffffull) - (1ll << 51);
  const double t = (e - static_cast<double>(n) * (1.0 / kPowExpSize)) * kLn2;
  const double t2 = t * t;
  const double p = (1.0 + t) + t2 * ((0.5 + t * (1.0 / 6.0)) + t2 * (1.0 / 24.0));
  // n >> 6 is floor(n / 64) for negative n too (C++20 shifts are arithmetic); |n >> 6| <= 160.
  const double power = std::bit_cast<double>(static_cast<std::uint64_t>((n >> kPowExpBits) + 1023) << 52);
  return kPowExp[static_cast<std::size_t>(n & (kPowExpSize - 1))] * p * power;
}

double log2_full(double x) {
  int k = 0;
  const double m = split(x, k);
  return static_cast<double>(k) + ln_reduced(m, kLnTerms) * kInvLn2;
}

double exp2_full(double y) {
  // 2^y = 2^k e^(f ln 2), k the nearest integer, |f| <= 1/2 (y - k is exact).
  const long long k = floor_int(y + 0.5);
  const double t = (y - static_cast<double>(k)) * kLn2;
  return scale2(exp_reduced(t, kExpTerms), k);
}

}  // namespace

double log2(double x) {
  if (std::isnan(x) || x < 0.0) return kNaN;
  if (x == 0.0) return -kInf;
  if (std::isinf(x)) return kInf;
  return log2_full(x);
}

double exp2(double y) {
  if (std::isnan(y)) return y;
  if (y > 1024.0) return kInf;
  if (y < -1075.0) return 0.0;
  // Whole powers of two exactly and at once (an exposure of 0 stops is the common case).
  if (const long long k = floor_int(y); static_cast<double>(k) == y) return scale2(1.0, k);
  return exp2_full(y);
}

double pow(double x, double y) {
  if (std::isnan(x) || std::isnan(y) || x < 0.0) return kNaN;
  if (y == 0.0 || x == 1.0) return 1.0;
  if (x == 0.0) return y > 0.0 ? 0.0 : kInf;
  if (std::isinf(x)) return y > 0.0 ? kInf : 0.0;
  return exp2(y * log2(x));
}

// pow_fast's common case, which pow_fast_normal computes: a normal, finite x other than 1 and a
// finite, non-zero y.
static bool pow_fast_is_normal(double x, double y) {
  return x >= 2.2250738585072014e-308 && x < kInf && x != 1.0 && y != 0.0 && std::fabs(y) < kInf;
}

double pow_fast(double x, double y) {
  if (pow_fast_is_normal(x, y)) return pow_fast_normal(x, y);
  if (std::isnan(x) || std::isnan(y) || x < 0.0) return kNaN;
  if (y == 0.0 || x == 1.0) return 1.0;
  if (x == 0.0) return y > 0.0 ? 0.0 : kInf;
  if (std::isinf(x)) return y > 0.0 ? kInf : 0.0;
  if (std::isinf(y)) return (x < 1.0) == (y > 0.0) ? 0.0 : kInf;
  return pow(x, y);  // a subnormal x: the full-precision function
}

float powf(float x, float y) { return static_cast<float>(pow_fast(x, y)); }

#if defined(__SSE2__)
namespace {

// pow_fast_normal of two (x, y) pairs at once, the same operations in the same order (SSE2's
// double arithmetic rounds as the scalar one does); the range checks select at the end.
__m128d pow_fast_normal2(__m128d x, __m128d y) {
  const __m128i bits = _mm_castpd_si128(x);
  const __m128i mantissa = _mm_set1_epi64x(0x000fffffffffffffll);
  // The biased exponents (below 2^11) as doubles: the low 32 bits of each lane, converted.
  const __m128i biased = _mm_srli_epi64(bits, 52);
  const __m128d k =
      _mm_sub_pd(_mm_cvtepi32_pd(_mm_shuffle_epi32(biased, _MM_SHUFFLE(3, 3, 2, 0))), _mm_set1_pd(1023.0));
  const __m128d m =
      _mm_castsi128_pd(_mm_or_si128(_mm_and_si128(bits, mantissa), _mm_set1_epi64x(0x3ff0000000000000ll)));
  const __m128i index = _mm_and_si128(_mm_srli_epi64(bits, 52 - kPowLogBits), _mm_set1_epi64x(kPowLogSize - 1));
  const PowLogEntry& a = kPowLog[static_cast<std::size_t>(_mm_cvtsi128_si32(index))];
  const PowLogEntry& b =
      kPowLog[static_cast<std::size_t>(_mm_cvtsi128_si32(_mm_shuffle_epi32(index, _MM_SHUFFLE(3, 3, 3, 2))))];
  const __m128d u = _mm_mul_pd(_mm_sub_pd(m, _mm_setr_pd(a.centre, b.centre)), _mm_setr_pd(a.inverse, b.inverse));
  const __m128d u2 = _mm_mul_pd(u, u);
  const __m128d ln1p = _mm_add_pd(
      u, _mm_mul_pd(u2, _mm_add_pd(_mm_add_pd(_mm_set1_pd(-0.5), _mm_mul_pd(u, _mm_set1_pd(1.0 / 3.0))),
                                   _mm_mul_pd(u2, _mm_add_pd(_mm_set1_pd(-0.25), _mm_mul_pd(u, _mm_set1_pd(0.2)))))));
  const __m128d e =
      _mm_mul_pd(y, _mm_add_pd(_mm_add_pd(k, _mm_setr_pd(a.log2, b.log2)), _mm_mul_pd(ln1p, _mm_set1_pd(kInvLn2))));
  constexpr double kShift = 6755399441055744.0;
  const __m128d shifted = _mm_add_pd(_mm_mul_pd(e, _mm_set1_pd(static_cast<double>(kPowExpSize))), _mm_set1_pd(kShift));
  // n in the low bits of `shifted`; as a double it is shifted - kShift, exactly (for e in range).
  const __m128i n = _mm_sub_epi64(_mm_and_si128(_mm_castpd_si128(shifted), mantissa), _mm_set1_epi64x(1ll << 51));
  const __m128d nd = _mm_sub_pd(shifted, _mm_set1_pd(kShift));
  const __m128d t = _mm_mul_pd(_mm_sub_pd(e, _mm_mul_pd(nd, _mm_set1_pd(1.0 / kPowExpSize))), _mm_set1_pd(kLn2));
  const __m128d t2 = _mm_mul_pd(t, t);
  const __m128d p =
      _mm_add_pd(_mm_add_pd(_mm_set1_pd(1.0), t),
                 _mm_mul_pd(t2, _mm_add_pd(_mm_add_pd(_mm_set1_pd(0.5), _mm_mul_pd(t, _mm_set1_pd(1.0 / 6.0))),
                                           _mm_mul_pd(t2, _mm_set1_pd(1.0 / 24.0)))));
  // n >> 6 (floor, |n| small in range) on the low 32 bits of each lane, then into the exponent.
  const __m128i n32 = _mm_shuffle_epi32(n, _MM_SHUFFLE(3, 3, 2, 0));
  const __m128i exponent = _mm_add_epi32(_mm_srai_epi32(n32, kPowExpBits), _mm_set1_epi32(1023));
  const __m128d power = _mm_castsi128_pd(_mm_slli_epi64(_mm_unpacklo_epi32(exponent, _mm_setzero_si128()), 52));
  const int j0 = _mm_cvtsi128_si32(n32) & (kPowExpSize - 1);
  const int j1 = _mm_cvtsi128_si32(_mm_shuffle_epi32(n32, _MM_SHUFFLE(3, 3, 3, 1))) & (kPowExpSize - 1);
  const __m128d table = _mm_setr_pd(kPowExp[static_cast<std::size_t>(j0)], kPowExp[static_cast<std::size_t>(j1)]);
  const __m128d r = _mm_mul_pd(_mm_mul_pd(table, p), power);
  // !(e > -160): 0 (NaN too); !(e < 160): +inf.
  const __m128d low = _mm_cmpgt_pd(e, _mm_set1_pd(-160.0));
  const __m128d high = _mm_cmplt_pd(e, _mm_set1_pd(160.0));
  const __m128d in_range = _mm_or_pd(_mm_and_pd(high, r), _mm_andnot_pd(high, _mm_set1_pd(kInf)));
  return _mm_and_pd(low, in_range);
}

}  // namespace
#endif

void powf(const float* x, const float* y, float* out, int n) {
  int i = 0;
#if defined(__SSE2__)
  // Two entries at a time where both are pow_fast_normal's case (pow_fast_normal2): the render
  // phase of whitted10 went down by 2.7 %.
  for (; i + 2 <= n; i += 2) {
    const double x0 = x[i], y0 = y[i], x1 = x[i + 1], y1 = y[i + 1];
    if (pow_fast_is_normal(x0, y0) && pow_fast_is_normal(x1, y1)) {
      const __m128d r = pow_fast_normal2(_mm_setr_pd(x0, x1), _mm_setr_pd(y0, y1));
      const __m128 f = _mm_cvtpd_ps(r);
      out[i] = _mm_cvtss_f32(f);
      out[i + 1] = _mm_cvtss_f32(_mm_shuffle_ps(f, f, _MM_SHUFFLE(1, 1, 1, 1)));
    } else {
      out[i] = static_cast<float>(pow_fast(x0, y0));
      out[i + 1] = static_cast<float>(pow_fast(x1, y1));
    }
  }
#endif
  for (; i < n; ++i) {
    const double xd = x[i], yd = y[i];
    // pow_fast's own test for its common case, and pow_fast_normal inlined here.
    out[i] = static_cast<float>(pow_fast_is_normal(xd, yd) ? pow_fast_normal(xd, yd) : pow_fast(xd, yd));
  }
}

SinCos sincos(double x) {
  if (!(std::fabs(x) <= 1048576.0)) return {kNaN, kNaN};
  // x = k pi/2 + r, |r| <= pi/4 (plus rounding); k * kPio2Hi is exact.
  const double k = static_cast<double>(floor_int(x * kTwoOverPi + 0.5));
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
