// The limits that keep shading finite in float (scene/description.h, derived in
// scene/load_objects.cpp): at each limit a scene loads and renders finite pixels; one step (one
// double) beyond it is refused, with the JSON Pointer of the value.
#include <cmath>
#include <string>
#include <string_view>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/description.h"
#include "scene/tiling.h"
#include "scene_testing.h"

namespace {

using namespace scene_testing;
namespace scene = dtraced::scene;
namespace render = dtraced::render;

// The JSON text of `d`: the shortest digits that read back to the same double.
std::string num(double d) { return fmt::format("{}", d); }

double below(double d) { return std::nextafter(d, 0.0); }
double above(double d) { return std::nextafter(d, HUGE_VAL); }

// The smallest double that rounds to a normal float: the midpoint between the largest subnormal
// float and FLT_MIN, which rounds (to even) up to FLT_MIN.
constexpr double kSmallestNormalAsFloat = 0x1.fffffep-127;

// A scene around `objects` and `lights` (JSON array bodies) that exercises every term shading
// sums: two facing mirrors (max_depth bounces), a glass sphere, a diffuse floor.
std::string scene_with(std::string_view objects, std::string_view lights, std::string_view render = "") {
  return fmt::format(R"({{
    "camera": {{"position": [0, 1, 6], "look_at": [0, 0.5, 0]}},
    "render": {{"width": 12, "height": 12, "samples": 2, "max_depth": 64 {}}},
    "scene_objects": [
      {{"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0], "material": {{"color": [1, 1, 1]}}}},
      {{"type": "plane", "loc": [0, 0, -3], "normal": [0, 0, 1],
        "material": {{"color": [1, 1, 1], "diffuse": 0, "reflectivity": 1}}}},
      {{"type": "plane", "loc": [0, 0, 9], "normal": [0, 0, -1],
        "material": {{"color": [1, 1, 1], "diffuse": 0, "reflectivity": 1}}}},
      {{"type": "sphere", "loc": [1, 0, 0], "radius": 0.5,
        "material": {{"color": [1, 1, 1], "transparency": 1, "ior": 1.5}}}}
      {}
    ],
    "scene_lights": [{{"type": "point", "loc": [0, 3, 2]}} {}]
  }})",
                     render, objects, lights);
}

// Loads `json` (REQUIREd to succeed) and renders it whole: whether every pixel is finite and no
// sample had a NaN or an Inf.
void check_renders_finite(const std::string& json) {
  const scene::SceneDesc desc = load_ok(json);
  const render::RenderScene rs = render::RenderScene::build(desc);
  const scene::TileRect whole{0, 0, desc.render.width, desc.render.height};
  const render::Tile tile = render::render_tile(rs, desc.render, whole);
  CHECK(tile.stats.nan_samples == 0);
  CHECK(tile.stats.inf_samples == 0);
  bool finite = true;
  for (const float v : tile.rgb) finite = finite && std::isfinite(v);
  CHECK(finite);
}

void check_refused_at(const std::string& json, std::string_view path, std::string_view fragment) {
  const LoadResult r = load_scene_string(json, kFile);
  INFO(format_errors(r.errors));
  CHECK_FALSE(r.ok());
  CHECK(r.errors.size() == 1);
  CHECK(has_error(r, path, fragment));
}

}  // namespace

TEST_CASE("a sphere's radius must round to a normal float", "[scene][limits]") {
  const auto sphere = [](double r) {
    return scene_with(fmt::format(R"(, {{"type": "sphere", "loc": [0, 0, 0], "radius": {}}})", num(r)), "");
  };
  check_renders_finite(sphere(kSmallestNormalAsFloat));
  check_refused_at(sphere(below(kSmallestNormalAsFloat)), "/scene_objects/4/radius", "normal float");
  check_refused_at(sphere(1e-46), "/scene_objects/4/radius", "too small");
  // Its bounds must be floats too, or the renderer skips it.
  check_refused_at(scene_with(R"(, {"type": "sphere", "loc": [3e38, 0, 0], "radius": 1e38})", ""),
                   "/scene_objects/4/radius", "beyond the float range");
}

TEST_CASE("an ior lies in [2^-31, 2^31], so that a ratio of two squared stays a normal float", "[scene][limits]") {
  // Glass of the largest ior inside glass of the smallest: eta = 2^62 at the inner surface.
  const auto nested = [](double outer, double inner) {
    return scene_with(fmt::format(R"(, {{"type": "sphere", "loc": [-1, 0.5, 1], "radius": 1,
                                       "material": {{"transparency": 1, "diffuse": 0, "ior": {}}}}},
                                     {{"type": "sphere", "loc": [-1, 0.5, 1], "radius": 0.5,
                                       "material": {{"transparency": 1, "diffuse": 0, "ior": {}}}}})",
                                  num(outer), num(inner)),
                      "");
  };
  check_renders_finite(nested(scene::kMinIor, scene::kMaxIor));
  check_renders_finite(nested(scene::kMaxIor, scene::kMinIor));
  check_refused_at(nested(below(scene::kMinIor), 1.5), "/scene_objects/4/material/ior", "must be in [");
  check_refused_at(nested(1.5, above(scene::kMaxIor)), "/scene_objects/5/material/ior", "must be in [");
  check_refused_at(nested(1e-46, 1.5), "/scene_objects/4/material/ior", "(got 1e-46)");
}

TEST_CASE("a sphere or disk light's radius lies in [2^-63, 2^63], so that its square is a normal float",
          "[scene][limits]") {
  const auto sphere_light = [](double r, std::string_view loc) {
    return scene_with("",
                      fmt::format(R"(, {{"type": "sphere", "loc": {}, "radius": {}, "intensity": 2}})", loc, num(r)));
  };
  const auto disk_light = [](double r) {
    return scene_with(
        "", fmt::format(R"(, {{"type": "disk", "loc": [0, 4, 0], "normal": [0, -1, 0], "radius": {}}})", num(r)));
  };
  check_renders_finite(sphere_light(scene::kMinLightRadius, "[0, 4, 0]"));
  check_renders_finite(disk_light(scene::kMinLightRadius));
  // The largest one, far away behind the camera.
  check_renders_finite(sphere_light(scene::kMaxLightRadius, "[0, 0, 1.2e19]"));
  check_refused_at(sphere_light(below(scene::kMinLightRadius), "[0, 4, 0]"), "/scene_lights/1/radius",
                   "must be in [1.0842e-19, 9.22337e+18] (2^-63 to 2^63: light sampling squares it)");
  check_refused_at(sphere_light(above(scene::kMaxLightRadius), "[0, 0, 1.2e19]"), "/scene_lights/1/radius",
                   "must be in [");
  check_refused_at(disk_light(1e-46), "/scene_lights/1/radius", "(got 1e-46)");
}

TEST_CASE("a light's color x intensity is at most 2^120 per channel, seen directly, in mirrors and lighting",
          "[scene][limits]") {
  // An area light seen by the camera and in the mirrors, and a point light 0.1 above the floor.
  const auto area = [](std::string_view color, double intensity) {
    return fmt::format(R"(, {{"type": "sphere", "loc": [0, 1.5, 0], "radius": 0.3, "color": {}, "intensity": {}}})",
                       color, num(intensity));
  };
  const auto point = [](std::string_view color, double intensity) {
    return fmt::format(R"(, {{"type": "point", "loc": [0.5, -0.9, 1], "color": {}, "intensity": {}}})", color,
                       num(intensity));
  };
  const std::string max = num(scene::kMaxRadiance);
  check_renders_finite(
      scene_with("", area("[1, 1, 1]", scene::kMaxRadiance) + point("[1, 1, 1]", scene::kMaxRadiance)));
  const std::string max_red = fmt::format("[{}, 0, 1]", max);
  check_renders_finite(scene_with("", area(max_red, 1) + point(max_red, 1)));

  check_refused_at(scene_with("", area("[1, 1, 1]", above(scene::kMaxRadiance))), "/scene_lights/1/intensity",
                   fmt::format("at most 2^120 (1.32923e+36) per channel, or shading overflows (got {} in channel 0)",
                               num(above(scene::kMaxRadiance))));
  check_refused_at(scene_with("", point("[0, 3e38, 1]", 3e38)), "/scene_lights/1/intensity", "in channel 1");
  // Without an intensity, the colour carries the blame.
  check_refused_at(scene_with("", fmt::format(R"(, {{"type": "point", "loc": [0, 3, 0], "color": [0, 0, {}]}})",
                                              num(above(scene::kMaxRadiance)))),
                   "/scene_lights/1/color", "in channel 2");
}

TEST_CASE("the background is a radiance: at most 2^120 per channel", "[scene][limits]") {
  const auto background = [](double b) {
    return scene_with("", "", fmt::format(R"(, "background": [{0}, {0}, {0}])", num(b)));
  };
  check_renders_finite(background(scene::kMaxRadiance));
  check_refused_at(scene_with("", "", fmt::format(R"(, "background": [1, {}, 1])", num(above(scene::kMaxRadiance)))),
                   "/render/background/1", "at most 2^120");
}

TEST_CASE("a material's colour is at most 1 per channel, or mirrors multiply light without bound", "[scene][limits]") {
  const auto mirror_colour = [](double c) {
    return scene_with(fmt::format(R"(, {{"type": "sphere", "loc": [-1, 0, 0], "radius": 0.5,
                                       "material": {{"color": [{0}, 1, 1], "reflectivity": 1, "diffuse": 0}}}})",
                                  num(c)),
                      "");
  };
  check_renders_finite(mirror_colour(scene::kMaxAlbedo));
  check_refused_at(mirror_colour(above(scene::kMaxAlbedo)), "/scene_objects/4/material/color/0", "at most 1");
  check_refused_at(mirror_colour(3e38), "/scene_objects/4/material/color/0", "at most 1");
}
