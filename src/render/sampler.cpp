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
  std::uint64_t h = math::mix64(key.seed ^ 0x510e527fade682d1ull);
  h = math::hash_combine(h, key.frame);
  h = math::hash_combine(h, (std::uint64_t(key.x) << 32) | key.y);
  return math::hash_combine(h, dim);
}

float unit_float(std::uint32_t bits) { return float(bits >> 8) * 0x1.0p-24f; }

}  // namespace

void sobol2(std::uint32_t index, std::uint32_t& x, std::uint32_t& y) {
  // Dimension 0 is the van der Corput sequence (the index's bits reversed). Dimension 1 has the
  // primitive polynomial x + 1: direction number k is the previous one xor itself shifted by one.
  x = 0;
  y = 0;
  std::uint32_t v = 1u << 31;
  for (std::uint32_t bit = 0; index != 0; ++bit, index >>= 1, v ^= v >> 1) {
    if (index & 1u) {
      x ^= 1u << (31 - bit);
      y ^= v;
    }
  }
}

std::uint32_t owen_scramble(std::uint32_t value, std::uint64_t seed, int bits) {
  std::uint32_t flips = 0;
  for (int level = 0; level < bits; ++level) {
    // The `level` bits above bit 31 - level (none at level 0); the level keeps prefixes of
    // different lengths apart.
    const std::uint32_t prefix = level == 0 ? 0u : value >> (32 - level);
    const std::uint64_t h = math::hash_combine(seed, (std::uint64_t(level) << 32) | prefix);
    flips |= std::uint32_t(h >> 63) << (31 - level);
  }
  return value ^ flips;
}

Sample2 stratified_2d(const math::SampleKey& key, std::uint32_t dim, std::uint32_t index) {
  const std::uint64_t seed = pixel_seed(key, dim);
  // Scrambling the index as a binary fraction maps the run [0, 2^k) onto one aligned run of 2^k
  // indices, and a run of a (0,2)-sequence is a net: the prefixes keep their stratification.
  const std::uint32_t shuffled = owen_scramble(index, seed ^ kIndexStream);
  std::uint32_t x, y;
  sobol2(shuffled, x, y);
  // Only the 24 bits a float keeps need scrambling.
  return Sample2{unit_float(owen_scramble(x, seed ^ kUStream, 24)), unit_float(owen_scramble(y, seed ^ kVStream, 24))};
}

}  // namespace dtraced::render
