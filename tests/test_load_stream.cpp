// Loading a scene without holding its description: `dtraced render` and the worker stream a static
// scene's objects into the render-ready scene (scene::ObjectsDigest, render::RenderSceneBuilder),
// and render the same bits as the description built whole; an animated scene keeps its
// description. scene::ObjectsDigest changes with every field of an object.
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "accel/isa.h"
#include "cli/verbs.h"
#include "image/image_io.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "scene/overrides.h"
#include "temp_dir.h"
#include "util/file.h"
#include "worker/scene_cache.h"

namespace {

namespace cli = dtraced::cli;
namespace image = dtraced::image;
namespace render = dtraced::render;
namespace scene = dtraced::scene;
namespace worker = dtraced::worker;
namespace accel = dtraced::accel;

// Keeps the indices it is given, to check that a digest passes objects on.
class Indices final : public scene::ObjectSink {
 public:
  void reserve(std::size_t) override {}
  void add(std::size_t index, const scene::Object&) override { seen.push_back(index); }
  std::vector<std::size_t> seen;
};

scene::SceneDesc load(const std::string& text) {
  scene::LoadResult loaded = scene::load_scene_string(text, "test");
  INFO(scene::format_errors(loaded.errors));
  REQUIRE(loaded.ok());
  return *loaded.scene;
}

std::string digest_of(const std::vector<scene::Object>& objects) {
  scene::ObjectsDigest d;
  for (std::size_t i = 0; i < objects.size(); ++i) d.add(i, objects[i]);
  return d.hex();
}

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

constexpr const char* kScene = R"({
  "camera": {"position": [0, 1, 6], "look_at": [0, 0, 0]},
  "render": {"width": 24, "height": 16, "samples": 2, "max_depth": 4},
  "scene_objects": [
    {"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0]},
    {"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"reflectivity": 0.3, "specular": 0.4}},
    {"type": "box", "min": [1, -1, -2], "max": [2, 0, -1], "material": {"transparency": 0.5}},
    {"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "translate": [-2, 0, 0]}
  ],
  "scene_lights": [{"type": "point", "loc": [3, 5, 4], "intensity": 40}]
})";

}  // namespace

TEST_CASE("the objects' digest changes with every field of an object and passes objects on", "[load][digest]") {
  const scene::SceneDesc desc = load(kScene);
  const std::string base = digest_of(desc.objects);
  CHECK(base.size() == 64);
  CHECK(digest_of(desc.objects) == base);

  std::vector<std::vector<scene::Object>> changed(9, desc.objects);
  changed[0][1].sphere.radius = std::nextafter(1.0, 2.0);  // one ulp
  changed[1][1].sphere.center.z = 1e-300;
  changed[2][0].plane.normal = {0, -1, 0};
  changed[3][2].box.max.x = 2.5;
  changed[4][1].material.ior = 1.6;
  changed[5][1].material.color.x = 0.5;
  changed[6][3].mesh = std::make_shared<const scene::Mesh>(*desc.objects[3].mesh);
  const_cast<scene::Mesh&>(*changed[6][3].mesh).obj += "# a comment\n";  // the canonical form keeps it
  std::swap(changed[7][1], changed[7][2]);                               // order
  changed[8].pop_back();                                                 // count
  for (std::size_t i = 0; i < changed.size(); ++i) {
    INFO("change " << i);
    CHECK(digest_of(changed[i]) != base);
  }
  // A mesh object with the same text is the same object, whoever holds it.
  std::vector<scene::Object> copied = desc.objects;
  copied[3].mesh = std::make_shared<const scene::Mesh>(*desc.objects[3].mesh);
  CHECK(digest_of(copied) == base);

  // Past a chunk, the digest still sees every object.
  std::vector<scene::Object> many(scene::ObjectsDigest::kChunkBytes / 64, desc.objects[1]);
  const std::string many_hex = digest_of(many);
  many[many.size() / 3].sphere.radius = 2.0;
  CHECK(digest_of(many) != many_hex);

  Indices next;
  scene::ObjectsDigest passing(&next);
  scene::LoadOptions options;
  options.object_sink = &passing;
  const scene::LoadResult loaded = scene::load_scene_string(kScene, "test", options);
  REQUIRE(loaded.ok());
  CHECK(loaded.scene->objects.empty());
  CHECK(next.seen == std::vector<std::size_t>{0, 1, 2, 3});
  CHECK(passing.count() == 4);
  CHECK(passing.hex() == base);
}

TEST_CASE("dtraced render streams a static scene and renders the description's bits", "[load][render]") {
  const dtraced::testing::TempDir dir;
  const std::string scene_path = dir.str() + "/scene.json", out = dir.str() + "/out.pfm";
  REQUIRE(dtraced::util::write_file_atomic(scene_path, kScene).ok());
  cli::RenderArgs args;
  args.scene = scene_path;
  args.output = out;
  args.overrides.tile_size = 8;
  args.threads = 2;
  args.quiet = true;
  REQUIRE(cli::run_render(args) == 0);

  const scene::SceneDesc desc = load(kScene);
  render::LocalOptions options;
  options.threads = 1;
  const render::LocalResult want =
      render::render_local(render::RenderScene::build(desc, args.isa), desc.render, options);
  const auto got = image::read_image(out);
  REQUIRE(got.ok());
  CHECK(same_bits(got->rgb, want.image.rgb));
  bool lit = false;
  for (const float v : got->rgb) lit = lit || v > 0.0f;
  CHECK(lit);
}

TEST_CASE("dtraced render still renders an animated scene from its description", "[load][render]") {
  const dtraced::testing::TempDir dir;
  cli::RenderArgs args;
  args.scene = std::string(DTRACED_SOURCE_DIR) + "/scenes/snowfall.json";
  args.output = dir.str() + "/frame.pfm";
  args.overrides.width = 24;
  args.overrides.height = 16;
  args.overrides.samples = 1;
  args.overrides.frame = 3;
  args.threads = 2;
  args.quiet = true;
  REQUIRE(cli::run_render(args) == 0);

  scene::LoadResult loaded = scene::load_scene_file(args.scene);
  REQUIRE(loaded.ok());
  REQUIRE(scene::is_animated(*loaded.scene));
  loaded.scene->render = scene::apply(args.overrides, loaded.scene->render);
  const render::AnimatedScene prepared = render::AnimatedScene::prepare(*loaded.scene, args.isa);
  const scene::SceneDesc frame = scene::scene_at_frame(*loaded.scene, 3);
  render::LocalOptions options;
  options.threads = 1;
  const render::LocalResult want = render::render_local(*prepared.frame(3), frame.render, options);
  const auto got = image::read_image(args.output);
  REQUIRE(got.ok());
  CHECK(same_bits(got->rgb, want.image.rgb));
}

TEST_CASE("a worker streams a canonical static body and renders the same bits as the description", "[load][worker]") {
  const scene::SceneDesc desc = load(kScene);
  const std::string canonical = scene::canonical_json(desc);
  const std::string digest = scene::scene_digest(desc);
  const render::RenderScene whole = render::RenderScene::build(desc);
  const scene::TileRect rect{0, 0, 24, 16};
  const std::vector<float> want = render::render_tile(whole, desc.render, rect).rgb;

  // Canonical (streamed) and pretty-printed (loaded whole, digest recomputed): the same pixels.
  for (const std::string& body : {canonical, std::string(kScene)}) {
    const worker::PreparedScene prepared = worker::prepare_scene(body, digest, accel::best_isa());
    INFO(prepared.error);
    REQUIRE(prepared.scene != nullptr);
    CHECK_FALSE(prepared.scene->scene().animated());
    CHECK(same_bits(prepared.scene->render(desc.render, rect).rgb, want));
  }
}

TEST_CASE("a worker given a canonical animated body keeps its description for the frames", "[load][worker]") {
  scene::LoadResult loaded = scene::load_scene_file(std::string(DTRACED_SOURCE_DIR) + "/scenes/snowfall.json");
  REQUIRE(loaded.ok());
  scene::SceneDesc desc = *loaded.scene;
  desc.render.width = 16;
  desc.render.height = 16;
  desc.render.samples = 1;
  const worker::PreparedScene prepared =
      worker::prepare_scene(scene::canonical_json(desc), scene::scene_digest(desc), accel::best_isa());
  INFO(prepared.error);
  REQUIRE(prepared.scene != nullptr);
  CHECK(prepared.scene->scene().animated());
  scene::RenderSettings settings = scene::scene_at_frame(desc, 5).render;
  const scene::TileRect rect{0, 0, 16, 16};
  const render::AnimatedScene local = render::AnimatedScene::prepare(desc);
  CHECK(
      same_bits(prepared.scene->render(settings, rect).rgb, render::render_tile(*local.frame(5), settings, rect).rgb));
}
