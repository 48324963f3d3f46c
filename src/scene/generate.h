// dtraced::scene generated scenes, for stress tests and benchmarks that should not ship a
// multi-megabyte file.
//
// Pure functions of their arguments: the same (count, seed) gives the same SceneDesc, and so the
// same digest, on every host (integer hashing and correctly rounded arithmetic only; no libm
// transcendental functions, whose last bits vary between C libraries). Thread-safe.
#pragma once

#include <cstdint>

#include "scene/description.h"

namespace dtraced::scene {

// `count` spheres (radius 0.15 to 0.4) resting on a ground plane, one per cell of a square grid
// with unit cells so they never overlap; about 80% diffuse with a specular highlight, 15%
// mirrors, 5% glass. A camera looks across the field, three point lights above it; render
// settings 1280x720, 1 sample, render.seed = `seed` mod 2^53 (the loader's seed limit). The
// result passes the loader's checks.
// Precondition: count < kMaxObjects (load.h), so the scene with its plane stays loadable.
SceneDesc generate_sphere_field(std::uint32_t count, std::uint64_t seed);

}  // namespace dtraced::scene
