// Helpers of the scene tests (test_scene.cpp, test_scene_mesh.cpp): a scene that is valid until
// one part of it is replaced, and checks of what loading it gives.
#pragma once

#include <algorithm>
#include <string>
#include <string_view>

#include <catch2/catch.hpp>

#include "scene/digest.h"
#include "scene/load.h"

namespace scene_testing {

using dtraced::scene::canonical_json;
using dtraced::scene::format_errors;
using dtraced::scene::load_scene_file;
using dtraced::scene::load_scene_string;
using dtraced::scene::LoadOptions;
using dtraced::scene::LoadResult;
using dtraced::scene::ObjectType;
using dtraced::scene::scene_digest;
using dtraced::scene::SceneDesc;

inline constexpr const char* kFile = "bad.json";
inline constexpr std::string_view kCamera = R"({"position": [0, 0, 5], "look_at": [0, 0, 0]})";
inline constexpr std::string_view kSphere = R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1})";
inline constexpr std::string_view kLight = R"({"type": "point", "loc": [5, 5, 5]})";

// A scene that is valid until one part is replaced by a broken one.
struct SceneParts {
  std::string camera{kCamera};
  std::string render = "{}";
  // append, not "[" + std::string(...): GCC 12 warns falsely (-Warray-bounds) on that operator+
  // once inlined into this constructor, as it is where the tests use a precompiled Catch2.
  std::string objects = std::string("[").append(kSphere).append("]");
  std::string lights = std::string("[").append(kLight).append("]");

  std::string json() const {
    return "{\"camera\": " + camera + ", \"render\": " + render + ", \"scene_objects\": " + objects +
           ", \"scene_lights\": " + lights + "}";
  }
};

inline std::string with_camera(std::string camera) {
  SceneParts p;
  p.camera = std::move(camera);
  return p.json();
}
inline std::string with_render(std::string render) {
  SceneParts p;
  p.render = std::move(render);
  return p.json();
}
inline std::string with_object(std::string object) {
  SceneParts p;
  p.objects = "[" + object + "]";
  return p.json();
}
inline std::string with_light(std::string light) {
  SceneParts p;
  p.lights = "[" + light + "]";
  return p.json();
}
inline std::string with_material(std::string material) {
  return with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": )" + material + "}");
}

inline bool has_error(const LoadResult& r, std::string_view path, std::string_view fragment) {
  return std::any_of(r.errors.begin(), r.errors.end(), [&](const auto& e) {
    return e.file == kFile && e.path == path && e.message.find(fragment) != std::string::npos;
  });
}

inline std::string source_path(std::string_view relative) {
  return std::string(DTRACED_SOURCE_DIR) + "/" + std::string(relative);
}

inline SceneDesc load_ok(std::string_view json) {
  LoadResult r = load_scene_string(json, "ok.json");
  INFO(format_errors(r.errors));
  REQUIRE(r.ok());
  return *r.scene;
}

}  // namespace scene_testing
