// dtraced::math floating-point helpers for conservative rounding-error bounds (pbrt-v4 style).
//
// gamma(n) bounds the relative error of n successive float operations (gamma_d(n) of double
// ones); next_float_up/down step one ulp. Pure functions: thread-safe.
#pragma once

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>

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

}  // namespace dtraced::math
