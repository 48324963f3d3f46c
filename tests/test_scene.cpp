// Tests for dtraced::scene: strict loading with located errors, the canonical form and digest,
// the generated stress scene, and the shipped scenes/*.json.
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <bit>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "jsonio/parse.h"
#include "scene/digest.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "scene/load_objects.h"
#include "scene/obj_mesh.h"
#include "scene_testing.h"

namespace {

using namespace scene_testing;
using dtraced::math::Vec3d;
using dtraced::scene::generate_sphere_field;

// A file removed when the test ends, however it ends.
class TempFile {
 public:
  explicit TempFile(std::string_view contents)
      : path_((std::filesystem::temp_directory_path() / ("dtraced_test_scene_" + std::to_string(::getpid()) + ".json"))
                  .string()) {
    std::ofstream(path_, std::ios::binary) << contents;
  }
  ~TempFile() { std::filesystem::remove(path_); }
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

struct BadCase {
  const char* name;
  std::string json;
  std::string path;
  std::string fragment;
};

std::string deep_nesting_scene(int arrays) {
  SceneParts p;
  p.render = "{\"x\": " + std::string(arrays, '[') + std::string(arrays, ']') + "}";
  return p.json();
}

}  // namespace

namespace {

// Each scene is refused with exactly one error, at `path`, whose message holds `fragment`.
void check_refused(const std::vector<BadCase>& cases) {
  for (const BadCase& c : cases) {
    const LoadResult r = load_scene_string(c.json, kFile);
    INFO("case: " << c.name << "\nerrors:\n" << format_errors(r.errors));
    CHECK_FALSE(r.ok());
    CHECK_FALSE(r.scene.has_value());
    CHECK(r.errors.size() == 1);
    CHECK(has_error(r, c.path, c.fragment));
  }
}

}  // namespace

TEST_CASE("malformed scene text, unknown keys and wrong kinds of value name the file and JSON path",
          "[scene][errors]") {
  // Root object, "render" object, then 62 arrays fill the 64 levels; the 63rd array is one too
  // many and sits at index 0 of the 62nd.
  std::string deep_path = "/render/x";
  for (int i = 0; i < 62; ++i) deep_path += "/0";

  check_refused({
      {"syntax error, located by line and column",
       "{\n  \"camera\": {\"position\": [0,0,5],, \"look_at\": [0,0,0]},\n \"scene_objects\": [], \"scene_lights\": "
       "[]}",
       "/camera", "invalid JSON at line 2, column 34"},
      {"truncated document", "{\"camera\": {\"position\": [0, 0", "/camera/position/2", "unexpected end of input"},
      {"empty input", "", "", "unexpected end of input"},
      {"data after the document", SceneParts().json() + " {}", "", "unexpected data after the JSON document"},
      {"nesting deeper than 64", deep_nesting_scene(63), deep_path, "deeper than the limit of 64 levels"},
      {"1e400 overflows a double", with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1e400})"),
       "/scene_objects/0/radius", "overflows a double"},
      {"1e39 overflows a float", with_object(R"({"type": "sphere", "loc": [0, 1e39, 0], "radius": 1})"),
       "/scene_objects/0/loc/1", "outside the float range"},
      {"-1e39 overflows a float", with_camera(R"({"position": [-1e39, 0, 5]})"), "/camera/position/0",
       "outside the float range"},
      {"string where a number goes", with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": "1"})"),
       "/scene_objects/0/radius", "expected a number, got a string"},
      {"null where a number goes", with_material(R"({"color": [null, 0, 0]})"), "/scene_objects/0/material/color/0",
       "expected a number, got null"},
      {"object where an array goes", with_camera(R"({"up": {"x": 0}})"), "/camera/up",
       "expected an array of 3 numbers, got an object"},
      {"unknown object key, with a suggestion",
       with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "raduis": 2})"), "/scene_objects/0/raduis",
       "did you mean \"radius\"?"},
      {"unknown material key", with_material(R"({"colour": [1, 0, 0]})"), "/scene_objects/0/material/colour",
       "did you mean \"color\"?"},
      {"unknown top-level key lists the known ones", SceneParts().json().insert(1, "\"frobnicate\": 1, "),
       "/frobnicate", "known keys: camera, render, scene_objects, scene_lights"},
      {"unknown render key, with an alias suggestion", with_render(R"({"spp": 4})"), "/render/spp",
       "unknown key \"spp\" (did you mean \"samples\"?)"},
      {"another renderer's name for loc",
       with_object(R"({"type": "sphere", "loc": [0, 0, 0], "center": [0, 0, 0], "radius": 1})"),
       "/scene_objects/0/center", "did you mean \"loc\"?"},
      {"unknown light key", with_light(R"({"type": "point", "loc": [0, 5, 0], "power": 3})"), "/scene_lights/0/power",
       "unknown key"},
      {"key needing JSON Pointer escapes", SceneParts().json().insert(1, "\"a/b~c\": 1, "), "/a~1b~0c", "unknown key"},
      {"duplicate key", with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "radius": 2})"),
       "/scene_objects/0/radius", "duplicate key \"radius\""},
      {"missing radius", with_object(R"({"type": "sphere", "loc": [0, 0, 0]})"), "/scene_objects/0/radius",
       "required key is missing"},
      {"missing type", with_object(R"({"loc": [0, 0, 0], "radius": 1})"), "/scene_objects/0/type",
       "required key is missing"},
      {"missing light position", with_light(R"({"type": "point", "intensity": 3})"), "/scene_lights/0/loc",
       "required key is missing"},
      {"missing camera", R"({"scene_objects": [], "scene_lights": []})", "/camera", "required key is missing"},
      {"top level is not an object", "[1, 2]", "", "expected a JSON object at the top level, got an array"},
      {"scene_objects is not an array", SceneParts{.objects = "{}"}.json(), "/scene_objects",
       "expected an array, got an object"},
      {"object is not an object", SceneParts{.objects = "[1]"}.json(), "/scene_objects/0",
       "expected an object, got a number"},
      {"material is not an object", with_material("true"), "/scene_objects/0/material",
       "expected an object, got a boolean"},
  });
}

TEST_CASE("scene values out of range name the file and the exact JSON path", "[scene][errors]") {
  check_refused({
      {"radius -1", with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": -1})"), "/scene_objects/0/radius",
       "must be > 0 (got -1)"},
      {"radius 0", with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 0})"), "/scene_objects/0/radius",
       "must be > 0 (got 0)"},
      {"ior 0", with_material(R"({"ior": 0})"), "/scene_objects/0/material/ior", "must be > 0 (got 0)"},
      {"fov 180", with_camera(R"({"position": [0, 0, 5], "fov": 180})"), "/camera/fov",
       "open interval (0, 180) (got 180)"},
      {"fov 0", with_camera(R"({"position": [0, 0, 5], "fov": 0})"), "/camera/fov", "open interval (0, 180) (got 0)"},
      {"zero plane normal", with_object(R"({"type": "plane", "loc": [0, 0, 0], "normal": [0, 0, 0]})"),
       "/scene_objects/0/normal", "must not be zero length"},
      {"up parallel to the view direction", with_camera(R"({"position": [0, 5, 0], "look_at": [0, 0, 0]})"),
       "/camera/up", "must not be parallel to the view direction"},
      {"up nearly parallel", with_camera(R"({"position": [0, 0, 5], "up": [0, 1e-9, -1]})"), "/camera/up",
       "must not be parallel"},
      {"zero up", with_camera(R"({"up": [0, 0, 0]})"), "/camera/up", "must not be the zero vector"},
      {"position == look_at", with_camera(R"({"position": [1, 2, 3], "look_at": [1, 2, 3]})"), "/camera/look_at",
       "must differ from the camera position"},
      {"position == look_at once in float",
       with_camera(R"({"position": [1, 2, 3], "look_at": [1.0000000000000002, 2, 3]})"), "/camera/look_at",
       "must differ"},
      {"array of the wrong length", with_object(R"({"type": "sphere", "loc": [0, 0], "radius": 1})"),
       "/scene_objects/0/loc", "expected an array of 3 numbers, got 2 elements"},
      {"colour of 4 channels", with_material(R"({"color": [1, 1, 1, 1]})"), "/scene_objects/0/material/color",
       "got 4 elements"},
      {"reflectivity + transparency > 1", with_material(R"({"reflectivity": 0.7, "transparency": 0.6})"),
       "/scene_objects/0/material", "reflectivity + transparency must be <= 1 (got 0.7 + 0.6)"},
      {"negative colour", with_material(R"({"color": [1, 1, -0.5]})"), "/scene_objects/0/material/color/2",
       "must be >= 0 (got -0.5)"},
      {"negative background", with_render(R"({"background": [-1, 0, 0]})"), "/render/background/0", "must be >= 0"},
      {"diffuse above 1", with_material(R"({"diffuse": 1.5})"), "/scene_objects/0/material/diffuse",
       "must be in [0, 1] (got 1.5)"},
      {"specular below 0", with_material(R"({"specular": -0.1})"), "/scene_objects/0/material/specular",
       "must be in [0, 1]"},
      {"transparency above 1", with_material(R"({"transparency": 2})"), "/scene_objects/0/material/transparency",
       "must be in [0, 1]"},
      {"shininess above 1e4", with_material(R"({"shininess": 2e4})"), "/scene_objects/0/material/shininess",
       "must be in [0, 10000] (got 20000)"},
      {"shininess below 0", with_material(R"({"shininess": -1})"), "/scene_objects/0/material/shininess",
       "must be in [0, 10000]"},
      {"negative intensity", with_light(R"({"type": "point", "loc": [0, 5, 0], "intensity": -1})"),
       "/scene_lights/0/intensity", "must be >= 0 (got -1)"},
      {"width 0", with_render(R"({"width": 0})"), "/render/width", "must be an integer in [1, 16384] (got 0)"},
      {"width 10.5", with_render(R"({"width": 10.5})"), "/render/width", "must be an integer (got 10.5)"},
      {"width too large", with_render(R"({"width": 16385})"), "/render/width", "[1, 16384]"},
      {"negative height", with_render(R"({"height": -3})"), "/render/height", "(got -3)"},
      {"height as a string", with_render(R"({"height": "480"})"), "/render/height",
       "expected an integer, got a string"},
      {"samples 0", with_render(R"({"samples": 0})"), "/render/samples", "[1, 65536] (got 0)"},
      {"samples too many", with_render(R"({"samples": 70000})"), "/render/samples", "[1, 65536]"},
      {"max_depth too deep", with_render(R"({"max_depth": 65})"), "/render/max_depth", "[0, 64] (got 65)"},
      {"seed 2^53", with_render(R"({"seed": 9007199254740992})"), "/render/seed", "[0, 9007199254740991]"},
      {"seed negative", with_render(R"({"seed": -1})"), "/render/seed", "(got -1)"},
      {"seed fractional", with_render(R"({"seed": 1.5})"), "/render/seed", "must be an integer"},
      {"seed beyond uint64", with_render(R"({"seed": 1e30})"), "/render/seed", "[0, 9007199254740991]"},
      {"unknown object type", with_object(R"({"type": "cone", "loc": [0, 0, 0], "radius": 1})"),
       "/scene_objects/0/type", "unknown object type \"cone\"; known types: sphere, box, plane"},
      {"type is not a string", with_object(R"({"type": 3, "loc": [0, 0, 0], "radius": 1})"), "/scene_objects/0/type",
       "expected a string"},
      {"unknown light type", with_light(R"({"type": "spot", "loc": [0, 5, 0]})"), "/scene_lights/0/type",
       "unknown light type \"spot\"; known types: point"},
      {"box size 0", with_object(R"({"type": "box", "loc": [0, 0, 0], "size": [1, 0, 1]})"), "/scene_objects/0/size/1",
       "must be > 0 (got 0)"},
      {"box in both forms", with_object(R"({"type": "box", "loc": [0, 0, 0], "size": [1, 1, 1], "max": [1, 1, 1]})"),
       "/scene_objects/0", "not both"},
      {"box with min only", with_object(R"({"type": "box", "min": [0, 0, 0]})"), "/scene_objects/0/max",
       "required key is missing"},
      {"box min not below max", with_object(R"({"type": "box", "min": [0, 0, 2], "max": [1, 1, 2]})"),
       "/scene_objects/0/max/2", "must be greater than min"},
      {"box too thin to represent", with_object(R"({"type": "box", "loc": [1e10, 0, 0], "size": [1e-10, 1, 1]})"),
       "/scene_objects/0/size/0", "too small to be represented"},
      {"sphere key on a plane", with_object(R"({"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0], "radius": 1})"),
       "/scene_objects/0/radius", "unknown key"},
  });
}

TEST_CASE("an error prints as FILE: PATH: MESSAGE", "[scene][errors]") {
  const LoadResult r = load_scene_string(with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": -1})"), kFile);
  REQUIRE(r.errors.size() == 1);
  CHECK(r.errors[0].to_string() == "bad.json: /scene_objects/0/radius: must be > 0 (got -1)");
  CHECK(format_errors(r.errors) == "bad.json: /scene_objects/0/radius: must be > 0 (got -1)\n");
}

TEST_CASE("every error in a scene is reported, not just the first", "[scene][errors]") {
  SceneParts p;
  p.camera = R"({"position": [0, 0, 5], "fov": 180})";
  p.objects = R"([{"type": "sphere", "loc": [0, 0, 0], "radius": -1},
                  {"type": "sphere", "loc": [0, 2, 0], "radius": 1, "material": {"ior": 0}}])";
  const LoadResult r = load_scene_string(p.json(), kFile);
  INFO(format_errors(r.errors));
  REQUIRE(r.errors.size() == 3);
  CHECK(has_error(r, "/camera/fov", "(0, 180)"));
  CHECK(has_error(r, "/scene_objects/0/radius", "must be > 0"));
  CHECK(has_error(r, "/scene_objects/1/material/ior", "must be > 0"));
}

TEST_CASE("the error list is capped, with a count of the rest", "[scene][errors]") {
  SceneParts p;
  p.objects = "[";
  for (int i = 0; i < 20; ++i)
    p.objects += std::string(i ? "," : "") + R"({"type": "sphere", "loc": [0, 0, 0], "radius": -1})";
  p.objects += "]";
  LoadOptions options;
  options.max_errors = 5;
  const LoadResult r = load_scene_string(p.json(), kFile, options);
  REQUIRE(r.errors.size() == 6);
  CHECK(r.errors[4].path == "/scene_objects/4/radius");
  CHECK(r.errors[5].message == "15 more problems not shown");
}

TEST_CASE("too many lights is one error on the list", "[scene][errors]") {
  SceneParts p;
  p.lights = "[";
  for (std::size_t i = 0; i <= dtraced::scene::kMaxLights; ++i)
    p.lights += std::string(i ? "," : "") + std::string(kLight);
  p.lights += "]";
  const LoadResult r = load_scene_string(p.json(), kFile);
  REQUIRE(r.errors.size() == 1);
  CHECK(has_error(r, "/scene_lights", "too many lights: 10001 (limit 10000)"));
}

TEST_CASE("defaults fill what a scene leaves out", "[scene][load]") {
  const SceneDesc d = load_ok(SceneParts().json());
  const SceneDesc defaults;
  CHECK(d.render == defaults.render);
  CHECK(d.camera.up == defaults.camera.up);
  CHECK(d.camera.fov_deg == defaults.camera.fov_deg);
  REQUIRE(d.objects.size() == 1);
  CHECK(d.objects[0].material == dtraced::scene::Material{});
  REQUIRE(d.lights.size() == 1);
  CHECK(d.lights[0].intensity == 1.0);
  CHECK(d.lights[0].color == dtraced::scene::Color{1, 1, 1});
}

TEST_CASE("boxes, planes and integral numbers are read as documented", "[scene][load]") {
  SceneParts p;
  p.objects = R"([{"type": "box", "loc": [1, 2, 3], "size": [2, 4, 6]},
                  {"type": "box", "min": [-1, -1, -1], "max": [1, 1, 1]},
                  {"type": "plane", "loc": [0, -1, 0], "normal": [0, 3, 4]}])";
  p.render = R"({"width": 320.0, "height": 2e2, "seed": 9007199254740991})";
  const SceneDesc d = load_ok(p.json());
  REQUIRE(d.objects.size() == 3);
  CHECK(d.objects[0].type == ObjectType::kBox);
  CHECK(d.objects[0].box.min == dtraced::math::Vec3d{0, 0, 0});
  CHECK(d.objects[0].box.max == dtraced::math::Vec3d{2, 4, 6});
  CHECK(d.objects[1].box.min == dtraced::math::Vec3d{-1, -1, -1});
  CHECK(d.objects[2].type == ObjectType::kPlane);
  CHECK(d.objects[2].plane.normal.y == Approx(0.6));
  CHECK(d.objects[2].plane.normal.z == Approx(0.8));
  CHECK(d.render.width == 320);
  CHECK(d.render.height == 200);
  CHECK(d.render.seed == 9007199254740991ull);
}

TEST_CASE("doubles are read correctly rounded", "[scene][load]") {
  // Boost.JSON 1.81's own conversion reads this one ulp off; the loader must not.
  const SceneDesc d = load_ok(with_object(R"({"type": "sphere", "loc": [60.647264433458076, 0, 0], "radius": 1})"));
  CHECK(d.objects[0].sphere.center.x == 60.647264433458076);
}

TEST_CASE("an empty scene loads, with warnings", "[scene][load]") {
  const LoadResult r = load_scene_string(R"({"camera": {}, "scene_objects": [], "scene_lights": []})", "empty.json");
  REQUIRE(r.ok());
  CHECK(r.warnings.size() == 2);
}

TEST_CASE("every scene in scenes/ loads without errors or warnings", "[scene][files]") {
  std::vector<std::string> files;
  for (const auto& entry : std::filesystem::directory_iterator(source_path("scenes"))) {
    if (entry.path().extension() == ".json") files.push_back(entry.path().string());
  }
  std::sort(files.begin(), files.end());
  REQUIRE(files.size() >= 3);
  for (const std::string& file : files) {
    const LoadResult r = load_scene_file(file);
    INFO(file << "\n" << format_errors(r.errors) << format_errors(r.warnings));
    CHECK(r.ok());
    CHECK(r.warnings.empty());
    if (!r.ok()) continue;

    // The canonical form is a scene file that reads back to the same scene, and is a fixed point.
    const std::string canonical = canonical_json(*r.scene);
    const LoadResult again = load_scene_string(canonical, file + " (canonical)");
    REQUIRE(again.ok());
    CHECK(*again.scene == *r.scene);
    CHECK(canonical_json(*again.scene) == canonical);
  }
}

TEST_CASE("the canonical form is pinned", "[scene][digest]") {
  // A change here changes every digest in every cache: make it on purpose or not at all.
  const SceneDesc d = load_ok(R"({"camera": {"position": [0, 0.5, 5]}, "render": {"seed": 3},
      "scene_objects": [{"type": "box", "loc": [0, 0, 0], "size": [1, 1, 1], "material": {"ior": 1.25}}],
      "scene_lights": [{"type": "point", "loc": [1, 2, 3], "intensity": 10}]})");
  CHECK(canonical_json(d) ==
        R"({"camera":{"position":[0,5E-1,5],"look_at":[0,0,0],"up":[0,1,0],"fov":45},)"
        R"("render":{"width":640,"height":480,"samples":1,"max_depth":8,"background":[0,0,0],"seed":3,"frame":0},)"
        R"("scene_objects":[{"type":"box","min":[-5E-1,-5E-1,-5E-1],"max":[5E-1,5E-1,5E-1],)"
        R"("material":{"color":[8E-1,8E-1,8E-1],"diffuse":1,"specular":0,"shininess":32,"reflectivity":0,)"
        R"("transparency":0,"ior":1.25E0}}],)"
        R"("scene_lights":[{"type":"point","loc":[1,2,3],"color":[1,1,1],"intensity":10}]})");
  CHECK(scene_digest(d).size() == 64);
}

TEST_CASE("the digest ignores layout and explicit defaults, and sees every semantic change", "[scene][digest]") {
  const std::string base = R"({"camera": {"position": [0, 1, 6], "look_at": [0, 1, 0]},
    "scene_objects": [
      {"type": "sphere", "loc": [0, 1, 0], "radius": 1, "material": {"color": [1, 0, 0]}},
      {"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0]},
      {"type": "box", "loc": [0, 0.5, 0], "size": [2, 1, 2]}],
    "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 100}]})";
  // Same scene: keys reordered, other whitespace, defaults spelled out, integers as doubles,
  // a non-unit normal, the box by its corners.
  const std::string same = R"(
  {
    "scene_lights" : [ { "intensity" : 100.0, "loc" : [ 5, 5, 5 ], "color": [1, 1, 1], "type" : "point" } ],
    "render": {"width": 640, "height": 480, "samples": 1, "max_depth": 8, "background": [0, 0, 0], "seed": 0, "frame": 0},
    "scene_objects" : [
      { "material" : { "ior": 1.5, "color" : [ 1, 0, 0 ], "diffuse": 1, "specular": 0, "shininess": 32,
                       "reflectivity": 0, "transparency": 0 },
        "radius" : 1e0, "loc" : [ 0, 1, 0 ], "type" : "sphere" },
      { "type" : "plane", "normal" : [ 0, 2.5, 0 ], "loc" : [ -0.0, 0, 0 ], "material": {} },
      { "type" : "box", "min" : [ -1, 0, -1 ], "max" : [ 1, 1, 1 ] }
    ],
    "camera" : { "up" : [ 0, 1, 0 ], "fov" : 45, "look_at" : [ 0, 1, 0 ], "position" : [ 0, 1, 6 ] }
  }
  )";
  const std::string digest = scene_digest(load_ok(base));
  CHECK(scene_digest(load_ok(same)) == digest);
  CHECK(load_ok(same) == load_ok(base));

  const auto changed = [&](std::string_view from, std::string_view to) {
    std::string s = base;
    const auto at = s.find(from);
    REQUIRE(at != std::string::npos);
    s.replace(at, from.size(), to);
    return scene_digest(load_ok(s));
  };
  CHECK(changed(R"("radius": 1)", R"("radius": 1.0000000000000002)") != digest);
  CHECK(changed(R"("color": [1, 0, 0])", R"("color": [1, 0, 0.001])") != digest);
  CHECK(changed(R"("intensity": 100)", R"("intensity": 99)") != digest);
  CHECK(changed(R"("size": [2, 1, 2])", R"("size": [2, 1, 2.5])") != digest);
  CHECK(changed(R"("look_at": [0, 1, 0])", R"("look_at": [0, 1, 0], "fov": 46)") != digest);
  CHECK(changed(R"("scene_objects")", R"("render": {"samples": 2}, "scene_objects")") != digest);
  CHECK(changed(R"("scene_objects")", R"("render": {"frame": 1}, "scene_objects")") != digest);
}

TEST_CASE("area lights and adaptive settings load as documented and round-trip through the canonical form",
          "[scene][lights]") {
  const SceneDesc d = load_ok(R"({"camera": {}, "render": {"error_target": 0.02, "min_samples": 8},
      "scene_objects": [], "scene_lights": [
        {"type": "sphere", "loc": [1, 2, 3], "radius": 0.5, "intensity": 4, "samples": 3},
        {"type": "disk", "loc": [0, 4, 0], "normal": [0, -2, 0], "radius": 1, "cast_shadows": false},
        {"type": "rect", "loc": [0, 5, 0], "u": [2, 0, 0], "v": [0, 0, 1]},
        {"type": "rect", "loc": [0, 5, 0], "u": [2, 0, 0], "v": [0, 0, 1], "normal": [0, -3, 0]},
        {"type": "point", "loc": [5, 5, 5]}]})");
  REQUIRE(d.lights.size() == 5);
  CHECK(d.render.error_target == 0.02);
  CHECK(d.render.min_samples == 8);
  const dtraced::scene::Light& sphere = d.lights[0];
  CHECK(sphere.type == dtraced::scene::LightType::kSphere);
  CHECK(sphere.radius == 0.5);
  CHECK(sphere.samples == 3);
  CHECK(sphere.cast_shadows);
  CHECK(d.lights[1].normal == Vec3d{0, -1, 0});
  CHECK_FALSE(d.lights[1].cast_shadows);
  // cross(u, v) = (0, -2, 0): the default side is -y; "normal" may pick the same side explicitly.
  CHECK(d.lights[2].normal == Vec3d{0, -1, 0});
  CHECK(d.lights[3].normal == Vec3d{0, -1, 0});
  CHECK(d.lights[2].edge_u == Vec3d{2, 0, 0});
  CHECK(d.lights[4].type == dtraced::scene::LightType::kPoint);

  // The canonical form reloads to the same description, so its digest is stable.
  const SceneDesc again = load_ok(canonical_json(d));
  CHECK(again == d);
  CHECK(scene_digest(again) == scene_digest(d));
  // The other side of a rect, and a different error target, are different scenes.
  const SceneDesc flipped = load_ok(R"({"camera": {}, "scene_objects": [], "scene_lights": [
        {"type": "rect", "loc": [0, 5, 0], "u": [2, 0, 0], "v": [0, 0, 1], "normal": [0, 1, 0]}]})");
  CHECK(flipped.lights[0].normal == Vec3d{0, 1, 0});
  CHECK(load_ok(canonical_json(flipped)) == flipped);
  SceneDesc other_target = d;
  other_target.render.error_target = 0.03;
  CHECK(scene_digest(other_target) != scene_digest(d));
}

TEST_CASE("broken area lights and adaptive settings name the field", "[scene][lights][errors]") {
  const std::vector<BadCase> cases = {
      {"unknown light type", with_light(R"({"type": "spot", "loc": [0, 0, 0]})"), "/scene_lights/0/type",
       "known types: point, sphere, disk, rect"},
      {"sphere light without a radius", with_light(R"({"type": "sphere", "loc": [0, 0, 0]})"), "/scene_lights/0/radius",
       "required key is missing"},
      {"sphere light of radius 0", with_light(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 0})"),
       "/scene_lights/0/radius", "must be > 0"},
      {"disk light without a normal", with_light(R"({"type": "disk", "loc": [0, 0, 0], "radius": 1})"),
       "/scene_lights/0/normal", "required key is missing"},
      {"disk light with a zero normal",
       with_light(R"({"type": "disk", "loc": [0, 0, 0], "radius": 1, "normal": [0, 0, 0]})"), "/scene_lights/0/normal",
       "zero length"},
      {"rect light with parallel edges",
       with_light(R"({"type": "rect", "loc": [0, 0, 0], "u": [1, 0, 0], "v": [-2, 0, 0]})"), "/scene_lights/0/v",
       "must not be parallel"},
      {"rect light with a zero edge",
       with_light(R"({"type": "rect", "loc": [0, 0, 0], "u": [0, 0, 0], "v": [1, 0, 0]})"), "/scene_lights/0/u",
       "zero vector"},
      {"rect light normal in its plane",
       with_light(R"({"type": "rect", "loc": [0, 0, 0], "u": [1, 0, 0], "v": [0, 0, 1], "normal": [1, 0, 0]})"),
       "/scene_lights/0/normal", "perpendicular to both edges"},
      {"too many light samples", with_light(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "samples": 257})"),
       "/scene_lights/0/samples", "[1, 256]"},
      {"cast_shadows not a boolean",
       with_light(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "cast_shadows": 1})"),
       "/scene_lights/0/cast_shadows", "expected true or false"},
      {"a radius on a point light", with_light(R"({"type": "point", "loc": [0, 0, 0], "radius": 1})"),
       "/scene_lights/0/radius", "unknown key"},
      {"negative error target", with_render(R"({"error_target": -0.1})"), "/render/error_target", "must be in [0, 1]"},
      {"min_samples of 0", with_render(R"({"min_samples": 0})"), "/render/min_samples", "[1, 65536]"},
  };
  for (const BadCase& c : cases) {
    const LoadResult r = load_scene_string(c.json, kFile);
    INFO("case: " << c.name << "\nerrors:\n" << format_errors(r.errors));
    CHECK_FALSE(r.ok());
    CHECK(r.errors.size() == 1);
    CHECK(has_error(r, c.path, c.fragment));
  }
}

TEST_CASE("the sphere field is deterministic and loadable", "[scene][generate]") {
  const SceneDesc a = generate_sphere_field(1000, 7);
  const SceneDesc b = generate_sphere_field(1000, 7);
  CHECK(a == b);
  CHECK(scene_digest(a) == scene_digest(b));
  CHECK(scene_digest(generate_sphere_field(1000, 8)) != scene_digest(a));

  std::vector<dtraced::scene::Sphere> spheres;
  std::size_t planes = 0;
  std::size_t mirrors = 0;
  std::size_t glass = 0;
  for (const auto& o : a.objects) {
    if (o.type == ObjectType::kPlane) ++planes;
    if (o.type != ObjectType::kSphere) continue;
    spheres.push_back(o.sphere);
    if (o.material.reflectivity > 0) ++mirrors;
    if (o.material.transparency > 0) ++glass;
    CHECK(o.sphere.center.y == o.sphere.radius);  // resting on the ground
  }
  CHECK(spheres.size() == 1000);
  CHECK(planes >= 1);
  CHECK(mirrors > 50);
  CHECK(glass > 10);
  CHECK(mirrors + glass < 400);
  CHECK(a.lights.size() >= 2);
  CHECK(a.lights.size() <= 3);
  CHECK(a.render.width == 1280);
  CHECK(a.render.height == 720);
  CHECK(a.render.samples == 1);
  CHECK(a.render.seed == 7);

  std::size_t overlaps = 0;
  for (std::size_t i = 0; i < spheres.size(); ++i) {
    for (std::size_t j = i + 1; j < spheres.size(); ++j) {
      const double r = spheres[i].radius + spheres[j].radius;
      if (dtraced::math::length_squared(spheres[i].center - spheres[j].center) < r * r) ++overlaps;
    }
  }
  CHECK(overlaps == 0);

  // Arbitrary doubles everywhere: the canonical form must still read back bit for bit.
  const LoadResult r = load_scene_string(canonical_json(a), "generated.json");
  INFO(format_errors(r.errors));
  REQUIRE(r.ok());
  CHECK(*r.scene == a);
  CHECK(r.warnings.empty());
}

TEST_CASE("an empty sphere field is still a valid scene", "[scene][generate]") {
  const SceneDesc d = generate_sphere_field(0, 1);
  const LoadResult r = load_scene_string(canonical_json(d), "generated.json");
  REQUIRE(r.ok());
  CHECK(*r.scene == d);
}

TEST_CASE("file-level errors name the file", "[scene][files]") {
  SECTION("missing file") {
    const std::string missing = "/nonexistent/dtraced/scene.json";
    const LoadResult r = load_scene_file(missing);
    REQUIRE(r.errors.size() == 1);
    CHECK_FALSE(r.scene.has_value());
    CHECK(r.errors[0].file == missing);
    CHECK(r.errors[0].path.empty());
    CHECK(r.errors[0].message.find("cannot open") != std::string::npos);
    CHECK(r.errors[0].to_string().rfind(missing + ": ", 0) == 0);
  }
  SECTION("a directory or a pipe, not a scene file") {
    const std::string dir = std::filesystem::temp_directory_path().string();
    const LoadResult r = load_scene_file(dir);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].file == dir);
    CHECK(r.errors[0].message == "is a directory, not a scene file");
    const std::string fifo = fmt::format("{}/dtraced-scene-fifo-{}", dir, ::getpid());
    REQUIRE(::mkfifo(fifo.c_str(), 0600) == 0);
    const LoadResult p = load_scene_file(fifo);  // would block for ever if it were opened
    std::filesystem::remove(fifo);
    REQUIRE(p.errors.size() == 1);
    CHECK(p.errors[0].message.find("not a regular file") != std::string::npos);
  }
  SECTION("file over the size limit") {
    const TempFile file(SceneParts().json());
    LoadOptions options;
    options.max_bytes = 100;
    const LoadResult r = load_scene_file(file.path(), options);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].file == file.path());
    CHECK(r.errors[0].message.find("larger than the limit of 100 bytes") != std::string::npos);
    CHECK(load_scene_file(file.path()).ok());
  }
  SECTION("string over the size limit") {
    LoadOptions options;
    options.max_bytes = 10;
    const LoadResult r = load_scene_string(SceneParts().json(), "upload.json", options);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].file == "upload.json");
    CHECK(r.errors[0].message.find("larger than the limit of 10 bytes") != std::string::npos);
  }
  SECTION("syntax errors in a file name it") {
    const TempFile file("{\"camera\": }");
    const LoadResult r = load_scene_file(file.path());
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].file == file.path());
    CHECK(r.errors[0].path == "/camera");
  }
}

TEST_CASE("objects are read on a second thread for a large text: same scene, same errors", "[scene][stream]") {
  const dtraced::scene::SceneDesc desc = generate_sphere_field(7000, 5);  // several batches and pieces
  const std::string canonical = dtraced::scene::canonical_json(desc);
  LoadOptions threaded, inline_only;
  threaded.parallel_min_bytes = 0;
  inline_only.parallel_min_bytes = std::numeric_limits<std::uint64_t>::max();
  {
    const LoadResult a = load_scene_string(canonical, "x.json", threaded);
    REQUIRE(a.ok());
    CHECK(*a.scene == desc);
    CHECK(a.scene->objects.capacity() >= desc.objects.size());
    const TempFile file(canonical);
    const LoadResult b = load_scene_file(file.path(), threaded);
    REQUIRE(b.ok());
    CHECK(*b.scene == desc);
  }
  // Problems in objects of several batches, a duplicate key, a warning-free camera error: every
  // message, in the order the inline reader gives them.
  std::string bad = canonical;
  for (const std::size_t k : {5000, 3000, 2100, 10}) {
    std::size_t at = 0;
    for (std::size_t n = 0; n < k; ++n) at = bad.find("\"radius\":", at + 1);
    bad.replace(at, 9, "\"radius\":-");
  }
  const std::size_t dup = bad.find("\"diffuse\":");
  bad.insert(dup, "\"diffuse\":0.5,");
  bad.replace(bad.find("\"fov\":"), 6, "\"fov\":-");
  const LoadResult a = load_scene_string(bad, "x.json", threaded);
  const LoadResult b = load_scene_string(bad, "x.json", inline_only);
  REQUIRE(a.errors.size() == 6);
  REQUIRE(b.errors.size() == a.errors.size());
  for (std::size_t i = 0; i < a.errors.size(); ++i) CHECK(a.errors[i].to_string() == b.errors[i].to_string());
  CHECK(a.errors[1].path == "/camera/fov");
  CHECK(a.errors[2].path == "/scene_objects/10/radius");
  CHECK(a.errors[5].path == "/scene_objects/5000/radius");
  SECTION("error limits hold across batches") {
    threaded.max_errors = 3;
    inline_only.max_errors = 3;
    const LoadResult c = load_scene_string(bad, "x.json", threaded);
    const LoadResult d = load_scene_string(bad, "x.json", inline_only);
    REQUIRE(c.errors.size() == d.errors.size());
    for (std::size_t i = 0; i < c.errors.size(); ++i) CHECK(c.errors[i].to_string() == d.errors[i].to_string());
  }
}

TEST_CASE("duplicate keys come first, in document order, inside objects or not: as the document's parse gives them",
          "[scene][stream]") {
  // The parser checks duplicate keys outside "scene_objects"; those inside an element are found
  // by the loader (StrictParser::record_elements), off the parsing thread, and put in between.
  const dtraced::scene::SceneDesc desc = generate_sphere_field(7000, 5);
  std::string text = dtraced::scene::canonical_json(desc);
  const auto insert_before = [&text](std::string_view key, std::size_t nth, std::string_view what) {
    std::size_t at = 0;
    for (std::size_t n = 0; n <= nth; ++n) at = text.find(key, n == 0 ? 0 : at + 1);
    REQUIRE(at != std::string::npos);
    text.insert(at, what);
  };
  insert_before("\"fov\":", 0, "\"fov\":40,");                       // the camera
  insert_before("\"normal\":", 0, "\"normal\":[0,1,0],");            // the plane: not a plain sphere
  insert_before("\"diffuse\":", 10, "\"diffuse\":0.5,");             // a sphere's material
  insert_before("\"radius\":", 3000, "\"radius\":1,\"radius\":2,");  // twice in one sphere
  insert_before("\"intensity\":", 0, "\"intensity\":1,");            // a light, after the objects
  LoadOptions threaded, inline_only;
  threaded.parallel_min_bytes = 0;
  inline_only.parallel_min_bytes = std::numeric_limits<std::uint64_t>::max();
  for (const std::size_t max_errors : {std::size_t(1000), std::size_t(4), std::size_t(2)}) {
    INFO("max_errors " << max_errors);
    threaded.max_errors = inline_only.max_errors = max_errors;
    const dtraced::jsonio::Document whole = dtraced::jsonio::parse_strict(text, 64, max_errors - 1);
    REQUIRE(whole.parsed);
    REQUIRE(whole.errors.size() == std::min<std::size_t>(6, max_errors - 1));
    for (const LoadOptions* options : {&threaded, &inline_only}) {
      const LoadResult r = load_scene_string(text, "x.json", *options);
      REQUIRE(r.errors.size() >= whole.errors.size());
      for (std::size_t i = 0; i < whole.errors.size(); ++i) {
        CHECK(r.errors[i].message == whole.errors[i].message);
        CHECK(r.errors[i].path == whole.errors[i].path);
      }
    }
  }
  SECTION("and a syntax error in an object after a duplicate key in it: the same errors, the syntax error last") {
    threaded.max_errors = inline_only.max_errors = dtraced::scene::kMaxReportedErrors;
    insert_before("\"loc\":", 5000, "\"loc\":[0,0,7],");
    text.insert(text.find("\"radius\":", text.find("\"loc\":[0,0,7],")), ",");  // the same object's
    const dtraced::jsonio::Document whole =
        dtraced::jsonio::parse_strict(text, 64, dtraced::scene::kMaxReportedErrors - 1);
    REQUIRE_FALSE(whole.parsed);
    // The camera's, the plane's, three in objects and one in the object cut short; the syntax error.
    REQUIRE(whole.errors.size() == 7);
    CHECK(whole.errors[5].message == "duplicate key \"loc\"");
    CHECK(whole.errors[6].path == whole.errors[5].path.substr(0, whole.errors[5].path.size() - 4));
    for (const LoadOptions* options : {&threaded, &inline_only}) {
      const LoadResult r = load_scene_string(text, "x.json", *options);
      REQUIRE(r.errors.size() == whole.errors.size());
      for (std::size_t i = 0; i < whole.errors.size(); ++i) {
        CHECK(r.errors[i].message == whole.errors[i].message);
        CHECK(r.errors[i].path == whole.errors[i].path);
      }
    }
  }
}

TEST_CASE("an object holds one geometry in shared storage", "[scene]") {
  STATIC_REQUIRE(sizeof(dtraced::scene::Object) <= 144);
  dtraced::scene::Object a, b;
  a.type = b.type = dtraced::scene::ObjectType::kBox;
  a.box = b.box = {{0, 0, 0}, {1, 2, 3}};
  CHECK(a == b);
  b.box.max.z = 4;
  CHECK_FALSE(a == b);
  b.type = dtraced::scene::ObjectType::kPlane;
  b.plane = {{0, 0, 0}, {0, 1, 0}};
  CHECK_FALSE(a == b);
}

TEST_CASE("Scene files are read and parsed in pieces: same scene, same errors", "[scene][stream]") {
  // Over 1 MiB (the loader's read size), so the objects and the error below cross pieces.
  const dtraced::scene::SceneDesc desc = generate_sphere_field(6000, 3);
  const std::string canonical = dtraced::scene::canonical_json(desc);
  REQUIRE(canonical.size() > (std::size_t(1) << 20));
  {
    const TempFile file(canonical);
    const LoadResult r = load_scene_file(file.path());
    REQUIRE(r.ok());
    CHECK(*r.scene == desc);
  }
  SECTION("an object's problem keeps its path, after the camera's and before the lights'") {
    std::string bad = canonical;
    const std::size_t at = bad.rfind("\"radius\":");
    bad.replace(at, 9, "\"radius\":-");
    const std::size_t cam = bad.find("\"fov\":");
    bad.replace(cam, 6, "\"fov\":-");
    const TempFile file(bad);
    const LoadResult r = load_scene_file(file.path());
    REQUIRE(r.errors.size() == 2);
    CHECK(r.errors[0].path == "/camera/fov");
    CHECK(r.errors[1].path == "/scene_objects/6000/radius");
    CHECK(r.errors[1].file == file.path());
    CHECK(load_scene_string(bad, "x.json").errors.size() == 2);
  }
  SECTION("a syntax error past the first piece: its line, column and byte") {
    std::string bad = canonical;
    const std::size_t at = bad.rfind("\"radius\":");
    bad.replace(at, 9, "\"radius\"::");
    const TempFile file(bad);
    const LoadResult r = load_scene_file(file.path());
    REQUIRE(r.errors.size() == 1);
    const LoadResult s = load_scene_string(bad, file.path());
    REQUIRE(s.errors.size() == 1);
    CHECK(r.errors[0].to_string() == s.errors[0].to_string());
    CHECK(r.errors[0].message.find(fmt::format("(byte {})", at + 9)) != std::string::npos);
  }
  SECTION("a file over the size limit stops the read with one error") {
    LoadOptions options;
    options.max_bytes = 100;
    CHECK(load_scene_file(TempFile(canonical).path(), options).errors.size() == 1);
  }
  SECTION("a large file's objects read on a second thread: the same scene, the same errors") {
    LoadOptions threaded, inline_only;
    threaded.parallel_min_bytes = 0;
    inline_only.parallel_min_bytes = std::numeric_limits<std::uint64_t>::max();
    const auto same = [&](const std::string& text, const LoadOptions& a, const LoadOptions& b) {
      const TempFile file(text);
      const LoadResult r = load_scene_file(file.path(), a);
      const LoadResult q = load_scene_file(file.path(), b);
      REQUIRE(r.errors.size() == q.errors.size());
      for (std::size_t i = 0; i < r.errors.size(); ++i) CHECK(r.errors[i].to_string() == q.errors[i].to_string());
      return r;
    };
    const LoadResult ok = same(canonical, threaded, inline_only);
    REQUIRE(ok.ok());
    CHECK(*ok.scene == desc);
    std::string bad = canonical;
    bad.replace(bad.rfind("\"radius\":"), 9, "\"radius\":-");
    CHECK(same(bad, threaded, inline_only).errors.size() == 1);
    // Over the limit in the second piece: the one error.
    LoadOptions small_threaded = threaded, small_inline = inline_only;
    small_threaded.max_bytes = small_inline.max_bytes = (std::size_t(3) << 20) / 2;
    const LoadResult big = same(canonical, small_threaded, small_inline);
    REQUIRE(big.errors.size() == 1);
    CHECK(big.errors[0].message.find("larger than the limit") != std::string::npos);
    // A syntax error in the first piece comes before the limit.
    std::string broken = canonical;
    broken.replace(broken.find("\"radius\":"), 9, "\"radius\"::");
    const LoadResult syntax = same(broken, small_threaded, small_inline);
    REQUIRE(syntax.errors.size() == 1);
    CHECK(syntax.errors[0].message.find("invalid JSON") != std::string::npos);
  }
}

namespace {

// The element `text` recorded as parse events and read by read_plain_sphere.
std::optional<dtraced::scene::Object> plain_sphere_of(const std::string& text) {
  namespace jsonio = dtraced::jsonio;
  jsonio::EventLog log;
  jsonio::StrictParser parser(64, 10);
  std::optional<dtraced::scene::Object> out;
  std::size_t elements = 0;
  parser.record_elements("o", &log, [&](std::size_t, const jsonio::EventLog& l, jsonio::EventLog::Mark begin) {
    ++elements;
    out = dtraced::scene::detail::read_plain_sphere(l, begin, l.mark());
  });
  REQUIRE(parser.write("{\"o\": [" + text + "]}"));
  REQUIRE(parser.finish().parsed);
  REQUIRE(elements == 1);
  return out;
}

std::uint64_t bits(double d) { return std::bit_cast<std::uint64_t>(d); }

}  // namespace

TEST_CASE("a plain sphere read from parse events is read_object's to the bit, and anything else is left to it",
          "[scene][stream]") {
  namespace jsonio = dtraced::jsonio;
  const LoadOptions options;
  // Every kind of number (integers, a uint64, subnormal, -0, 17 digits, exponents), any key order.
  const std::vector<std::string> plain = {
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1})",
      R"({"loc": [-4.995457014501857E2, 3.8299796722481083E-1, -0.0], "radius": 3.8299796722481083E-1,
          "type": "sphere", "material": {"color": [4.2860352145080083E-1, 1, 0], "diffuse": 9E-1,
          "specular": 2.541818501401477E-1, "shininess": 1.1082363531405262E2, "reflectivity": 0,
          "transparency": 1, "ior": 1.5E0}})",
      R"({"type": "sphere", "loc": [9007199254740993, -9223372036854775808, 1e-320], "radius": 1e30, "material": {}})",
      R"({"type": "sphere", "loc": [18446744073709551615, -0, 0.1], "radius": 2.5E-38})",
      R"({"material": {"reflectivity": 0.3, "transparency": 0.7, "ior": 4.656612873077393e-10, "shininess": 1e4},
          "radius": 0.30000000000000004, "loc": [0.1, 0.2, 0.3], "type": "sphere"})",
  };
  for (const std::string& text : plain) {
    INFO(text);
    const std::optional<dtraced::scene::Object> fast = plain_sphere_of(text);
    REQUIRE(fast);
    const jsonio::Document doc = jsonio::parse_strict(text, 64, 10);
    REQUIRE(doc.parsed);
    dtraced::scene::detail::SceneReader reader("x.json", options);
    const jsonio::Path root;
    const jsonio::Path list = root.key("o");
    const std::optional<dtraced::scene::Object> slow =
        dtraced::scene::detail::read_object(reader, doc.value, list.index(0));
    REQUIRE(slow);
    CHECK(reader.r.error_count() == 0);
    CHECK(reader.warnings.empty());
    CHECK(fast->type == slow->type);
    CHECK(fast->mesh == nullptr);
    for (std::size_t i = 0; i < 3; ++i) {
      CHECK(bits(fast->sphere.center[i]) == bits(slow->sphere.center[i]));
      CHECK(bits(fast->material.color[i]) == bits(slow->material.color[i]));
    }
    CHECK(bits(fast->sphere.radius) == bits(slow->sphere.radius));
    const auto& a = fast->material;
    const auto& b = slow->material;
    CHECK(bits(a.diffuse) == bits(b.diffuse));
    CHECK(bits(a.specular) == bits(b.specular));
    CHECK(bits(a.shininess) == bits(b.shininess));
    CHECK(bits(a.reflectivity) == bits(b.reflectivity));
    CHECK(bits(a.transparency) == bits(b.transparency));
    CHECK(bits(a.ior) == bits(b.ior));
  }
  // Each a problem read_object reports, or a shape it reads otherwise (a track, another type).
  const std::vector<std::string> other = {
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": -1})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 0})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1e-46})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": "1"})",
      R"({"type": "sphere", "loc": [1e39, 2, 3], "radius": 1})",
      R"({"type": "sphere", "loc": [3e38, 2, 3], "radius": 1e38})",
      R"({"type": "sphere", "loc": [1, 2], "radius": 1})",
      R"({"type": "sphere", "loc": [1, 2, 3, 4], "radius": 1})",
      R"({"type": "sphere", "loc": {"keys": [{"t": 0, "value": [0, 0, 0]}]}, "radius": 1})",
      R"({"type": "box", "loc": [1, 2, 3], "size": [1, 1, 1]})",
      R"({"type": "Sphere", "loc": [1, 2, 3], "radius": 1})",
      R"({"loc": [1, 2, 3], "radius": 1})",
      R"({"type": "sphere", "loc": [1, 2, 3]})",
      R"({"type": "sphere", "radius": 1})",
      R"({"type": "sphere", "centre": [1, 2, 3], "radius": 1})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "radius": 2})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"color": [1.5, 0, 0]}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"color": [-0.1, 0, 0]}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"reflectivity": 0.5, "transparency": 0.6}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"shininess": 1e5}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"ior": 0}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"ior": 1e10}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"colour": [1, 1, 1]}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"diffuse": 1, "diffuse": 1}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": 3})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1, "material": {"color": {"keys": []}}})",
      R"({"type": "sphere", "loc": [1, 2, 3], "radius": 1e400})",
      R"([1, 2, 3])",
      R"("sphere")",
  };
  for (const std::string& text : other) {
    INFO(text);
    CHECK_FALSE(plain_sphere_of(text));
  }
}

TEST_CASE("an element too large to keep in a batch's log is read, and so are the objects after it", "[scene][stream]") {
  // 17 MiB of text in one element: past what a log keeps for the next elements (load.cpp).
  const std::string big(std::size_t(17) << 20, 'x');
  std::string objects = "[";
  for (int i = 0; i < 3000; ++i) {
    if (i > 0) objects += ", ";
    objects += i == 1000 ? R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1, "name": ")" + big + "\"}"
                         : fmt::format(R"({{"type": "sphere", "loc": [{}, 0, 0], "radius": 0.5}})", i);
  }
  objects += "]";
  SceneParts parts;
  parts.objects = objects;
  const std::string text = parts.json();
  for (const std::uint64_t threshold : {std::uint64_t(0), std::numeric_limits<std::uint64_t>::max()}) {
    INFO("parallel_min_bytes " << threshold);
    LoadOptions options;
    options.parallel_min_bytes = threshold;
    const LoadResult r = load_scene_string(text, kFile, options);
    REQUIRE(r.errors.size() == 1);
    CHECK(r.errors[0].path == "/scene_objects/1000/name");
    CHECK(r.errors[0].message.find("unknown key") != std::string::npos);
    // Without it, every object loads, the last ones after the large element's batch included.
    std::string fixed = text;
    fixed.replace(fixed.find(", \"name\""), big.size() + 12, "");  // , "name": "...", quotes included
    const LoadResult ok = load_scene_string(fixed, kFile, options);
    INFO(format_errors(ok.errors));
    REQUIRE(ok.ok());
    REQUIRE(ok.scene->objects.size() == 3000);
    CHECK(ok.scene->objects[2999].sphere.center.x == 2999);
    CHECK(ok.scene->objects[1000].sphere.radius == 1);
  }
}
