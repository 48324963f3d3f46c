// dtraced::scene generated scenes, for stress tests and benchmarks that should not ship a
// multi-megabyte file.
//
// Pure functions of their arguments: the same (count, seed) gives the same SceneDesc, and so the
// same digest, on every host (integer hashing and correctly rounded arithmetic only; no libm
// transcendental functions, whose last bits vary between C libraries). Thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "scene/description.h"

namespace dtraced::scene {

// `count` spheres (radius 0.15 to 0.4) resting on a ground plane, one per cell of a square grid
// with unit cells so they never overlap; about 80% diffuse with a specular highlight, 15%
// mirrors, 5% glass. A camera looks across the field, three point lights above it; render
// settings 1280x720, 1 sample, render.seed = `seed` mod 2^53 (the loader's seed limit). The
// result passes the loader's checks.
// Precondition: count < kMaxObjects (load.h), so the scene with its plane stays loadable.
SceneDesc generate_sphere_field(std::uint32_t count, std::uint64_t seed);

// A file the mesh generator writes beside its scene; `path` is relative to the scene's directory.
struct GeneratedFile {
  std::string path;
  std::string text;
};

// A scene file (JSON text, meshes given by "file") and the OBJ files it names.
struct GeneratedMeshScene {
  std::string scene_json;
  std::vector<GeneratedFile> objs;
  std::size_t triangles = 0;  // of all mesh objects, as the loader will count them
};

// About `triangles` triangles of meshes (at least a few hundred whatever the request): a gently
// rolling tessellated ground, and on it tessellated spheres and tori (one OBJ each, placed several
// times by translate/rotate/scale) in a grid with seeded jitter; a mirror sphere, a glass sphere,
// coloured glossy spheres and tori, two point lights, 960x540 at 2 samples. The OBJ files are
// `model_prefix`-ground.obj, -sphere.obj and -torus.obj (model_prefix relative to the scene's
// directory, e.g. "models/mesh"). Vertices are written with 6 decimals, and sines and cosines come
// from a Taylor series in plain arithmetic rather than libm, so the same arguments give the same
// bytes on every host. Precondition: 1 <= triangles <= kMaxTriangles (load.h).
GeneratedMeshScene generate_mesh_scene(std::uint32_t triangles, std::uint64_t seed, const std::string& model_prefix);

}  // namespace dtraced::scene
