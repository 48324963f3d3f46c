// dtraced::math counter-based random numbers.
//
// Every random number in dtraced is a pure function of (seed, frame, pixel x, pixel y, sample
// index, dimension): no generator state, so a pixel renders to the same bits whichever thread,
// tile, worker or restart computes it. The mixer is a 64-bit finaliser (splitmix64 / Stafford
// variant 13) applied in a chain over the key words. Thread-safe.
#pragma once

#include <cstdint>

namespace dtraced::math {

constexpr std::uint64_t mix64(std::uint64_t z) {
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

constexpr std::uint64_t hash_combine(std::uint64_t h, std::uint64_t v) {
  return mix64(h ^ (v + 0x9e3779b97f4a7c15ULL + (h << 6) + (h >> 2)));
}

// Key of one pixel sample; `sample_hash(key, dim)` gives the dim-th random word of that sample.
struct SampleKey {
  std::uint64_t seed = 0;
  std::uint32_t frame = 0;
  std::uint32_t x = 0;
  std::uint32_t y = 0;
  std::uint32_t sample = 0;
};

constexpr std::uint64_t sample_hash(const SampleKey& k, std::uint32_t dim) {
  std::uint64_t h = mix64(k.seed ^ 0x6a09e667f3bcc909ULL);
  h = hash_combine(h, (std::uint64_t(k.frame) << 32) | k.sample);
  h = hash_combine(h, (std::uint64_t(k.x) << 32) | k.y);
  h = hash_combine(h, dim);
  return h;
}

// Uniform float in [0, 1): the top 24 bits, so every value is exact and < 1.
constexpr float to_unit_float(std::uint64_t h) { return float(h >> 40) * 0x1.0p-24f; }

constexpr float sample_uniform(const SampleKey& k, std::uint32_t dim) { return to_unit_float(sample_hash(k, dim)); }

}  // namespace dtraced::math
