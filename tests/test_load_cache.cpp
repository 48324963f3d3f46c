// The worker's binary scene cache (worker/scene_cache.h): a static scene written after its first
// load is read back on the next job with the same digest and renders the same bits as from its
// JSON; a cache file that is corrupt, truncated, of another version or of another scene is an
// error naming the file, and prepare_scene then loads the JSON (and writes the cache again).
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <new>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "temp_dir.h"
#include "util/file.h"
#include "worker/scene_cache.h"

namespace {

namespace render = dtraced::render;
namespace scene = dtraced::scene;
namespace worker = dtraced::worker;
namespace accel = dtraced::accel;
namespace util = dtraced::util;

// Glass (a mesh and a box: camera media and the owner table), a mirror, a plane, two lights.
constexpr const char* kScene = R"({
  "camera": {"position": [0.2, 0.5, 0.3], "look_at": [0, 0, -5]},
  "render": {"width": 24, "height": 16, "samples": 2, "max_depth": 5},
  "scene_objects": [
    {"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0]},
    {"type": "sphere", "loc": [0, 0, -5], "radius": 1, "material": {"reflectivity": 0.3, "specular": 0.4}},
    {"type": "mesh", "obj": "v -4 -4 -4\nv 12 -4 -4\nv -4 12 -4\nv -4 -4 12\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
     "material": {"transparency": 0.9, "ior": 1.3}},
    {"type": "box", "min": [1, -1, -7], "max": [2, 0, -6], "material": {"transparency": 0.5}},
    {"type": "sphere", "loc": [-2, 0, -6], "radius": 0.5}
  ],
  "scene_lights": [{"type": "point", "loc": [3, 5, 4], "intensity": 40},
                   {"type": "sphere", "loc": [-3, 4, -2], "radius": 0.5, "intensity": 20, "samples": 2}]
})";

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

struct Fixture {
  dtraced::testing::TempDir dir;
  std::string canonical;
  std::string digest;
  scene::RenderSettings settings;
  std::vector<float> want;  // the image rendered from the description
  scene::TileRect rect{0, 0, 24, 16};

  Fixture() {
    scene::LoadResult loaded = scene::load_scene_string(kScene, "test");
    REQUIRE(loaded.ok());
    canonical = scene::canonical_json(*loaded.scene);
    digest = scene::scene_digest(*loaded.scene);
    settings = loaded.scene->render;
    want = render::render_tile(render::RenderScene::build(*loaded.scene), settings, rect).rgb;
  }
  std::string file() const { return worker::cached_scene_path(dir.str(), digest); }
  // Writes the cache file by a first load.
  void prime() const {
    const worker::PreparedScene first = worker::prepare_scene(canonical, digest, accel::best_isa(), 1, dir.str());
    INFO(first.error << first.warning);
    REQUIRE(first.scene != nullptr);
    REQUIRE(first.warning.empty());
    REQUIRE(std::filesystem::exists(file()));
  }
  std::string bytes() const { return *util::read_file_limited(file(), 1 << 24); }
  void write(const std::string& b) const { REQUIRE(util::write_file_atomic(file(), b).ok()); }
};

}  // namespace

TEST_CASE("a scene read from its cache file renders the bits of its JSON", "[load][cache]") {
  const Fixture f;
  f.prime();
  // An empty body: the scene can only come from the cache file.
  const worker::PreparedScene cached = worker::prepare_scene("", f.digest, accel::best_isa(), 1, f.dir.str());
  INFO(cached.error << cached.warning);
  REQUIRE(cached.scene != nullptr);
  CHECK(cached.warning.empty());
  CHECK(same_bits(cached.scene->render(f.settings, f.rect).rgb, f.want));
  const auto direct = worker::read_cached_scene(f.file(), f.digest, accel::Isa::kScalar, 2);
  REQUIRE(direct.ok());
  CHECK(same_bits((*direct)->render(f.settings, f.rect).rgb, f.want));
  bool lit = false;
  for (const float v : f.want) lit = lit || v > 0.0f;
  CHECK(lit);
}

TEST_CASE("a bad cache file is an error naming it, and the JSON is loaded instead", "[load][cache]") {
  const Fixture f;
  f.prime();
  const std::string good = f.bytes();
  // The header: 8 magic, 4 version, 4 byte order, 4 + 4 sizes, 64 digest, 5 x 8 counts, 4 + 4
  // features, 5 x 32 checksums; then the description, then the shapes.
  constexpr std::size_t kHeader = 8 + 4 + 4 + 4 + 4 + 64 + 5 * 8 + 4 + 4 + 5 * 32;
  struct Case {
    const char* name;
    std::string bytes;
    const char* says;
  };
  std::vector<Case> cases;
  std::string flipped = good;
  flipped[flipped.size() - 9] ^= 0x40;  // in the last sections
  cases.push_back({"a flipped byte", flipped, "checksum"});
  std::string shape = good;
  shape[kHeader + 200] ^= 0x01;
  cases.push_back({"a flipped byte early", shape, "checksum"});
  cases.push_back({"truncated", good.substr(0, good.size() - 7), "truncated"});
  cases.push_back({"only a header", good.substr(0, kHeader), "truncated"});
  cases.push_back({"shorter than a header", good.substr(0, 20), "not a dtraced scene cache file"});
  std::string old = good;
  old[8] = 0;  // version 0 (little-endian low byte of 1)
  cases.push_back({"another version", old, "version"});
  std::string huge = good;
  std::memset(&huge[8 + 4 + 4 + 4 + 4 + 64 + 8], 0xff, 8);  // the shape count
  cases.push_back({"a count over its bound", huge, "over its limit"});
  cases.push_back({"not a cache file", std::string(4096, 'x'), "not a dtraced scene cache file"});

  for (const Case& c : cases) {
    INFO(c.name);
    f.write(c.bytes);
    const auto read = worker::read_cached_scene(f.file(), f.digest, accel::best_isa(), 1);
    REQUIRE_FALSE(read.ok());
    CHECK(read.error().file == f.file());
    CHECK_THAT(read.error().to_string(), Catch::Contains(c.says) && Catch::Contains(f.file()));
    // The worker loads the JSON, says why, and writes a good cache file again.
    const worker::PreparedScene prepared =
        worker::prepare_scene(f.canonical, f.digest, accel::best_isa(), 1, f.dir.str());
    REQUIRE(prepared.scene != nullptr);
    CHECK_THAT(prepared.warning, Catch::Contains(f.file()) && Catch::Contains("from its JSON instead"));
    CHECK(same_bits(prepared.scene->render(f.settings, f.rect).rgb, f.want));
    CHECK(worker::read_cached_scene(f.file(), f.digest, accel::best_isa(), 1).ok());
  }
}

TEST_CASE("a cache file is of one scene: another digest does not read it", "[load][cache]") {
  const Fixture f;
  f.prime();
  const std::string other(64, 'a');
  const auto read = worker::read_cached_scene(f.file(), other, accel::best_isa(), 1);
  REQUIRE_FALSE(read.ok());
  CHECK_THAT(read.error().to_string(), Catch::Contains("another scene"));
  // A missing file names itself too.
  const auto missing = worker::read_cached_scene(f.dir.str() + "/none.dtscene", f.digest, accel::best_isa(), 1);
  REQUIRE_FALSE(missing.ok());
  CHECK_THAT(missing.error().to_string(), Catch::Contains("none.dtscene"));
}

TEST_CASE("parts that do not fit together are refused", "[load][cache]") {
  accel::Shape sphere;
  sphere.type = accel::ShapeType::kSphere;
  const render::MaterialF m;
  CHECK(render::RenderSceneBuilder::from_parts({sphere, sphere}, {m, m}, {}, {}, {}).ok());
  CHECK_FALSE(render::RenderSceneBuilder::from_parts({sphere, sphere}, {m}, {}, {}, {}).ok());
  CHECK(render::RenderSceneBuilder::from_parts({sphere, sphere, sphere}, {m, m}, {0, 1, 1}, {}, {}).ok());
  CHECK_FALSE(render::RenderSceneBuilder::from_parts({sphere, sphere, sphere}, {m, m}, {0, 2, 2}, {}, {}).ok());
  CHECK_FALSE(render::RenderSceneBuilder::from_parts({sphere, sphere, sphere}, {m, m, m}, {0, 1, 1}, {}, {}).ok());
  CHECK_FALSE(render::RenderSceneBuilder::from_parts({sphere, sphere}, {m, m}, {}, {{2, false}}, {}).ok());
  accel::Shape odd = sphere;
  std::memset(static_cast<void*>(&odd), 9, 1);  // the type byte
  CHECK_FALSE(render::RenderSceneBuilder::from_parts({sphere, odd}, {m, m}, {}, {}, {}).ok());
}

TEST_CASE("the scene cache keeps its most recently used files and nothing else is touched", "[load][cache]") {
  dtraced::testing::TempDir dir;
  const std::filesystem::path root = dir.path();
  const auto now = std::filesystem::file_time_type::clock::now();
  for (int i = 0; i < 5; ++i) {
    const std::filesystem::path file = root / ("scene" + std::to_string(i) + ".dtscene");
    std::ofstream(file) << "x";
    // scene4 is the most recently used, scene0 the least.
    std::filesystem::last_write_time(file, now - std::chrono::hours(10 - i));
  }
  std::ofstream(root / "notes.txt") << "not a cache file";
  std::filesystem::last_write_time(root / "notes.txt", now - std::chrono::hours(100));
  CHECK(worker::prune_scene_cache(root.string(), 8) == 0);
  CHECK(worker::prune_scene_cache(root.string(), 2) == 3);
  CHECK_FALSE(std::filesystem::exists(root / "scene0.dtscene"));
  CHECK_FALSE(std::filesystem::exists(root / "scene2.dtscene"));
  CHECK(std::filesystem::exists(root / "scene3.dtscene"));
  CHECK(std::filesystem::exists(root / "scene4.dtscene"));
  CHECK(std::filesystem::exists(root / "notes.txt"));
}

TEST_CASE("a shape's bytes do not depend on what its memory held before", "[load][cache]") {
  // The cache file holds shapes as they are in memory, and its checksums cover them: two workers
  // writing the same scene must write the same bytes. Build shapes in memory filled with 0xAB
  // and check every byte that no member holds is zero.
  for (const accel::ShapeType type :
       {accel::ShapeType::kSphere, accel::ShapeType::kBox, accel::ShapeType::kPlane, accel::ShapeType::kTriangle}) {
    alignas(accel::Shape) unsigned char memory[sizeof(accel::Shape)];
    // Volatile: a memset before the placement new is a dead store the optimiser may drop.
    volatile unsigned char* fill = memory;
    for (std::size_t i = 0; i < sizeof memory; ++i) fill[i] = 0xAB;
    accel::Shape* s = new (memory) accel::Shape();
    s->type = type;
    std::size_t used = 0;  // bytes of the union the member holds
    switch (type) {
      case accel::ShapeType::kSphere:
        s->sphere = {{1, 2, 3}, 4};
        used = sizeof(accel::SphereShape);
        break;
      case accel::ShapeType::kBox:
        s->box = {{0, 0, 0}, {1, 1, 1}};
        used = sizeof(accel::BoxShape);
        break;
      case accel::ShapeType::kPlane:
        s->plane = {{0, 0, 0}, {0, 1, 0}};
        used = sizeof(accel::PlaneShape);
        break;
      case accel::ShapeType::kTriangle:
        s->triangle = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
        used = sizeof(accel::TriangleShape);
        break;
    }
    accel::Shape copy = *s;  // what a vector of shapes holds
    unsigned char bytes[sizeof(accel::Shape)];
    std::memcpy(bytes, &copy, sizeof bytes);
    const std::size_t member = offsetof(accel::Shape, sphere);
    INFO("shape type " << int(type));
    for (std::size_t i = sizeof(accel::ShapeType); i < member; ++i) CHECK(int(bytes[i]) == 0);
    for (std::size_t i = member + used; i < sizeof bytes; ++i) CHECK(int(bytes[i]) == 0);
    s->~Shape();
  }
}
