#include "render/sampler.h"

namespace dtraced::render {

namespace {

// Domain separators: the index permutation and the two coordinates' scrambles draw from
// unrelated hash streams of the same (pixel, dimension).
constexpr std::uint64_t kIndexStream = 0x243f6a8885a308d3ull;
constexpr std::uint64_t kUStream = 0x13198a2e03707344ull;
constexpr std::uint64_t kVStream = 0xa4093822299f31d0ull;

// The scramble seed of one pixel and dimension pair, the same for all of its points.
std::uint64_t pixel_seed(const math::SampleKey& key, std::uint32_t dim) {
  std::uint64_t h = math::mix64(key.seed ^ 0x510e527fade682d1ull ^ (std::uint64_t(key.frame) << 32 | dim));
  return math::hash_combine(h, (std::uint64_t(key.x) << 32) | key.y);
}

std::uint32_t reverse_bits(std::uint32_t x) {
  x = ((x >> 1) & 0x55555555u) | ((x & 0x55555555u) << 1);
  x = ((x >> 2) & 0x33333333u) | ((x & 0x33333333u) << 2);
  x = ((x >> 4) & 0x0f0f0f0fu) | ((x & 0x0f0f0f0fu) << 4);
  x = ((x >> 8) & 0x00ff00ffu) | ((x & 0x00ff00ffu) << 8);
  return (x >> 16) | (x << 16);
}

// A random bijection of 32-bit integers in which bit k of the result is bit k of x flipped by a
// function of x's lower bits only: adding a constant, multiplying by an odd one and xoring in a
// product with an even one all carry information upwards only. Applied to a binary fraction with
// its bits reversed, that is a nested (Owen-type) scramble: each bit flipped by a function of
// the more significant bits, with constants drawn from `a` (mix64 of a seed).
inline std::uint32_t scramble_upwards_mixed(std::uint32_t x, std::uint64_t a) {
  x += std::uint32_t(a);
  x *= std::uint32_t(a >> 32) | 1u;
  x ^= x * 0x6a5d39eau;
  x += std::uint32_t(a >> 17);
  x ^= x * 0xb36534e6u;
  return x;
}

// The same with the seed's constants drawn here (a = mix64(seed)).
inline std::uint32_t scramble_upwards(std::uint32_t x, std::uint64_t seed) {
  return scramble_upwards_mixed(x, math::mix64(seed));
}

float unit_float(std::uint32_t bits) { return float(bits >> 8) * 0x1.0p-24f; }

inline std::uint32_t owen(std::uint32_t value, std::uint64_t seed) {
  return reverse_bits(scramble_upwards(reverse_bits(value), seed));
}

// Sobol' dimension 1 with its bits reversed. Its direction numbers (primitive polynomial x + 1)
// are the rows of Pascal's triangle mod 2: index bit b adds C(b, j) mod 2 to result bit 31 - j,
// and by Lucas' theorem C(b, j) is odd exactly when the bits of j are a subset of those of b. So
// bit j of the reversed result is the xor of the index bits b that are supersets of j: the
// superset-sum transform over GF(2), one shift, mask and xor for each of the 5 bits of j
// (instead of a step for each of the index's bits).
inline std::uint32_t sobol1_reversed(std::uint32_t index) {
  index ^= (index >> 1) & 0x55555555u;
  index ^= (index >> 2) & 0x33333333u;
  index ^= (index >> 4) & 0x0f0f0f0fu;
  index ^= (index >> 8) & 0x00ff00ffu;
  index ^= (index >> 16) & 0x0000ffffu;
  return index;
}

}  // namespace

void sobol2(std::uint32_t index, std::uint32_t& x, std::uint32_t& y) {
  // Dimension 0 is the van der Corput sequence (the index's bits reversed).
  x = reverse_bits(index);
  y = reverse_bits(sobol1_reversed(index));
}

std::uint32_t owen_scramble(std::uint32_t value, std::uint64_t seed) { return owen(value, seed); }

PixelSampler2::PixelSampler2(const math::SampleKey& key, std::uint32_t dim) {
  const std::uint64_t seed = pixel_seed(key, dim);
  index_mix_ = math::mix64(seed ^ kIndexStream);
  u_mix_ = math::mix64(seed ^ kUStream);
  v_mix_ = math::mix64(seed ^ kVStream);
}

Sample2 PixelSampler2::at(std::uint32_t index) const {
  // Scrambling the index as a binary fraction maps the run [0, 2^k) onto one aligned run of 2^k
  // indices, and a run of a (0,2)-sequence is a net: the prefixes keep their stratification.
  // Indices are below 2^24, so the bits above are zero and their flips only choose the run: they
  // are dropped, which keeps the map a bijection of [0, 2^24).
  const std::uint32_t shuffled = reverse_bits(scramble_upwards_mixed(reverse_bits(index), index_mix_)) & 0xffffffu;
  // Dimension 0 of the point is the shuffled index reversed; scrambling reverses it back.
  const std::uint32_t u = reverse_bits(scramble_upwards_mixed(shuffled, u_mix_));
  // Dimension 1 is Sobol's second dimension, whose owen scramble reverses, scrambles and
  // reverses back: the reversed form goes straight in.
  const std::uint32_t v = reverse_bits(scramble_upwards_mixed(sobol1_reversed(shuffled), v_mix_));
  return Sample2{unit_float(u), unit_float(v)};
}

Sample2 stratified_2d(const math::SampleKey& key, std::uint32_t dim, std::uint32_t index) {
  return PixelSampler2(key, dim).at(index);
}

}  // namespace dtraced::render
