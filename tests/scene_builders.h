// Scene pieces the render tests build scenes from, and the bundled scenes at a test's size.
#pragma once

#include <cstdint>
#include <string>

#include <catch2/catch.hpp>

#include "scene/description.h"
#include "scene/load.h"

namespace dtraced::testing {

inline scene::Object sphere(math::Vec3d c, double r, scene::Material m) {
  scene::Object o;
  o.type = scene::ObjectType::kSphere;
  o.sphere = {c, r};
  o.material = m;
  return o;
}

inline scene::Object plane(math::Vec3d p, math::Vec3d n, scene::Material m) {
  scene::Object o;
  o.type = scene::ObjectType::kPlane;
  o.plane = {p, n};
  o.material = m;
  return o;
}

inline scene::Object box(math::Vec3d lo, math::Vec3d hi, scene::Material m) {
  scene::Object o;
  o.type = scene::ObjectType::kBox;
  o.box = {lo, hi};
  o.material = m;
  return o;
}

// scenes/NAME.json from the source tree, resized to width x height.
inline scene::SceneDesc bundled_scene(const std::string& name, std::uint32_t width, std::uint32_t height) {
  scene::LoadResult r = scene::load_scene_file(std::string(DTRACED_SOURCE_DIR) + "/scenes/" + name + ".json");
  REQUIRE(r.ok());
  scene::SceneDesc d = *r.scene;
  d.render.width = width;
  d.render.height = height;
  return d;
}

}  // namespace dtraced::testing
