#include "scene/generate.h"

#include <algorithm>
#include <cassert>
#include <cmath>

#include "math/rng.h"
#include "scene/load.h"

namespace dtraced::scene {
namespace {

// Counter-based randomness: the d-th number of sphere i is a hash of (seed, i, d), so sphere i
// does not depend on how many spheres came before it.
class SphereDice {
 public:
  explicit SphereDice(std::uint64_t seed) : base_(math::mix64(seed ^ 0x5f3759df2b7e1516ULL)) {}

  // Uniform double in [0, 1) with 53 random bits.
  double uniform(std::uint64_t sphere, std::uint64_t dim) const {
    const std::uint64_t h = math::hash_combine(math::hash_combine(base_, sphere), dim);
    return static_cast<double>(h >> 11) * 0x1.0p-53;
  }

 private:
  std::uint64_t base_;
};

// Dimensions of the per-sphere random vector, named so that adding one changes nothing else.
enum Dim : std::uint64_t { kRadius, kOffsetX, kOffsetZ, kKind, kRed, kGreen, kBlue, kSpecular, kShininess };

Material sphere_material(const SphereDice& dice, std::uint64_t i) {
  Material m;
  const double kind = dice.uniform(i, kKind);
  if (kind < 0.80) {
    // Saturated but not pure colours: each channel in [0.1, 0.9].
    m.color = {0.1 + 0.8 * dice.uniform(i, kRed), 0.1 + 0.8 * dice.uniform(i, kGreen),
               0.1 + 0.8 * dice.uniform(i, kBlue)};
    m.diffuse = 0.9;
    m.specular = 0.5 * dice.uniform(i, kSpecular);
    m.shininess = 8 + 120 * dice.uniform(i, kShininess);
  } else if (kind < 0.95) {
    m.color = {0.75 + 0.2 * dice.uniform(i, kRed), 0.75 + 0.2 * dice.uniform(i, kGreen),
               0.75 + 0.2 * dice.uniform(i, kBlue)};
    m.diffuse = 0.1;
    m.specular = 0.8;
    m.shininess = 256;
    m.reflectivity = 0.85;
  } else {
    m.color = {1, 1, 1};
    m.diffuse = 0;
    m.specular = 0.9;
    m.shininess = 512;
    m.transparency = 0.95;
    m.ior = 1.5;
  }
  return m;
}

}  // namespace

SceneDesc generate_sphere_field(std::uint32_t count, std::uint64_t seed) {
  assert(count < kMaxObjects);
  const SphereDice dice(seed);

  // Smallest square grid holding `count` unit cells, centred on the origin in x and z.
  std::uint32_t side = 0;
  while (std::uint64_t(side) * side < count) ++side;
  const double half = 0.5 * side;

  SceneDesc scene;
  scene.objects.reserve(std::size_t(count) + 1);

  Object ground;
  ground.type = ObjectType::kPlane;
  ground.plane = Plane{{0, 0, 0}, {0, 1, 0}};
  ground.material.color = {0.55, 0.55, 0.5};
  ground.material.specular = 0.1;
  scene.objects.push_back(ground);

  for (std::uint32_t i = 0; i < count; ++i) {
    const std::uint32_t row = i / side;
    const std::uint32_t col = i % side;
    const double radius = 0.15 + 0.25 * dice.uniform(i, kRadius);
    // Keep the whole sphere inside its cell: no two spheres touch.
    const double x = -half + col + radius + (1 - 2 * radius) * dice.uniform(i, kOffsetX);
    const double z = -half + row + radius + (1 - 2 * radius) * dice.uniform(i, kOffsetZ);
    Object sphere;
    sphere.type = ObjectType::kSphere;
    sphere.sphere = Sphere{{x, radius, z}, radius};
    sphere.material = sphere_material(dice, i);
    scene.objects.push_back(sphere);
  }

  // From the front edge, raised, looking at a point a little behind the field's centre, so the
  // whole field recedes towards the horizon.
  const double extent = std::max(half, 2.0);
  scene.camera.position = {0, 0.6 * extent + 1, 1.6 * extent + 2};
  scene.camera.look_at = {0, 0, -0.2 * extent};
  scene.camera.up = {0, 1, 0};
  scene.camera.fov_deg = 50;

  // Point lights fall off as 1/r^2: each intensity is chosen for a given irradiance at the
  // field's centre (the origin), so the field is about as bright at any size.
  const double height = 1.5 * extent + 4;
  const auto light = [](Vec3d position, Color color, double irradiance) {
    return PointLight{position, color, irradiance * math::length_squared(position)};
  };
  scene.lights = {
      light({-extent, height, extent}, {1.0, 0.95, 0.9}, 2.0),
      light({extent, height, 0.5 * extent}, {0.9, 0.95, 1.0}, 1.0),
      light({0, 0.5 * height, -1.5 * extent}, {1, 1, 1}, 0.6),
  };

  scene.render.width = 1280;
  scene.render.height = 720;
  scene.render.samples = 1;
  scene.render.max_depth = 8;
  scene.render.background = {0.55, 0.65, 0.85};
  scene.render.seed = seed & kMaxSeed;
  return scene;
}

}  // namespace dtraced::scene
