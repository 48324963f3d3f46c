#include "scene/generate.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <numbers>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <fmt/format.h>

#include "jsonio/write.h"
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
    return Light{position, color, irradiance * math::length_squared(position)};
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

namespace dtraced::scene {
namespace {

namespace json = boost::json;

// sin and cos by their Taylor series after reducing x to [-pi, pi]: only correctly rounded + - *
// and /, so every host computes the same bits (libm's last bits differ between C libraries, and
// the generated files must not).
std::pair<double, double> sin_cos(double x) {
  constexpr double kTwoPi = 2.0 * std::numbers::pi;
  x -= kTwoPi * std::round(x / kTwoPi);
  double s = 0, c = 0, ts = x, tc = 1;
  for (int k = 0; k < 24; ++k) {
    s += ts;
    c += tc;
    ts *= -x * x / double((2 * k + 2) * (2 * k + 3));
    tc *= -x * x / double((2 * k + 1) * (2 * k + 2));
  }
  return {s, c};
}

// Height of the rolling ground at (x, z).
double ground_height(double x, double z) {
  return 0.12 * sin_cos(0.55 * x + 0.3).first * sin_cos(0.45 * z - 0.2).second;
}

void vertex(std::string& out, double x, double y, double z) { out += fmt::format("v {:.6f} {:.6f} {:.6f}\n", x, y, z); }

// A square heightfield of side 2 * half, cells x cells quads (two triangles each).
std::string ground_obj(int cells, double half) {
  std::string out = fmt::format("# dtraced generate: ground, {} triangles\n", 2 * cells * cells);
  for (int j = 0; j <= cells; ++j) {
    for (int i = 0; i <= cells; ++i) {
      const double x = -half + 2 * half * i / cells, z = -half + 2 * half * j / cells;
      vertex(out, x, ground_height(x, z), z);
    }
  }
  // Counter-clockwise seen from above, so the normals point up (+y).
  for (int j = 0; j < cells; ++j) {
    for (int i = 0; i < cells; ++i) {
      const int a = j * (cells + 1) + i + 1;
      out += fmt::format("f {} {} {} {}\n", a, a + cells + 1, a + cells + 2, a + 1);
    }
  }
  return out;
}

// A unit sphere of `stacks` bands and 2 * stacks slices: 2 * slices * (stacks - 1) triangles,
// the pole bands as triangles, the rest as quads, all wound outward.
std::string sphere_obj(int stacks) {
  const int slices = 2 * stacks;
  std::string out = fmt::format("# dtraced generate: unit sphere, {} triangles\n", 2 * slices * (stacks - 1));
  vertex(out, 0, 1, 0);
  for (int j = 1; j < stacks; ++j) {
    const auto [st, ct] = sin_cos(std::numbers::pi * j / stacks);
    for (int i = 0; i < slices; ++i) {
      const auto [sp, cp] = sin_cos(2 * std::numbers::pi * i / slices);
      vertex(out, st * cp, ct, -st * sp);
    }
  }
  vertex(out, 0, -1, 0);
  const int bottom = 2 + (stacks - 1) * slices;
  const auto ring = [slices](int j, int i) { return 2 + (j - 1) * slices + (i % slices); };
  for (int i = 0; i < slices; ++i) out += fmt::format("f 1 {} {}\n", ring(1, i), ring(1, i + 1));
  for (int j = 1; j + 1 < stacks; ++j) {
    for (int i = 0; i < slices; ++i) {
      out += fmt::format("f {} {} {} {}\n", ring(j, i), ring(j + 1, i), ring(j + 1, i + 1), ring(j, i + 1));
    }
  }
  for (int i = 0; i < slices; ++i) {
    out += fmt::format("f {} {} {}\n", ring(stacks - 1, i), bottom, ring(stacks - 1, i + 1));
  }
  return out;
}

// A torus around the y axis: ring radius 1, tube radius 0.35, 2 * sides x sides quads, wound
// outward.
std::string torus_obj(int sides) {
  const int rings = 2 * sides;
  std::string out = fmt::format("# dtraced generate: torus, {} triangles\n", 2 * rings * sides);
  for (int i = 0; i < rings; ++i) {
    const auto [su, cu] = sin_cos(2 * std::numbers::pi * i / rings);
    for (int j = 0; j < sides; ++j) {
      const auto [sv, cv] = sin_cos(2 * std::numbers::pi * j / sides);
      const double r = 1.0 + 0.35 * cv;
      vertex(out, r * cu, 0.35 * sv, -r * su);
    }
  }
  const auto at = [rings, sides](int i, int j) { return 1 + (i % rings) * sides + (j % sides); };
  for (int i = 0; i < rings; ++i) {
    for (int j = 0; j < sides; ++j) {
      out += fmt::format("f {} {} {} {}\n", at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
    }
  }
  return out;
}

// Shortest JSON for a value rounded to 4 decimals: the scene file stays readable.
double tidy(double x) { return std::round(x * 1e4) / 1e4 + 0.0; }

json::array vec(double x, double y, double z) { return json::array{tidy(x), tidy(y), tidy(z)}; }

json::object material(const Material& m) {
  json::object o;
  o["color"] = vec(m.color.x, m.color.y, m.color.z);
  o["diffuse"] = tidy(m.diffuse);
  o["specular"] = tidy(m.specular);
  o["shininess"] = tidy(m.shininess);
  o["reflectivity"] = tidy(m.reflectivity);
  o["transparency"] = tidy(m.transparency);
  o["ior"] = tidy(m.ior);
  return o;
}

// The material of mesh instance `k`: the mirror, the glass, or a seeded glossy colour.
Material instance_material(const SphereDice& dice, int k, bool mirror, bool glass) {
  Material m;
  if (mirror) {
    m.color = {0.92, 0.92, 0.95};
    m.diffuse = 0.05;
    m.specular = 0.8;
    m.shininess = 512;
    m.reflectivity = 0.9;
  } else if (glass) {
    m.color = {1, 1, 1};
    m.diffuse = 0;
    m.specular = 0.9;
    m.shininess = 512;
    m.transparency = 0.95;
  } else {
    m.color = {0.15 + 0.75 * dice.uniform(k, kRed), 0.15 + 0.75 * dice.uniform(k, kGreen),
               0.15 + 0.75 * dice.uniform(k, kBlue)};
    m.diffuse = 0.85;
    m.specular = 0.15 + 0.5 * dice.uniform(k, kSpecular);
    m.shininess = 16 + 200 * dice.uniform(k, kShininess);
    m.reflectivity = 0.1;
  }
  return m;
}

}  // namespace

GeneratedMeshScene generate_mesh_scene(std::uint32_t triangles, std::uint64_t seed, const std::string& model_prefix) {
  assert(triangles >= 1 && triangles <= kMaxTriangles);
  const SphereDice dice(seed ^ 0x6d657368ULL);  // "mesh": another stream than the sphere field's
  const double n = std::max<double>(triangles, 400);

  // A quarter of the budget for the ground, the rest shared by the instances, half spheres and
  // half tori. More triangles mean more instances as well as finer ones.
  const int instances = std::clamp(int(std::lround(std::sqrt(n) / 16)), 6, 300);
  const double per_instance = 0.75 * n / instances;
  const int stacks = std::max(3, int(std::lround(std::sqrt(per_instance / 4) + 0.5)));
  const int sides = std::max(3, int(std::lround(std::sqrt(per_instance / 4))));
  const int cells = std::max(2, int(std::lround(std::sqrt(n / 8))));

  const int columns = int(std::ceil(std::sqrt(double(instances))));
  const int rows = (instances + columns - 1) / columns;
  constexpr double kSpacing = 2.2;
  const double half = 0.5 * kSpacing * std::max(columns, rows) + 16;  // its edge stays out of view

  GeneratedMeshScene out;
  out.objs = {{model_prefix + "-ground.obj", ground_obj(cells, half)},
              {model_prefix + "-sphere.obj", sphere_obj(stacks)},
              {model_prefix + "-torus.obj", torus_obj(sides)}};
  const std::size_t sphere_tris = std::size_t(4) * stacks * (stacks - 1);
  const std::size_t torus_tris = std::size_t(4) * sides * sides;
  out.triangles = std::size_t(2) * cells * cells;

  std::vector<std::string> objects;
  {
    json::object ground;
    ground["type"] = "mesh";
    ground["file"] = out.objs[0].path;
    Material m;
    m.color = {0.55, 0.52, 0.47};
    m.specular = 0.05;
    ground["material"] = material(m);
    objects.push_back(jsonio::to_text(ground));
  }
  for (int k = 0; k < instances; ++k) {
    const int row = k / columns, column = k % columns;
    const double cx = (column - 0.5 * (columns - 1)) * kSpacing + 0.5 * (dice.uniform(k, kOffsetX) - 0.5);
    const double cz = (row - 0.5 * (rows - 1)) * kSpacing + 0.5 * (dice.uniform(k, kOffsetZ) - 0.5);
    const double ground_y = ground_height(cx, cz);
    // The mirror and the glass sphere sit mid-field, where the others reflect and refract in them.
    const int mirror = instances / 2, glass = mirror - 1;
    const bool sphere = k == mirror || k == glass || dice.uniform(k, kKind) < 0.5;
    const Material m = instance_material(dice, k, k == mirror, k == glass);
    json::object o;
    o["type"] = "mesh";
    if (sphere) {
      const double radius = k == mirror || k == glass ? 0.9 : 0.45 + 0.35 * dice.uniform(k, kRadius);
      o["file"] = out.objs[1].path;
      o["translate"] = vec(cx, ground_y + radius, cz);
      o["scale"] = tidy(radius);
      out.triangles += sphere_tris;
    } else {
      // Tori lie flat or stand on edge, turned about y.
      const double size = 0.55 + 0.25 * dice.uniform(k, kRadius);
      const bool standing = dice.uniform(k, kShininess + 1) < 0.5;
      const double turn = 180 * dice.uniform(k, kShininess + 2);
      o["file"] = out.objs[2].path;
      o["translate"] = vec(cx, ground_y + size * (standing ? 1.35 : 0.35), cz);
      o["rotate"] = vec(standing ? 90 : 0, turn, 0);
      o["scale"] = tidy(size);
      out.triangles += torus_tris;
    }
    o["material"] = material(m);
    objects.push_back(jsonio::to_text(o));
  }

  const double extent = 0.5 * kSpacing * std::max(columns, rows);
  json::object camera;
  camera["position"] = vec(0.3 * extent, 0.9 * extent + 1.2, 1.9 * extent + 2.5);
  camera["look_at"] = vec(0, 0.3, -0.1 * extent);
  camera["up"] = vec(0, 1, 0);
  camera["fov"] = 40;
  json::object render;
  render["width"] = 960;
  render["height"] = 540;
  render["samples"] = 2;
  render["max_depth"] = 8;
  render["background"] = vec(0.55, 0.65, 0.8);
  render["seed"] = seed & kMaxSeed;
  // Intensities for about the same irradiance on the field whatever its size (1/r^2 falloff).
  const double r2 = (extent + 6) * (extent + 6);
  json::object key;
  key["type"] = "point";
  key["loc"] = vec(-0.8 * extent - 3, 1.2 * extent + 5, 0.8 * extent + 3);
  key["color"] = vec(1, 0.95, 0.85);
  key["intensity"] = tidy(2.2 * r2);
  json::object fill;
  fill["type"] = "point";
  fill["loc"] = vec(1.2 * extent + 4, 0.7 * extent + 3, 0.4 * extent + 2);
  fill["color"] = vec(0.75, 0.82, 1);
  fill["intensity"] = tidy(0.9 * r2);

  std::string& s = out.scene_json;
  s = "{\n  \"camera\": " + jsonio::to_text(camera) + ",\n  \"render\": " + jsonio::to_text(render) +
      ",\n  \"scene_objects\": [\n";
  for (std::size_t i = 0; i < objects.size(); ++i) s += "    " + objects[i] + (i + 1 < objects.size() ? ",\n" : "\n");
  s += "  ],\n  \"scene_lights\": [\n    " + jsonio::to_text(key) + ",\n    " + jsonio::to_text(fill) + "\n  ]\n}\n";
  return out;
}

}  // namespace dtraced::scene
