// dtraced::math floating-point helpers for conservative rounding-error bounds (pbrt-v4 style).
//
// gamma(n) bounds the relative error of n successive float operations (gamma_d(n) of double
// ones); next_float_up/down step one ulp. Pure functions: thread-safe.
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace dtraced::math {

inline constexpr float kMachineEpsilon = std::numeric_limits<float>::epsilon() * 0.5f;

constexpr float gamma(int n) { return (float(n) * kMachineEpsilon) / (1.0f - float(n) * kMachineEpsilon); }

// The same for n successive double operations (unit roundoff 2^-53): the bound for a quantity
// computed in double, such as a sphere's hit point.
inline constexpr double kMachineEpsilonD = std::numeric_limits<double>::epsilon() * 0.5;
constexpr double gamma_d(int n) { return (double(n) * kMachineEpsilonD) / (1.0 - double(n) * kMachineEpsilonD); }

// The next representable float above v (+inf stays +inf; -0 becomes the smallest positive).
inline float next_float_up(float v) {
  if (std::isinf(v) && v > 0.0f) return v;
  if (v == -0.0f) v = 0.0f;
  std::uint32_t bits = std::bit_cast<std::uint32_t>(v);
  bits = v >= 0.0f ? bits + 1 : bits - 1;
  return std::bit_cast<float>(bits);
}

inline float next_float_down(float v) {
  if (std::isinf(v) && v < 0.0f) return v;
  if (v == 0.0f) v = -0.0f;
  std::uint32_t bits = std::bit_cast<std::uint32_t>(v);
  bits = v > 0.0f ? bits - 1 : bits + 1;
  return std::bit_cast<float>(bits);
}

#if defined(__SSE2__)
// Four lanes of `off > 0 ? next_float_up(v) : off < 0 ? next_float_down(v) : v` (off 0 or NaN:
// v), without a branch: the same integer steps as the scalar functions, chosen by masks, so the
// same bits (NaN v included). What offset_ray_origin does after its addition, for one ray's three
// components or for four rays' one (a data-dependent branch per component mispredicted there).
inline __m128 step_away4(__m128 v, __m128 off) {
  const __m128 zero = _mm_setzero_ps(), sign = _mm_set1_ps(-0.0f);
  const __m128 inf = _mm_set1_ps(std::numeric_limits<float>::infinity());
  const __m128i up = _mm_castps_si128(_mm_cmpgt_ps(off, zero));    // next_float_up
  const __m128i down = _mm_castps_si128(_mm_cmplt_ps(off, zero));  // next_float_down
  // The lanes that step: not up at +inf, not down at -inf.
  const __m128i step_lane =
      _mm_or_si128(_mm_andnot_si128(_mm_castps_si128(_mm_cmpeq_ps(v, inf)), up),
                   _mm_andnot_si128(_mm_castps_si128(_mm_cmpeq_ps(v, _mm_xor_ps(inf, sign))), down));
  // The step: up, +1 where v >= 0 (+-0 too: it starts from +0), else -1 (NaN too); down, -1 where
  // v > 0, else +1 (+-0 too: it starts from -0). (~m | 1) and (m | 1) are -1 or +1.
  const __m128i one = _mm_set1_epi32(1), ones = _mm_set1_epi32(-1);
  const __m128i step_up = _mm_or_si128(_mm_xor_si128(_mm_castps_si128(_mm_cmpge_ps(v, zero)), ones), one);
  const __m128i step_down = _mm_or_si128(_mm_castps_si128(_mm_cmpgt_ps(v, zero)), one);
  const __m128i step =
      _mm_and_si128(step_lane, _mm_or_si128(_mm_and_si128(up, step_up), _mm_andnot_si128(up, step_down)));
  // The bits stepped from: v's, except a zero that steps starts from +0 up and from -0 down.
  const __m128i from_zero = _mm_and_si128(step_lane, _mm_castps_si128(_mm_cmpeq_ps(v, zero)));
  const __m128i from = _mm_or_si128(_mm_andnot_si128(from_zero, _mm_castps_si128(v)),
                                    _mm_and_si128(from_zero, _mm_and_si128(down, _mm_castps_si128(sign))));
  return _mm_castsi128_ps(_mm_add_epi32(from, step));
}
#endif

}  // namespace dtraced::math
