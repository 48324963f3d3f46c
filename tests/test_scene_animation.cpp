// Tests for dtraced::scene animation: tracks in scene files (interpolation against closed forms,
// repeat and offset, validation located at the key), the render block's animation and display
// keys, scene_at / scene_at_frame / moving_objects, and the canonical form of animated scenes.
#include <algorithm>
#include <cmath>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>

#include "jsonio/reader.h"
#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "scene/overrides.h"
#include "scene/scene_json.h"
#include "scene_testing.h"

namespace {

using namespace scene_testing;
using dtraced::math::Vec3d;
using namespace dtraced::scene;

// A scene whose one sphere's "loc" is `loc` (a track, or a vector).
std::string sphere_at(std::string_view loc, std::string_view render = "{}") {
  SceneParts p;
  p.render = std::string(render);
  p.objects = R"([{"type": "sphere", "loc": )" + std::string(loc) + R"(, "radius": 1}])";
  return p.json();
}

// The first track of the scene `json` (which must load).
Track first_track(std::string_view json) {
  const SceneDesc d = load_ok(json);
  REQUIRE(d.animation != nullptr);
  REQUIRE(!d.animation->tracks.empty());
  return d.animation->tracks.front();
}

// A scalar track over `keys` ("[{"t": 0, "value": 1}, ...]") with `extra` keys: a sphere's radius.
Track radius_track(std::string_view keys, std::string_view extra = "") {
  SceneParts p;
  p.objects =
      R"([{"type": "sphere", "loc": [0, 0, 0], "radius": {"keys": )" + std::string(keys) + std::string(extra) + "}}]";
  return first_track(p.json());
}

void check_refused_once(const std::string& json, std::string_view path, std::string_view fragment) {
  const LoadResult r = load_scene_string(json, kFile);
  INFO("errors:\n" << format_errors(r.errors));
  CHECK_FALSE(r.ok());
  CHECK(r.errors.size() == 1);
  CHECK(has_error(r, path, fragment));
}

}  // namespace

TEST_CASE("linear tracks are exact at keys and midpoints and hold before the first and after the last key",
          "[scene][animation]") {
  const Track t = first_track(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 2, "value": [2, 4, -2]}]})"));
  CHECK(t.target == Target::kObjectLoc);
  CHECK(t.interpolation == Interpolation::kLinear);
  CHECK(evaluate(t, 0) == Vec3d{0, 0, 0});
  CHECK(evaluate(t, 2) == Vec3d{2, 4, -2});
  CHECK(evaluate(t, 1) == Vec3d{1, 2, -1});
  CHECK(evaluate(t, 0.5) == Vec3d{0.5, 1, -0.5});
  CHECK(evaluate(t, -1) == Vec3d{0, 0, 0});
  CHECK(evaluate(t, 1e9) == Vec3d{2, 4, -2});

  // Three keys, uneven spacing: each segment is its own straight line.
  const Track u = radius_track(R"([{"t": 0, "value": 1}, {"t": 1, "value": 3}, {"t": 5, "value": 2}])");
  CHECK(evaluate(u, 0.25).x == 1.5);
  CHECK(evaluate(u, 3).x == 2.5);
  CHECK(evaluate(u, 1).x == 3);
}

TEST_CASE("smooth tracks follow the monotone cubic Hermite: ease at the ends, Brodlie tangents inside",
          "[scene][animation]") {
  // Two keys: zero end tangents, so p0 + (p1 - p0) (3 s^2 - 2 s^3).
  const Track two = radius_track(R"([{"t": 0, "value": 1}, {"t": 4, "value": 3}])", R"(, "interpolation": "smooth")");
  CHECK(two.interpolation == Interpolation::kSmooth);
  CHECK(evaluate(two, 0).x == 1);
  CHECK(evaluate(two, 4).x == 3);
  CHECK(evaluate(two, 2).x == 2);  // the midpoint
  for (const double s : {0.1, 0.25, 0.6, 0.9}) {
    CHECK(evaluate(two, 4 * s).x == Approx(1 + 2 * (3 * s * s - 2 * s * s * s)).epsilon(1e-14));
  }
  CHECK(evaluate(two, -3).x == 1);
  CHECK(evaluate(two, 7).x == 3);

  // Keys 0, 1, 3 at t = 0, 1, 2: the middle tangent is 3 (1 + 1) / ((2 + 1) / 1 + (1 + 2) / 2) = 4/3,
  // so at t = 0.5: h01 * 1 + h11 * 4/3 = 0.5 - 0.125 * 4/3 = 1/3.
  const Track three = radius_track(R"([{"t": 0, "value": 1}, {"t": 1, "value": 2}, {"t": 2, "value": 4}])",
                                   R"(, "interpolation": "smooth")");
  CHECK(evaluate(three, 0.5).x == Approx(1 + 1.0 / 3).epsilon(1e-14));
  CHECK(evaluate(three, 1).x == 2);
  // A key where the motion turns gets a zero tangent: an extremum at the key, not past it.
  const Track peak = radius_track(R"([{"t": 0, "value": 1}, {"t": 1, "value": 2}, {"t": 2, "value": 1}])",
                                  R"(, "interpolation": "smooth")");
  CHECK(evaluate(peak, 0.5).x == 1.5);
  CHECK(evaluate(peak, 1.5).x == 1.5);
}

TEST_CASE("smooth interpolation never overshoots: every value stays between its segment's keys", "[scene][animation]") {
  const Track t = radius_track(R"([{"t": 0, "value": 0.5}, {"t": 0.3, "value": 1}, {"t": 0.35, "value": 1},
      {"t": 2, "value": 0.2}, {"t": 2.1, "value": 0.9}, {"t": 5, "value": 0.95}, {"t": 5.01, "value": 10}])",
                               R"(, "interpolation": "smooth")");
  for (std::size_t k = 0; k + 1 < t.keys.size(); ++k) {
    const Key& a = t.keys[k];
    const Key& b = t.keys[k + 1];
    const double lo = std::min(a.value.x, b.value.x), hi = std::max(a.value.x, b.value.x);
    double previous = a.value.x;
    for (int i = 1; i <= 200; ++i) {
      const double x = evaluate(t, a.t + (b.t - a.t) * i / 200.0).x;
      INFO("segment " << k << ", step " << i << ": " << x);
      CHECK(x >= lo);
      CHECK(x <= hi);
      // Monotone within the segment, in the direction of its keys.
      CHECK((b.value.x >= a.value.x ? x >= previous : x <= previous));
      previous = x;
    }
  }
}

TEST_CASE("repeat makes the key span periodic and offset shifts the keys later", "[scene][animation]") {
  const std::string keys = R"("keys": [{"t": 0, "value": [0, 6, 0]}, {"t": 2, "value": [0, 0, 0]}])";
  const Track loop = first_track(sphere_at("{" + keys + R"(, "repeat": true, "offset": 0.5})"));
  CHECK(loop.repeat);
  CHECK(loop.offset == 0.5);
  CHECK(evaluate(loop, 0.5) == Vec3d{0, 6, 0});   // the first key, 0.5 s late
  CHECK(evaluate(loop, 1.5) == Vec3d{0, 3, 0});   // halfway
  CHECK(evaluate(loop, 2.5) == Vec3d{0, 6, 0});   // one period on: the first key again
  CHECK(evaluate(loop, 0) == Vec3d{0, 1.5, 0});   // before the offset: the previous period
  CHECK(evaluate(loop, -3.5) == Vec3d{0, 6, 0});  // two periods before
  CHECK(evaluate(loop, 100.5 + 1) == Vec3d{0, 3, 0});

  // Without repeat the same keys hold at both ends.
  const Track once = first_track(sphere_at("{" + keys + R"(, "offset": 0.5})"));
  CHECK(evaluate(once, 0) == Vec3d{0, 6, 0});
  CHECK(evaluate(once, 1.5) == Vec3d{0, 3, 0});
  CHECK(evaluate(once, 10) == Vec3d{0, 0, 0});
}

TEST_CASE("a smooth repeating track whose ends meet loops without a kink", "[scene][animation]") {
  // 0 -> 1 -> -1 -> 0: at the seam the wrapped neighbours give the tangent 3 * 2 / (3 + 3) = 1.
  const std::string keys = R"([{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [1, 0, 0]},
                               {"t": 2, "value": [-1, 0, 0]}, {"t": 3, "value": [0, 0, 0]}])";
  const Track loop = first_track(sphere_at(R"({"keys": )" + keys + R"(, "interpolation": "smooth", "repeat": true})"));
  CHECK(evaluate(loop, 0.001).x == Approx(0.001).epsilon(1e-3));
  CHECK(evaluate(loop, -0.001).x == Approx(-0.001).epsilon(1e-3));
  // Not repeating, the ends ease in: the slope there is 0.
  const Track once = first_track(sphere_at(R"({"keys": )" + keys + R"(, "interpolation": "smooth"})"));
  CHECK(std::abs(evaluate(once, 0.001).x) < 1e-5);
}

TEST_CASE("every key is validated like a static value, and the error names the key", "[scene][animation][errors]") {
  check_refused_once(
      sphere_at(
          R"({"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1.5, "value": [1, 0, 0]}, {"t": 1.5, "value": [2, 0, 0]}]})"),
      "/scene_objects/0/loc/keys/2/t", "must be greater than the previous key's t (1.5)");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [1, 0]}]})"),
                     "/scene_objects/0/loc/keys/1/value", "expected an array of 3 numbers");
  check_refused_once(sphere_at(R"({"keys": []})"), "/scene_objects/0/loc/keys", "at least one key");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}], "repeat": true})"),
                     "/scene_objects/0/loc/repeat", "at least two keys");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}], "interpolation": "cubic"})"),
                     "/scene_objects/0/loc/interpolation", "unknown interpolation \"cubic\"");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}], "ofset": 1})"), "/scene_objects/0/loc/ofset",
                     "did you mean \"offset\"");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0]}], "offset": 1e7})"),
                     "/scene_objects/0/loc/offset", "must be in");
  check_refused_once(sphere_at(R"({"keys": [{"t": 0, "value": [0, 0, 0], "tt": 1}]})"),
                     "/scene_objects/0/loc/keys/0/tt", "unknown key");
  check_refused_once(with_object(R"({"type": "sphere", "loc": [0, 0, 0],
                                     "radius": {"keys": [{"t": 0, "value": 1}, {"t": 1, "value": -1}]}})"),
                     "/scene_objects/0/radius/keys/1/value", "must be > 0");
  check_refused_once(
      with_material(R"({"color": {"keys": [{"t": 0, "value": [0.5, 0.5, 0.5]}, {"t": 1, "value": [1, 1, 2]}]}})"),
      "/scene_objects/0/material/color/keys/1/value/2", "must be at most 1");
  // Derived checks hold over the keys' whole range: the brightest colour times the largest intensity.
  check_refused_once(with_light(R"({"type": "point", "loc": [0, 5, 0],
                                    "color": {"keys": [{"t": 0, "value": [1, 1, 1]}, {"t": 1, "value": [4, 1, 1]}]},
                                    "intensity": {"keys": [{"t": 0, "value": 1e36}, {"t": 3, "value": 1}]}})"),
                     "/scene_lights/0/intensity", "must be at most 2^120");
  check_refused_once(with_object(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
                                     "scale": {"keys": [{"t": 0, "value": 1}, {"t": 1, "value": [1, -1, 1]}]}})"),
                     "/scene_objects/0/scale/keys/1/value", "component 1 must have the sign of the first key's");
  check_refused_once(with_object(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
                                     "translate": {"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [3.4e38, 0, 0]}]},
                                     "scale": 1e38})"),
                     "/scene_objects/0/obj", "beyond the float range");
  check_refused_once(with_object(R"({"type": "sphere", "radius": 1e38,
                                     "loc": {"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [3e38, 0, 0]}]}})"),
                     "/scene_objects/0/radius", "sphere extends beyond the float range");
  // A unit box moved to 1e17, where doubles are 16 apart, would collapse to a point on the way.
  check_refused_once(with_object(R"({"type": "box", "size": [1, 1, 1],
                                     "loc": {"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [1e17, 0, 0]}]}})"),
                     "/scene_objects/0/size/0", "too small to be represented");
  // A camera that passes through its look_at at a frame of the scene's own range.
  SceneParts p;
  p.camera =
      R"({"position": {"keys": [{"t": 0, "value": [0, 0, 5]}, {"t": 2, "value": [0, 0, -5]}]}, "look_at": [0, 0, 0]})";
  p.render = R"({"fps": 24, "frames": {"first": 0, "last": 47}})";
  check_refused_once(p.json(), "/camera/look_at", "at t = 1 s (frame 24): must differ from the camera position");

  std::string many = R"({"keys": [)";
  for (std::size_t i = 0; i <= kMaxKeys; ++i)
    many += std::string(i ? "," : "") + R"({"t": )" + std::to_string(i) + R"(, "value": [0, 0, 0]})";
  check_refused_once(sphere_at(many + "]}"), "/scene_objects/0/loc/keys", "too many keys: 10001 (limit 10000)");
}

TEST_CASE("the render block reads fps, frames, exposure and tone, and refuses bad ones by name",
          "[scene][animation][render]") {
  const SceneDesc d = load_ok(with_render(
      R"({"fps": 12.5, "frames": {"first": 2, "last": 20, "step": 3}, "exposure": -1.5, "tone": "filmic"})"));
  CHECK(d.render.fps == 12.5);
  REQUIRE(d.render.frames.has_value());
  CHECK(*d.render.frames == FrameRange{2, 20, 3});
  CHECK(d.render.frames->count() == 7);
  CHECK(d.render.display.exposure == -1.5);
  CHECK(d.render.display.tone == dtraced::image::ToneCurve::kFilmic);
  CHECK(load_ok(with_render(R"({"frames": {"first": 0, "last": 9}})")).render.frames->step == 1);

  check_refused_once(with_render(R"({"fps": 0})"), "/render/fps", "must be in (0, 1000]");
  check_refused_once(with_render(R"({"fps": 1001})"), "/render/fps", "must be in (0, 1000]");
  check_refused_once(with_render(R"({"frames": {"first": 5, "last": 4}})"), "/render/frames/last",
                     "must be >= first (5)");
  check_refused_once(with_render(R"({"frames": {"first": 0, "last": 100000}})"), "/render/frames",
                     "100001 frames, more than the limit of 100000");
  check_refused_once(with_render(R"({"frames": {"first": 0, "last": 4, "step": 0}})"), "/render/frames/step",
                     "integer");
  check_refused_once(with_render(R"({"frames": [0, 4]})"), "/render/frames", "expected an object");
  check_refused_once(with_render(R"({"exposure": 33})"), "/render/exposure", "must be in [-32, 32]");
  check_refused_once(with_render(R"({"tone": "aces"})"), "/render/tone", "unknown tone curve \"aces\"");
}

TEST_CASE("overrides read the same render keys, each set only when present", "[scene][animation][render]") {
  dtraced::jsonio::Reader r("overrides");
  const auto doc =
      r.parse(R"({"fps": 30, "frames": {"first": 1, "last": 24}, "tone": "reinhard"})", "overrides", 4096, 8);
  REQUIRE(doc.has_value());
  Overrides o;
  const dtraced::jsonio::Path root;
  dtraced::jsonio::Fields f(r, doc->get_object(), root, kRenderKeys);
  read_render_settings(f, o, dtraced::jsonio::Need::kOptional);
  CHECK_FALSE(r.failed());
  CHECK(o.fps == 30.0);
  CHECK(o.frames == FrameRange{1, 24, 1});
  CHECK(o.tone == dtraced::image::ToneCurve::kReinhard);
  CHECK_FALSE(o.exposure.has_value());
  CHECK_FALSE(o.width.has_value());
}

TEST_CASE("render keys at their defaults are not written, so static scenes keep their digests",
          "[scene][animation][digest]") {
  // Digests as main computed them before animation existed: scenes/snowman.json as it is, and
  // scenes/showcase.json without the tone curve it has since been given.
  const LoadResult snowman = load_scene_file(source_path("scenes/snowman.json"));
  REQUIRE(snowman.ok());
  CHECK(scene_digest(*snowman.scene) == "0779b8fc55ed7132f54ca1430f2aa0c6b32e0853ddc9b458609737faf04e6326");
  LoadResult showcase = load_scene_file(source_path("scenes/showcase.json"));
  REQUIRE(showcase.ok());
  CHECK(showcase.scene->animation == nullptr);
  CHECK(showcase.scene->render.display.tone == dtraced::image::ToneCurve::kFilmic);
  showcase.scene->render.display = {};
  CHECK(scene_digest(*showcase.scene) == "fa416a6e067312d90a10552d808142c0676ed03d4d5ecac32920f983a1c38e35");

  const SceneDesc explicit_defaults = load_ok(with_render(R"({"fps": 24, "exposure": 0, "tone": "clamp"})"));
  CHECK(canonical_json(explicit_defaults) == canonical_json(load_ok(with_render("{}"))));
  const std::string set = canonical_json(
      load_ok(with_render(R"({"fps": 30, "frames": {"first": 0, "last": 47}, "exposure": -1, "tone": "filmic"})")));
  CHECK(set.find(R"("fps":30,"frames":{"first":0,"last":47,"step":1},"exposure":-1,"tone":"filmic")") !=
        std::string::npos);
}

namespace {

const std::string kAnimated = R"({
  "camera": {"position": {"keys": [{"t": 0, "value": [0, 1, 6]}, {"t": 2, "value": [1, 1.5, 6]}], "interpolation": "smooth"},
             "look_at": [0, 1, 0], "fov": {"keys": [{"t": 0, "value": 40}, {"t": 1, "value": 45.5}]}},
  "render": {"fps": 24, "frames": {"first": 0, "last": 47}},
  "scene_objects": [
    {"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0]},
    {"type": "sphere", "loc": {"keys": [{"t": 0, "value": [0.3, 6, 0.1]}, {"t": 2, "value": [0.5, -0.1, 0.1]}],
                                "repeat": true, "offset": 0.7}, "radius": 0.05},
    {"type": "sphere", "loc": [1, 1, 0], "radius": 0.5,
     "material": {"color": {"keys": [{"t": 0, "value": [1, 0, 0]}, {"t": 1, "value": [0, 0, 1]}], "interpolation": "smooth"}}},
    {"type": "box", "loc": {"keys": [{"t": 0, "value": [-1, 0.5, 0]}, {"t": 1, "value": [-1, 1.5, 0]}]}, "size": [1, 1, 0.3]},
    {"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "rotate": {"keys": [{"t": 0, "value": [0, 0, 0]}, {"t": 1, "value": [0, 90, 0]}]},
     "scale": {"keys": [{"t": 0, "value": 1}, {"t": 1, "value": [2, 2, 2]}]}}
  ],
  "scene_lights": [{"type": "point", "loc": {"keys": [{"t": 0, "value": [5, 5, 5]}, {"t": 1, "value": [-5, 5, 5]}]},
                    "intensity": {"keys": [{"t": 0, "value": 50}, {"t": 1, "value": 80}], "interpolation": "smooth"}}]
})";

}  // namespace

TEST_CASE("an animated scene's canonical form reloads to the same scene and names it", "[scene][animation][digest]") {
  const SceneDesc d = load_ok(kAnimated);
  REQUIRE(is_animated(d));
  CHECK(d.animation->tracks.size() == 9);
  const std::string canonical = canonical_json(d);
  const SceneDesc again = load_ok(canonical);
  CHECK(again == d);
  CHECK(canonical_json(again) == canonical);
  CHECK(canonical.find(R"("loc":{"keys":[{"t":0,"value":[3E-1,6,1E-1]},{"t":2,"value":[5E-1,-1E-1,1E-1]}],)"
                       R"("interpolation":"linear","repeat":true,"offset":7E-1})") != std::string::npos);
  CHECK(canonical.find(R"("size":[1,1,3E-1])") != std::string::npos);  // a moving box keeps loc and size

  // The same scene frozen at t = 0 is another scene.
  const SceneDesc frozen = scene_at(d, 0);
  CHECK(frozen.animation == nullptr);
  CHECK(scene_digest(frozen) != scene_digest(d));
  // Any change to a key changes the digest.
  std::string moved = kAnimated;
  moved.replace(moved.find("45.5"), 4, "45.6");
  CHECK(scene_digest(load_ok(moved)) != scene_digest(d));
}

TEST_CASE("scene_at evaluates every animated value, and the description holds the values at t = 0",
          "[scene][animation]") {
  const SceneDesc d = load_ok(kAnimated);
  // The description itself is the scene at t = 0.
  CHECK(d.objects[1].sphere.center == evaluate(d.animation->tracks[2], 0));
  const SceneDesc at0 = scene_at(d, 0);
  CHECK(at0.objects == d.objects);
  CHECK(at0.camera == d.camera);

  const SceneDesc s = scene_at(d, 0.5);
  CHECK(s.animation == nullptr);
  CHECK(s.camera.fov_deg == 42.75);
  CHECK(s.camera.position == Vec3d{0.15625, 1.078125, 6});  // smooth: 3 s^2 - 2 s^3 at s = 1/4 is 5/32
  // The flake, 0.7 s late, is at 1.8 s of its 2 s loop: 0.9 of the way down.
  CHECK(s.objects[1].sphere.center.y == Approx(6 - 6.1 * 0.9).epsilon(1e-12));
  CHECK(s.objects[2].material.color == Vec3d{0.5, 0, 0.5});
  CHECK(s.objects[3].box.min == Vec3d{-1.5, 0.5, -0.15});
  CHECK(s.objects[3].box.max == Vec3d{-0.5, 1.5, 0.15});
  CHECK(s.lights[0].position == Vec3d{0, 5, 5});
  CHECK(s.lights[0].intensity == 65);
  // The mesh at t = 1: scale 2, then 90 degrees about Y: (1, 0, 0) -> (0, 0, -2).
  const SceneDesc s1 = scene_at(d, 1);
  REQUIRE(s1.objects[4].mesh->vertices.size() == 3);
  CHECK(s1.objects[4].mesh->vertices[1].x == Approx(0).margin(1e-6));
  CHECK(s1.objects[4].mesh->vertices[1].z == Approx(-2));
  CHECK(s1.objects[4].mesh->scale == Vec3d{2, 2, 2});
  // The description's mesh is untouched (shared, immutable).
  CHECK(d.objects[4].mesh->scale == Vec3d{1, 1, 1});
  CHECK(d.objects[4].mesh->vertices[1].x == 1);
}

TEST_CASE("scene_at_frame takes the time frame / fps and sets the frame, and a static scene only changes frame",
          "[scene][animation]") {
  const SceneDesc d = load_ok(kAnimated);
  const SceneDesc f12 = scene_at_frame(d, 12);
  CHECK(f12.render.frame == 12);
  CHECK(f12 == [&] {
    SceneDesc s = scene_at(d, 0.5);
    s.render.frame = 12;
    return s;
  }());
  // The snowflake loops every 2 s: 48 frames at 24 fps.
  CHECK(scene_at_frame(d, 48).objects[1] == scene_at_frame(d, 0).objects[1]);

  const SceneDesc still = load_ok(with_render("{}"));
  const SceneDesc still5 = scene_at_frame(still, 5);
  CHECK(still5.render.frame == 5);
  CHECK(still5.objects == still.objects);
  CHECK(still5.camera == still.camera);
  CHECK(moving_objects(still) == std::vector<bool>{false});
}

TEST_CASE("moving_objects flags geometry that changes, not a material alone", "[scene][animation]") {
  CHECK(moving_objects(load_ok(kAnimated)) == std::vector<bool>{false, true, false, true, true});
}

TEST_CASE("between checked times a degenerate camera falls back to the t = 0 view", "[scene][animation]") {
  // The camera passes through look_at at t = 1, neither a key nor a frame of the scene's range.
  SceneParts p;
  p.camera =
      R"({"position": {"keys": [{"t": 0, "value": [0, 0, 5]}, {"t": 2, "value": [0, 0, -5]}]}, "look_at": [0, 0, 0]})";
  const SceneDesc d = load_ok(p.json());
  const Camera raw = animated_camera(d, 1);
  CHECK(camera_problem(raw).has_value());
  const Camera c = scene_at(d, 1).camera;
  CHECK_FALSE(camera_problem(c).has_value());
  CHECK(c.position == Vec3d{0, 0, 0});
  CHECK(c.look_at == Vec3d{0, 0, -5});

  // An up that lines up with the view: the t = 0 up is used instead.
  p.camera = R"({"position": [0, 0, 5], "look_at": [0, 0, 0],
                 "up": {"keys": [{"t": 0, "value": [0, 1, 0]}, {"t": 2, "value": [0, -1, 2]}]}})";
  const SceneDesc e = load_ok(p.json());
  CHECK(camera_problem(animated_camera(e, 1)).has_value());  // (0, 0, 1): parallel to the view
  CHECK(scene_at(e, 1).camera.up == Vec3d{0, 1, 0});
}

TEST_CASE("the shipped snowfall loops seamlessly over its 48 frames, every flake moving", "[scene][animation][files]") {
  const LoadResult r = load_scene_file(source_path("scenes/snowfall.json"));
  INFO(format_errors(r.errors));
  REQUIRE(r.ok());
  const SceneDesc& d = *r.scene;
  REQUIRE(d.render.frames.has_value());
  CHECK(d.render.frames->count() == 48);
  CHECK(d.render.fps == 24);
  CHECK(d.render.width == 320);
  CHECK(d.render.height == 240);
  // Frame 48 (one past the range) is frame 0 again, bit for bit; frame 12 is not.
  CHECK(scene_at_frame(d, 48).objects == scene_at_frame(d, 0).objects);
  CHECK(scene_at_frame(d, 12).objects != scene_at_frame(d, 0).objects);
  const std::vector<bool> moving = moving_objects(d);
  CHECK(std::count(moving.begin(), moving.end(), true) == 100);
  CHECK(std::count(moving.begin(), moving.begin() + 10, true) == 0);  // the snowman stands still
}

TEST_CASE("a hand-made animation whose tracks name no such object or light changes nothing", "[scene][animation]") {
  SceneDesc d = load_ok(with_render("{}"));  // one sphere, one light
  auto animation = std::make_shared<Animation>();
  for (const Target target : {Target::kObjectLoc, Target::kMeshScale, Target::kLightIntensity}) {
    Track track;
    track.target = target;
    track.index = target == Target::kMeshScale ? 0 : 5;  // object 0 is a sphere, not a mesh
    track.keys = {Key{0, Vec3d{3, 3, 3}}};
    animation->tracks.push_back(track);
  }
  sort_tracks(*animation);
  d.animation = animation;
  const SceneDesc s = scene_at(d, 1);
  CHECK(s.objects == d.objects);
  CHECK(s.lights == d.lights);
}
