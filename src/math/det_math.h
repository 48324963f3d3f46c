// dtraced::math::det: elementary functions that give the same bits on every host.
//
// Owns: pow, log2, exp2, sin, cos and tan for everything that reaches a pixel or a vertex (the
// specular lobe, light sampling, the camera, mesh rotations, exposure, sRGB encoding). The C
// library's versions are not a fixed function of their input: glibc picks a variant at run time
// by CPU (an FMA one where the CPU has FMA), and other libc versions round differently, so a
// farm of mixed hosts could render different bits for the same tile. These are written in
// plain IEEE double arithmetic in a fixed order (the build forbids FMA contraction, see the top
// CMakeLists.txt): range reduction that is exact where it matters, then polynomials whose
// coefficients are compile-time constants. Their error is a few units in the last place of a
// double (tests/test_det_math.cpp measures it against the C library and pins exact bits of
// chosen inputs, so a compiler that reordered them would fail there, not in a farm).
//
// Thread safety: pure functions.
#pragma once

namespace dtraced::math::det {

// log2(x) for finite x > 0 (x <= 0 or NaN gives NaN).
double log2(double x);
// 2^y; +inf above 1024, 0 below -1075, NaN for NaN.
double exp2(double y);
// x^y for x >= 0 (NaN for x < 0): 0^0 = 1, 0^y = 0 for y > 0 and +inf for y < 0, 1^y = 1.
double pow(double x, double y);
// x^y from small tables and short series: relative error below 1e-12, for results rounded to
// float or quantised to 16 bits; 0 where x^y < 2^-160, +inf above 2^160. About as fast as the C
// library's pow, a fifth of the time of det::pow.
double pow_fast(double x, double y);
// pow_fast rounded to float once: the specular lobe's cos^shininess.
float powf(float x, float y);
// out[i] = powf(x[i], y[i]) for i < n, the same bits: the specular lobes of a packet's lanes in one
// call, without powf's two calls per lane (out may alias x or y).
void powf(const float* x, const float* y, float* out, int n);

struct SinCos {
  double sin;
  double cos;
};
// sin and cos of x radians, |x| <= 2^20 (beyond that, and for NaN/inf, both are NaN): the
// reduction by pi/2 is exact for such x.
SinCos sincos(double x);
// tan(x) = sin / cos, the same domain.
double tan(double x);

}  // namespace dtraced::math::det
