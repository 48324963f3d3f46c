// Scene pieces the render tests build scenes from (objects, materials, lights), and the bundled
// scenes at a test's size. Header-only values and functions: no state, any test may include it.
#pragma once

#include <cstdint>
#include <string>

#include <catch2/catch.hpp>

#include "scene/description.h"
#include "scene/load.h"

namespace dtraced::testing {

// An object of `type` with material m; the caller sets its shape.
inline scene::Object object_of(scene::ObjectType type, const scene::Material& m) {
  scene::Object o;
  o.type = type;
  o.material = m;
  return o;
}

inline scene::Object sphere(math::Vec3d c, double r, scene::Material m) {
  scene::Object o = object_of(scene::ObjectType::kSphere, m);
  o.sphere = {c, r};
  return o;
}

inline scene::Object plane(math::Vec3d p, math::Vec3d n, scene::Material m) {
  scene::Object o = object_of(scene::ObjectType::kPlane, m);
  o.plane = {p, n};
  return o;
}

inline scene::Object box(math::Vec3d lo, math::Vec3d hi, scene::Material m) {
  scene::Object o = object_of(scene::ObjectType::kBox, m);
  o.box = {lo, hi};
  return o;
}

// Lambertian: `color`, diffuse 1, no specular, no mirror coat, opaque.
inline scene::Material diffuse(math::Vec3d color = {0.8, 0.8, 0.8}) {
  scene::Material m;
  m.color = color;
  m.diffuse = 1.0;
  m.specular = 0.0;
  return m;
}

// Clear dielectric: no local shading, no mirror coat; Fresnel alone splits the light.
inline scene::Material glass(double ior, double transparency = 1.0) {
  scene::Material m;
  m.color = {1, 1, 1};
  m.diffuse = 0.0;
  m.transparency = transparency;
  m.ior = ior;
  return m;
}

// A white mirror with no local shading.
inline scene::Material mirror(double reflectivity) {
  scene::Material m;
  m.color = {1, 1, 1};
  m.diffuse = 0.0;
  m.reflectivity = reflectivity;
  return m;
}

// A white point light of `intensity` W/sr.
inline scene::Light point_light(math::Vec3d position, double intensity) {
  scene::Light l;
  l.position = position;
  l.color = {1, 1, 1};
  l.intensity = intensity;
  return l;
}

// Area lights of radiance `le` (white): a sphere, a disk facing `n`, and a rect facing -y (down)
// with edges a along x and b along z.
inline scene::Light sphere_light(math::Vec3d c, double r, double le) {
  scene::Light l;
  l.type = scene::LightType::kSphere;
  l.position = c;
  l.radius = r;
  l.intensity = le;
  return l;
}
inline scene::Light disk_light(math::Vec3d c, double r, math::Vec3d n, double le) {
  scene::Light l = sphere_light(c, r, le);
  l.type = scene::LightType::kDisk;
  l.normal = n;
  return l;
}
inline scene::Light rect_light_down(math::Vec3d c, double a, double b, double le) {
  scene::Light l;
  l.type = scene::LightType::kRect;
  l.position = c;
  l.edge_u = {a, 0, 0};
  l.edge_v = {0, 0, b};
  l.normal = {0, -1, 0};
  l.intensity = le;
  return l;
}

// scenes/RELATIVE from the source tree (RELATIVE names the file: "room.json", "hard/x.json").
inline scene::SceneDesc load_bundled(const std::string& relative) {
  // append, not a chain of operator+: GCC 12 warns falsely (-Warray-bounds) on that chain at -O1.
  std::string path(DTRACED_SOURCE_DIR);
  path.append("/scenes/").append(relative);
  scene::LoadResult r = scene::load_scene_file(path);
  REQUIRE(r.ok());
  return *r.scene;
}

// scenes/NAME.json from the source tree, resized to width x height.
inline scene::SceneDesc bundled_scene(const std::string& name, std::uint32_t width, std::uint32_t height) {
  scene::SceneDesc d = load_bundled(name + ".json");
  d.render.width = width;
  d.render.height = height;
  return d;
}

}  // namespace dtraced::testing
