// Tests for dtraced::render::tile_cost_map (the submission's cost pre-pass) and the tile costs of
// a JobSubmit: the pre-pass's size stays within its bounds, tiles showing glass cost more than
// tiles showing a diffuse floor or the background, the costs are the same on every call, and the
// decoder accepts exactly one finite cost >= 0 per tile of a frame, naming the field otherwise.
#include <algorithm>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>

#include "decode_testing.h"
#include "protocol/messages.h"
#include "render/cost_map.h"
#include "render/render_scene.h"
#include "scene/load.h"
#include "scene/tiling.h"

namespace {

namespace protocol = dtraced::protocol;
namespace render = dtraced::render;
namespace scene = dtraced::scene;

// A diffuse sphere on the left, a glass sphere on the right, over a diffuse floor.
constexpr std::string_view kScene = R"({
  "camera": {"position": [0, 1, 6], "look_at": [0, 0.5, 0], "fov": 50},
  "render": {"width": 320, "height": 160, "samples": 4, "max_depth": 8},
  "scene_objects": [
    {"type": "plane", "loc": [0, 0, 0], "normal": [0, 1, 0], "material": {"color": [0.6, 0.6, 0.6]}},
    {"type": "sphere", "loc": [-1.5, 0.8, 0], "radius": 0.8, "material": {"color": [0.8, 0.2, 0.2]}},
    {"type": "sphere", "loc": [1.5, 0.8, 0], "radius": 0.8,
     "material": {"color": [1, 1, 1], "diffuse": 0, "transparency": 0.9, "reflectivity": 0.1, "ior": 1.5}}
  ],
  "scene_lights": [{"type": "point", "loc": [-3, 5, 4], "intensity": 60}]
})";

scene::SceneDesc load(std::string_view text) {
  scene::LoadResult loaded = scene::load_scene_string(text, "cost.json");
  for (const auto& e : loaded.errors) INFO(e.to_string());
  REQUIRE(loaded.ok());
  return std::move(*loaded.scene);
}

std::string submit_body(std::string_view extra) { return dtraced::testing::submit_body(kScene, extra); }

using dtraced::testing::first_error;

// "[1, 1, ..., 1]" with n entries.
std::string ones(std::size_t n) {
  std::string s = "[";
  for (std::size_t i = 0; i < n; ++i) s += i == 0 ? "1" : ", 1";
  return s + "]";
}

}  // namespace

TEST_CASE("the pre-pass is at most 1/8 of each side and at most max_pixels", "[cost]") {
  const render::CostGridSize small = render::cost_grid_size(320, 160);
  CHECK(small.width == 40);
  CHECK(small.height == 20);
  const render::CostGridSize big = render::cost_grid_size(3840, 2160);
  CHECK(std::uint64_t{big.width} * big.height <= 16384);
  CHECK(big.width <= 3840 / 8);
  CHECK(big.width > big.height);  // the aspect ratio is kept, roughly
  const render::CostGridSize tiny = render::cost_grid_size(3, 2);
  CHECK(tiny.width == 1);
  CHECK(tiny.height == 1);
  render::CostMapOptions capped;
  capped.max_pixels = 100;
  const render::CostGridSize c = render::cost_grid_size(1000, 1000, capped);
  CHECK(std::uint64_t{c.width} * c.height <= 100);
  CHECK(c.width >= 9);
}

TEST_CASE("tiles showing glass cost more than tiles showing diffuse objects", "[cost]") {
  const scene::SceneDesc desc = load(kScene);
  const render::RenderScene rs = render::RenderScene::build(desc);
  const scene::RenderSettings& s = desc.render;
  const std::uint32_t tile = 80;  // 4 x 2 tiles
  const render::CostMap map = render::tile_cost_map(rs, s, tile);
  REQUIRE(map.costs.size() == scene::TileGrid(s, tile).count());
  CHECK(map.width == 40);
  CHECK(map.height == 20);
  CHECK(map.rays > 0);
  for (const float c : map.costs) CHECK(c >= 0);
  // Lower row: tile 4 is the floor and the left (diffuse) sphere's edge, tiles 5 and 6 hold the
  // spheres, the glass one to the right of the image centre. The costliest tile is a glass tile.
  const auto top = std::max_element(map.costs.begin(), map.costs.end()) - map.costs.begin();
  INFO("costs: " << map.costs[0] << " " << map.costs[1] << " " << map.costs[2] << " " << map.costs[3] << " / "
                 << map.costs[4] << " " << map.costs[5] << " " << map.costs[6] << " " << map.costs[7]);
  CHECK((top == 6 || top == 2));
  CHECK(map.costs[6] > map.costs[5]);  // the glass sphere's tile over the diffuse one's
  CHECK(map.costs[6] > map.costs[0]);  // and over the sky

  // A pure function: the same costs again (ray counts, not times).
  CHECK(render::tile_cost_map(rs, s, tile).costs == map.costs);
}

TEST_CASE("tile costs sum the pre-pass's rays over the image whatever the tile size", "[cost]") {
  const scene::SceneDesc desc = load(kScene);
  const render::RenderScene rs = render::RenderScene::build(desc);
  // Every full-resolution pixel counts its low-resolution pixel's rays once: the sum over the tiles
  // is the same for any tile size (tiles that do not divide the image included).
  double sums[3] = {0, 0, 0};
  const std::uint32_t sizes[3] = {16, 37, 160};
  for (int i = 0; i < 3; ++i) {
    const render::CostMap map = render::tile_cost_map(rs, desc.render, sizes[i]);
    for (const float c : map.costs) sums[i] += c;
  }
  CHECK(sums[1] == Approx(sums[0]).epsilon(1e-5));
  CHECK(sums[2] == Approx(sums[0]).epsilon(1e-5));
  // The pre-pass's 40 x 20 pixels each stand for 8 x 8 pixels of the image.
  const render::CostMap map = render::tile_cost_map(rs, desc.render, 16);
  CHECK(sums[0] == Approx(double(map.rays) * 64).epsilon(1e-5));
}

TEST_CASE("a submission's tile costs round trip and are checked", "[cost][protocol]") {
  // 320 x 160 in tiles of 80: 8 tiles a frame.
  auto d = protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": [0, 1.5, 2, 3, 4, 5, 6, 1e20])"));
  for (const auto& e : d.ok() ? dtraced::util::Errors{} : d.error()) INFO(e.to_string());
  REQUIRE(d.ok());
  CHECK(d.value().tile_costs == std::vector<float>{0, 1.5f, 2, 3, 4, 5, 6, 1e20f});
  const auto back = protocol::decode_job_submit(protocol::encode(d.value()));
  REQUIRE(back.ok());
  CHECK(back.value() == d.value());

  // Absent: none, and none on the wire.
  auto none = protocol::decode_job_submit(submit_body(R"("tile_size": 80)"));
  REQUIRE(none.ok());
  CHECK(none.value().tile_costs.empty());
  CHECK(protocol::encode(none.value()).find("tile_costs") == std::string::npos);

  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": [1, 2, 3])"))) ==
        "/tile_costs: has 3 costs; the job has 8 tiles per frame (one cost each)");
  // The count follows the overrides: at width 160 the grid is 2 x 2.
  CHECK(protocol::decode_job_submit(submit_body(R"("tile_size": 80, "width": 160, "tile_costs": [1, 2, 3, 4])")).ok());
  CHECK(first_error(
            protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": [0, 1, 2, 3, -1, 5, 6, 7])")))
            .rfind("/tile_costs/4: ", 0) == 0);
  CHECK(first_error(
            protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": [0, 1, 2, "3", 4, 5, 6, 7])")))
            .rfind("/tile_costs/3: ", 0) == 0);
  CHECK(first_error(
            protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": [0, 1, 2, 3, 4, 5, 6, 1e31])")))
            .rfind("/tile_costs/7: ", 0) == 0);
  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("tile_size": 80, "tile_costs": 5)")))
            .rfind("/tile_costs: ", 0) == 0);
  // A sequence sends one frame's costs, used for every frame.
  CHECK(protocol::decode_job_submit(
            submit_body(R"("tile_size": 80, "frames": {"first": 1, "last": 3}, "tile_costs": )" + ones(8)))
            .ok());
}
