// dtraced::render stratified samples: per-pixel Owen-scrambled Sobol' points in two dimensions.
//
// A pixel's film positions, and each area light's shadow-ray positions, are the first two
// dimensions of the Sobol' sequence (a (0,2)-sequence in base 2), with a random permutation of the
// point indices and an independent nested (Owen-type) scramble of each coordinate. Both are
// drawn from counter-based hashes of (seed, frame, pixel, dimension), so a sample is a pure
// function of (seed, frame, pixel x, pixel y, dimension, point index): no state, the same bits on
// every host, thread, tiling and instruction set (integer arithmetic only).
//
// What it buys: the points of any aligned run of 2^k indices [j 2^k, (j + 1) 2^k), in particular
// the first 2^k samples of a pixel, form a (0,k,2)-net: every box of area 2^-k that is a product
// of dyadic intervals holds exactly one point. Adaptive sampling's checkpoints (min_samples times
// a power of two) are such runs when min_samples is a power of two. Each coordinate alone is still
// uniform on [0, 1), so every estimate stays unbiased. Different dimensions get different index
// permutations, so film position and light samples are not paired in lockstep.
// Thread-safe: pure functions.
#pragma once

#include <cstdint>

#include "math/rng.h"

namespace dtraced::render {

struct Sample2 {
  float u = 0.0f;  // [0, 1), a multiple of 2^-24
  float v = 0.0f;  // [0, 1), a multiple of 2^-24
};

// The first two Sobol' dimensions of point `index`, as 32-bit binary fractions (unscrambled).
void sobol2(std::uint32_t index, std::uint32_t& x, std::uint32_t& y);

// Nested (Owen-type) scramble of a 32-bit binary fraction under `seed`: each bit is flipped by a
// seeded function of the bits above it (a few integer multiplies, not one hash per bit). A
// bijection of [0, 2^32) that maps every aligned run of 2^k values onto another one, so it keeps
// nets nets.
std::uint32_t owen_scramble(std::uint32_t value, std::uint64_t seed);

// The 2D sample of dimensions (dim, dim + 1) for point `index` of the pixel that `key` names
// (key.sample is not read: the caller's index says which point), index < 2^24. Points of one
// pixel and dimension pair with indices in an aligned run of 2^k form a (0,k,2)-net.
Sample2 stratified_2d(const math::SampleKey& key, std::uint32_t dim, std::uint32_t index);

// stratified_2d for many points of one pixel and dimension pair: the hashing of (seed, frame,
// pixel, dimension) done once, at construction; at(index) is then a few integer operations and
// gives stratified_2d(key, dim, index), bit for bit.
class PixelSampler2 {
 public:
  PixelSampler2() = default;
  PixelSampler2(const math::SampleKey& key, std::uint32_t dim);
  Sample2 at(std::uint32_t index) const;  // index < 2^24

 private:
  // The scramble constants of the index permutation and of the two coordinates.
  std::uint64_t index_mix_ = 0, u_mix_ = 0, v_mix_ = 0;
};

}  // namespace dtraced::render
