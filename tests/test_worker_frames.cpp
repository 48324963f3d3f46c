// Tests of the worker's frames (worker/scene_cache.h, SceneFrames): a lease's settings.frame picks
// the frame of an animated scene, and the tile a worker renders for it is the tile of
// scene::scene_at_frame rendered locally; frames are built once while kept, at most kKeptFrames of
// them; static scenes keep their one RenderScene.
#include <cstdint>
#include <cstring>
#include <memory>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>

#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "scene_builders.h"
#include "worker/scene_cache.h"

using namespace dtraced;
using namespace dtraced::testing;

namespace {

// The bundled mesh scene with a few more spheres, small; marked animated (an empty Animation:
// until scenes animate, the frames differ by their noise) so that frames take the layered path.
scene::SceneDesc animated_scene() {
  scene::SceneDesc d = bundled_scene("mesh", 36, 24);
  d.render.samples = 2;
  for (int i = 0; i < 5; ++i) {
    d.objects.push_back(testing::sphere(d.camera.look_at + math::Vec3d{0.4 * i - 1, 0.2, 0}, 0.2, diffuse()));
  }
  d.animation = std::make_shared<const scene::Animation>();
  return d;
}

// The last six objects move (five spheres and what precedes them).
std::vector<bool> last_move(const scene::SceneDesc& d) {
  std::vector<bool> moving(d.objects.size(), false);
  for (std::size_t i = d.objects.size() - 6; i < d.objects.size(); ++i) {
    moving[i] = d.objects[i].type != scene::ObjectType::kMesh;
  }
  return moving;
}

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

}  // namespace

TEST_CASE("a worker's tile of frame k is the tile of scene_at_frame(k) rendered locally", "[worker][frames]") {
  const scene::SceneDesc desc = animated_scene();
  const worker::SceneFrames frames(render::AnimatedScene::prepare(desc, last_move(desc)));
  REQUIRE(frames.scene().animated());
  const render::TileRect rect{5, 3, 20, 14};
  for (const std::uint32_t k : {0u, 2u, 5u}) {
    CAPTURE(k);
    const scene::SceneDesc at = scene::scene_at_frame(desc, k);
    // The lease carries the frame's settings (its render block, frame = k).
    const render::Tile worker_tile = frames.render(at.render, rect);
    const render::Tile local = render::render_tile(render::RenderScene::build(at), at.render, rect);
    CHECK(same_bits(worker_tile.rgb, local.rgb));
  }
  // Frames differ (the noise at least), so the comparison above can tell them apart.
  const scene::SceneDesc f0 = scene::scene_at_frame(desc, 0), f2 = scene::scene_at_frame(desc, 2);
  CHECK_FALSE(same_bits(frames.render(f0.render, rect).rgb, frames.render(f2.render, rect).rgb));
}

TEST_CASE("an animated scene's body: the worker's tile of frame k is the local tile of scene_at_frame(k)",
          "[worker][frames]") {
  // A sphere flying across a ground plane, a box rising, a still sphere; 24 frames a second.
  const std::string json = R"({
    "camera": {"position": [0, 2, 8], "look_at": [0, 1, 0], "up": [0, 1, 0], "fov": 50},
    "render": {"width": 32, "height": 24, "samples": 2},
    "scene_objects": [
      {"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0], "material": {"color": [0.8, 0.8, 0.8]}},
      {"type": "sphere", "loc": {"keys": [{"t": 0, "value": [-3, 1, 0]}, {"t": 1, "value": [3, 1, 0]}]},
       "radius": 0.8, "material": {"color": [0.9, 0.3, 0.2]}},
      {"type": "box", "min": [-0.5, 0, -2], "max": [0.5, 1, -1], "material": {"color": [0.2, 0.8, 0.3]}},
      {"type": "sphere", "loc": [1.5, 0.5, 1], "radius": 0.5, "material": {"color": [0.3, 0.3, 0.9]}}
    ],
    "scene_lights": [{"type": "point", "loc": [2, 6, 4], "intensity": 60}]
  })";
  const scene::LoadResult loaded = scene::load_scene_string(json, "flying");
  REQUIRE(loaded.ok());
  const scene::SceneDesc& desc = *loaded.scene;
  REQUIRE(scene::is_animated(desc));
  const worker::PreparedScene prepared =
      worker::prepare_scene(scene::canonical_json(desc), scene::scene_digest(desc), accel::best_isa());
  REQUIRE(prepared.scene != nullptr);
  REQUIRE(prepared.scene->scene().animated());
  CHECK(prepared.scene->scene().static_part()->moving == std::vector<bool>{false, true, false, false});
  const render::TileRect rect{0, 0, 32, 24};
  std::vector<std::vector<float>> images;
  for (const std::uint32_t k : {12u, 0u, 24u}) {
    CAPTURE(k);
    const scene::SceneDesc at = scene::scene_at_frame(desc, k);
    const render::Tile worker_tile = prepared.scene->render(at.render, rect);
    CHECK(same_bits(worker_tile.rgb, render::render_tile(render::RenderScene::build(at), at.render, rect).rgb));
    images.push_back(worker_tile.rgb);
  }
  CHECK_FALSE(same_bits(images[1], images[2]));
}

TEST_CASE("a static scene from a body renders frame k as scene_at_frame(k), one scene for all", "[worker][frames]") {
  scene::SceneDesc desc = animated_scene();
  desc.animation = nullptr;
  const std::string body = scene::canonical_json(desc);
  const worker::PreparedScene prepared = worker::prepare_scene(body, scene::scene_digest(desc), accel::best_isa());
  REQUIRE(prepared.scene != nullptr);
  CHECK_FALSE(prepared.scene->scene().animated());
  CHECK(prepared.scene->frame(0) == prepared.scene->frame(9));
  const scene::SceneDesc at = scene::scene_at_frame(desc, 3);
  const render::TileRect rect{0, 0, 36, 24};
  CHECK(same_bits(prepared.scene->render(at.render, rect).rgb,
                  render::render_tile(render::RenderScene::build(at), at.render, rect).rgb));
  CHECK(prepared.scene->kept() == 0);
}

TEST_CASE("a worker builds a frame once while kept and keeps only the latest few", "[worker][frames]") {
  const scene::SceneDesc desc = animated_scene();
  const worker::SceneFrames frames(render::AnimatedScene::prepare(desc, last_move(desc)), 3);
  const worker::ScenePtr first = frames.frame(1);
  CHECK(frames.frame(1) == first);
  CHECK(first->geometry().fixed() == frames.scene().static_part()->layer.get());
  for (const std::uint32_t k : {2u, 3u, 4u}) frames.frame(k);
  CHECK(frames.kept() == 3);
  const worker::ScenePtr again = frames.frame(1);  // evicted, built again: another object
  CHECK(again != first);
  CHECK(frames.kept() == 3);
  const scene::SceneDesc at = scene::scene_at_frame(desc, 1);
  const render::TileRect rect{0, 0, 36, 24};
  CHECK(same_bits(render::render_tile(*first, at.render, rect).rgb, render::render_tile(*again, at.render, rect).rgb));
}

TEST_CASE("render threads asking for one frame at once share one build", "[worker][frames]") {
  const scene::SceneDesc desc = animated_scene();
  const worker::SceneFrames frames(render::AnimatedScene::prepare(desc, last_move(desc)));
  std::vector<worker::ScenePtr> got(6);
  {
    std::vector<std::jthread> threads;
    for (std::size_t i = 0; i < got.size(); ++i) {
      threads.emplace_back([&frames, &got, i] { got[i] = frames.frame(7); });
    }
  }
  for (const worker::ScenePtr& p : got) CHECK(p == got[0]);
  CHECK(frames.kept() == 1);
}
