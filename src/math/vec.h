// dtraced::math vectors.
//
// Owns: the 3-vector value type used by every layer (float for render-ready data, double for
// scene descriptions and reference computations). Plain values, no state: thread-safe.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>

namespace dtraced::math {

template <typename T>
struct Vec3 {
  T x{}, y{}, z{};

  constexpr Vec3() = default;
  constexpr Vec3(T x_, T y_, T z_) : x(x_), y(y_), z(z_) {}
  template <typename U>
  constexpr explicit Vec3(const Vec3<U>& o) : x(T(o.x)), y(T(o.y)), z(T(o.z)) {}

  constexpr T operator[](std::size_t i) const { return i == 0 ? x : (i == 1 ? y : z); }
  constexpr T& operator[](std::size_t i) { return i == 0 ? x : (i == 1 ? y : z); }

  constexpr Vec3 operator-() const { return {-x, -y, -z}; }
  constexpr Vec3& operator+=(const Vec3& o) {
    x += o.x;
    y += o.y;
    z += o.z;
    return *this;
  }
  constexpr Vec3& operator-=(const Vec3& o) {
    x -= o.x;
    y -= o.y;
    z -= o.z;
    return *this;
  }
  constexpr Vec3& operator*=(T s) {
    x *= s;
    y *= s;
    z *= s;
    return *this;
  }
  constexpr bool operator==(const Vec3&) const = default;
};

using Vec3f = Vec3<float>;
using Vec3d = Vec3<double>;

template <typename T>
constexpr Vec3<T> operator+(Vec3<T> a, const Vec3<T>& b) {
  return a += b;
}
template <typename T>
constexpr Vec3<T> operator-(Vec3<T> a, const Vec3<T>& b) {
  return a -= b;
}
template <typename T>
constexpr Vec3<T> operator*(Vec3<T> a, T s) {
  return a *= s;
}
template <typename T>
constexpr Vec3<T> operator*(T s, Vec3<T> a) {
  return a *= s;
}
template <typename T>
constexpr Vec3<T> operator/(const Vec3<T>& a, T s) {
  return {a.x / s, a.y / s, a.z / s};
}
// Component-wise product (colours, per-axis error bounds).
template <typename T>
constexpr Vec3<T> mul(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.x * b.x, a.y * b.y, a.z * b.z};
}

template <typename T>
constexpr T dot(const Vec3<T>& a, const Vec3<T>& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
template <typename T>
constexpr Vec3<T> cross(const Vec3<T>& a, const Vec3<T>& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <typename T>
inline T length_squared(const Vec3<T>& a) {
  return dot(a, a);
}
template <typename T>
inline T length(const Vec3<T>& a) {
  return std::sqrt(dot(a, a));
}
template <typename T>
inline Vec3<T> normalize(const Vec3<T>& a) {
  return a / length(a);
}
template <typename T>
constexpr Vec3<T> abs(const Vec3<T>& a) {
  return {std::abs(a.x), std::abs(a.y), std::abs(a.z)};
}
template <typename T>
constexpr Vec3<T> min(const Vec3<T>& a, const Vec3<T>& b) {
  return {std::min(a.x, b.x), std::min(a.y, b.y), std::min(a.z, b.z)};
}
template <typename T>
constexpr Vec3<T> max(const Vec3<T>& a, const Vec3<T>& b) {
  return {std::max(a.x, b.x), std::max(a.y, b.y), std::max(a.z, b.z)};
}
template <typename T>
constexpr T max_component(const Vec3<T>& a) {
  return std::max(a.x, std::max(a.y, a.z));
}
template <typename T>
constexpr std::size_t max_dimension(const Vec3<T>& a) {
  return a.x > a.y ? (a.x > a.z ? 0 : 2) : (a.y > a.z ? 1 : 2);
}
template <typename T>
inline bool is_finite(const Vec3<T>& a) {
  return std::isfinite(a.x) && std::isfinite(a.y) && std::isfinite(a.z);
}

}  // namespace dtraced::math
