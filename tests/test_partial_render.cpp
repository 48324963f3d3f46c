// A local render stopped between tiles and resumed: render_local's cancellation, its tile_done
// hook and its skip list put together give the same bits as a render straight through (uniform
// and adaptive), and the partial file (cli/partial_render.h) keeps tiles bit for bit, drops a
// torn last record, and refuses a partial of other settings.
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "cli/partial_render.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/load.h"
#include "scene/tiling.h"
#include "temp_dir.h"
#include "util/file.h"
#include "util/sha256.h"

using namespace dtraced;

namespace {

scene::SceneDesc showcase(bool adaptive) {
  scene::LoadResult r = scene::load_scene_file(DTRACED_SOURCE_DIR "/scenes/showcase.json");
  REQUIRE(r.ok());
  scene::SceneDesc d = *r.scene;
  d.render.width = 40;
  d.render.height = 24;
  d.render.samples = adaptive ? 16 : 2;
  if (adaptive) {
    d.render.error_target = 0.05;
    d.render.min_samples = 4;
  }
  return d;
}

// A render of `d` in tiles of 8 that stops after `keep` tiles, its tiles collected by index.
std::vector<std::pair<std::size_t, render::Tile>> stopped_render(const render::RenderScene& rs,
                                                                 const scene::SceneDesc& d, std::size_t keep) {
  std::vector<std::pair<std::size_t, render::Tile>> kept;
  std::size_t started = 0;  // one render thread asks before each tile it starts
  render::LocalOptions o;
  o.threads = 1;
  o.tile_size = 8;
  o.stop_requested = [&] { return started++ >= keep; };
  o.tile_done = [&](std::size_t index, const render::Tile& t) { kept.emplace_back(index, t); };
  const render::LocalResult r = render::render_local(rs, d.render, o);
  CHECK_FALSE(r.complete);
  CHECK(r.tiles_rendered == keep);
  return kept;
}

// The adaptive showcase stopped after 3 tiles of 8, with a partial file's path in a directory of
// its own and the key that file carries.
struct StoppedShowcase {
  testing::TempDir dir;
  std::string path = (dir.path() / "out.pfm.partial").string();
  scene::SceneDesc d = showcase(/* adaptive = */ true);
  render::RenderScene rs = render::RenderScene::build(d);
  std::string key = cli::partial_key(d, 8);
  std::vector<std::pair<std::size_t, render::Tile>> kept = stopped_render(rs, d, 3);
};

}  // namespace

TEST_CASE("a render stopped between tiles and resumed is bitwise the straight render", "[render][resume]") {
  for (const bool adaptive : {false, true}) {
    INFO("adaptive " << adaptive);
    const scene::SceneDesc d = showcase(adaptive);
    const render::RenderScene rs = render::RenderScene::build(d);
    render::LocalOptions straight_options;
    straight_options.tile_size = 8;
    const render::LocalResult straight = render::render_local(rs, d.render, straight_options);
    REQUIRE(straight.complete);
    const std::uint64_t total = scene::TileGrid(d.render, 8).count();
    REQUIRE(total == 15);

    const auto kept = stopped_render(rs, d, 6);
    REQUIRE(kept.size() == 6);
    render::LocalOptions rest;
    rest.tile_size = 8;
    rest.skip.assign(total, false);
    for (const auto& [index, tile] : kept) rest.skip[index] = true;
    std::size_t progress_done = 0;
    rest.progress = [&](std::size_t done, std::size_t all) {
      CHECK(all == total);
      progress_done = done;
    };
    render::LocalResult resumed = render::render_local(rs, d.render, rest);
    CHECK(resumed.complete);
    CHECK(resumed.tiles_rendered == total - 6);
    CHECK(progress_done == total);
    // Before the kept tiles are pasted the image differs (so the comparison below can fail).
    CHECK(std::memcmp(resumed.image.rgb.data(), straight.image.rgb.data(), straight.image.rgb.size() * 4) != 0);
    for (const auto& [index, tile] : kept) render::paste_tile(tile, d.render.width, resumed);
    CHECK(std::memcmp(resumed.image.rgb.data(), straight.image.rgb.data(), straight.image.rgb.size() * 4) == 0);
    CHECK(resumed.spp == straight.spp);
  }
}

TEST_CASE("the partial file keeps tiles bit for bit, drops a torn end, and refuses other settings", "[cli][resume]") {
  const StoppedShowcase f;
  const std::string& path = f.path;
  const scene::SceneDesc& d = f.d;
  const std::string& key = f.key;
  const auto& kept = f.kept;
  {
    auto w = cli::PartialWriter::create(path, key);
    REQUIRE(w);
    for (const auto& [index, tile] : kept) REQUIRE(w->append(static_cast<std::uint32_t>(index), tile));
    REQUIRE(w->sync());
    // Never replaces a partial file.
    CHECK_FALSE(cli::PartialWriter::create(path, key));
  }
  auto read = cli::read_partial(path, key, d.render, 8);
  REQUIRE(read);
  CHECK(read->version == 2);
  REQUIRE(read->tiles.size() == 3);
  CHECK(read->dropped_bytes == 0);
  CHECK(read->good_bytes == std::filesystem::file_size(path));
  for (std::size_t i = 0; i < 3; ++i) {
    CHECK(read->tiles[i].rect == kept[i].second.rect);
    CHECK(std::memcmp(read->tiles[i].rgb.data(), kept[i].second.rgb.data(), kept[i].second.rgb.size() * 4) == 0);
    CHECK(read->tiles[i].spp == kept[i].second.spp);
  }

  // A kill in the middle of an append: the torn record is dropped, the others kept.
  REQUIRE(::truncate(path.c_str(), static_cast<off_t>(read->good_bytes - 5)) == 0);
  auto torn = cli::read_partial(path, key, d.render, 8);
  REQUIRE(torn);
  CHECK(torn->tiles.size() == 2);
  CHECK(torn->dropped_bytes > 0);
  {
    auto w = cli::PartialWriter::reopen(path, torn->good_bytes, torn->version);
    REQUIRE(w);
    REQUIRE(w->append(static_cast<std::uint32_t>(kept[2].first), kept[2].second));
  }
  auto mended = cli::read_partial(path, key, d.render, 8);
  REQUIRE(mended);
  CHECK(mended->tiles.size() == 3);
  CHECK(mended->dropped_bytes == 0);

  // Other settings or another tile size have another key: refused, naming the file.
  scene::SceneDesc other = d;
  other.render.samples = 32;
  const auto refused = cli::read_partial(path, cli::partial_key(other, 8), other.render, 8);
  REQUIRE_FALSE(refused);
  CHECK(refused.error().file == path);
  CHECK(refused.error().message.find("another scene or other settings") != std::string::npos);
  CHECK(cli::partial_key(d, 16) != key);
  // A flipped byte in a record ends the reading there.
  {
    auto bytes = util::read_file_limited(path, 1 << 20);
    REQUIRE(bytes);
    (*bytes)[200] ^= 1;
    REQUIRE(util::write_file_atomic(path, *bytes));
  }
  auto damaged = cli::read_partial(path, key, d.render, 8);
  REQUIRE(damaged);
  CHECK(damaged->tiles.empty());
  // Not a partial file at all.
  REQUIRE(util::write_file_atomic(path, "hello"));
  CHECK_FALSE(cli::read_partial(path, key, d.render, 8));
}

TEST_CASE("a version 1 partial file (SHA-256 records) still resumes, appended to in version 1", "[cli][resume]") {
  const StoppedShowcase f;
  const std::string& path = f.path;
  const scene::SceneDesc& d = f.d;
  const std::string& key = f.key;
  const auto& kept = f.kept;
  // The file an earlier dtraced wrote: its header, then two records with their SHA-256.
  std::string file = "dtraced-partial-v1\n" + key + "\n";
  for (std::size_t k = 0; k < 2; ++k) {
    const render::Tile& t = kept[k].second;
    const auto index = static_cast<std::uint32_t>(kept[k].first);
    const auto bytes = static_cast<std::uint32_t>(t.rgb.size() * 4 + t.spp.size() * 4);
    std::string body(8, '\0');
    std::memcpy(body.data(), &index, 4);
    std::memcpy(body.data() + 4, &bytes, 4);
    body.append(reinterpret_cast<const char*>(t.rgb.data()), t.rgb.size() * 4);
    body.append(reinterpret_cast<const char*>(t.spp.data()), t.spp.size() * 4);
    const util::Sha256Digest sum = util::sha256_bytes(body);
    file += "TILE" + body + std::string(reinterpret_cast<const char*>(sum.data()), sum.size());
  }
  REQUIRE(util::write_file_atomic(path, file));
  auto read = cli::read_partial(path, key, d.render, 8);
  REQUIRE(read);
  CHECK(read->version == 1);
  CHECK(read->good_bytes == file.size());
  REQUIRE(read->tiles.size() == 2);
  CHECK(std::memcmp(read->tiles[1].rgb.data(), kept[1].second.rgb.data(), kept[1].second.rgb.size() * 4) == 0);
  {
    auto w = cli::PartialWriter::reopen(path, read->good_bytes, read->version);
    REQUIRE(w);
    REQUIRE(w->append(static_cast<std::uint32_t>(kept[2].first), kept[2].second));
  }
  auto more = cli::read_partial(path, key, d.render, 8);
  REQUIRE(more);
  CHECK(more->version == 1);
  REQUIRE(more->tiles.size() == 3);
  CHECK(more->dropped_bytes == 0);
  CHECK(std::memcmp(more->tiles[2].rgb.data(), kept[2].second.rgb.data(), kept[2].second.rgb.size() * 4) == 0);
  CHECK(more->tiles[2].spp == kept[2].second.spp);
}
