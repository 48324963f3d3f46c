// Tests for the store's job management: the upgrade of a version 1 database in place, the
// 'paused' state, deleting a job with its tiles (and its scene when nothing else uses it), space
// given back to the file system, and job ids that are never handed out twice.
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>

#include "store_testing.h"

namespace {
using namespace dtraced::testing;
namespace store = dtraced::store;

// The schema dtraced 0.x created (version 1): no 'paused' state, no last_job_id, no auto-vacuum.
constexpr const char* kVersion1Sql = R"sql(
CREATE TABLE meta(key TEXT PRIMARY KEY NOT NULL, value ANY) STRICT;
CREATE TABLE scenes(digest TEXT PRIMARY KEY NOT NULL, json TEXT NOT NULL) STRICT;
CREATE TABLE jobs(
  id INTEGER PRIMARY KEY,
  digest TEXT NOT NULL REFERENCES scenes(digest),
  settings_json TEXT NOT NULL,
  output TEXT NOT NULL,
  priority INTEGER NOT NULL CHECK (priority BETWEEN -2147483648 AND 2147483647),
  tile_size INTEGER NOT NULL CHECK (tile_size BETWEEN 1 AND 4294967295),
  state TEXT NOT NULL CHECK (state IN ('queued', 'rendering', 'done', 'cancelled')),
  created_unix INTEGER NOT NULL,
  finished_unix INTEGER NOT NULL,
  client_key TEXT UNIQUE
) STRICT;
CREATE TABLE tiles(
  job INTEGER NOT NULL REFERENCES jobs(id),
  tile INTEGER NOT NULL CHECK (tile BETWEEN 0 AND 4294967295),
  pixels BLOB NOT NULL,
  worker TEXT NOT NULL,
  stored_unix INTEGER NOT NULL,
  PRIMARY KEY (job, tile)
) STRICT;
INSERT INTO meta(key, value) VALUES ('schema_version', 1);
INSERT INTO scenes VALUES ('digest-a', '{"scene":1}');
INSERT INTO jobs VALUES (1, 'digest-a', '{}', 'a.png', 0, 32, 'done', 1700000000, 1700000100, NULL);
INSERT INTO jobs VALUES (2, 'digest-a', '{}', 'b.png', 5, 32, 'rendering', 1700000001, 0, 'one-shot:k');
INSERT INTO tiles VALUES (2, 0, x'00112233', 'w1', 1700000050);
INSERT INTO tiles VALUES (2, 3, x'44556677', 'w2', 1700000060);
)sql";

constexpr std::string_view kEnded[] = {store::kJobDone, store::kJobCancelled};

std::int64_t job_with_tiles(Store& s, const std::string& digest, std::uint32_t tiles, std::size_t bytes) {
  require_ok(s.put_scene(digest, R"({"scene":2})"));
  auto id = s.insert_job(sample_job(digest));
  if (!id) FAIL(id.error().message);
  std::vector<TileWrite> writes;
  for (std::uint32_t t = 0; t < tiles; ++t) writes.push_back(tile_write(id.value(), t, bytes));
  auto stored = s.insert_tiles(writes);
  if (!stored) FAIL(stored.error().message);
  return id.value();
}

}  // namespace

TEST_CASE("a version 1 database is upgraded in place and keeps every job and tile", "[store]") {
  StoreDir tmp;
  fs::create_directories(tmp.path());
  raw_exec(tmp.db(), kVersion1Sql);
  {
    Store s = open_ok(tmp.path());
    auto jobs = s.list_jobs();
    REQUIRE(jobs.ok());
    REQUIRE(jobs.value().size() == 2);
    CHECK(jobs.value()[0].state == "done");
    CHECK(jobs.value()[1].state == "rendering");
    CHECK(jobs.value()[1].priority == 5);
    CHECK(jobs.value()[1].client_key == std::optional<std::string>("one-shot:k"));
    CHECK(s.stored_tiles(2).value() == std::vector<std::uint32_t>{0, 3});
    CHECK(s.get_tile(2, 3).value()->worker == "w2");
    // The new state is accepted now, and the next id follows the old ones.
    const std::string_view from[] = {store::kJobRendering};
    auto paused = s.change_job_state(2, from, store::kJobPaused, 0);
    REQUIRE(paused.ok());
    CHECK(paused.value().changed);
    auto id = s.insert_job(sample_job());
    REQUIRE(id.ok());
    CHECK(id.value() == 3);
  }
  CHECK(raw_query_text(tmp.db(), "SELECT value FROM meta WHERE key = 'schema_version'") == "4");
  CHECK(raw_query_text(tmp.db(), "SELECT value FROM meta WHERE key = 'last_job_id'") == "3");
  CHECK(raw_query_text(tmp.db(), "PRAGMA auto_vacuum") == "2");
  CHECK(raw_query_text(tmp.db(), "PRAGMA foreign_key_check") == "");
  // Opened again, it is simply version 4 (1 -> 2 -> 3 -> 4: the credential tables exist).
  Store again = open_ok(tmp.path());
  CHECK(again.get_job(2).value()->state == "paused");
  CHECK(again.list_credentials().value().empty());
}

TEST_CASE("delete_job removes an ended job, its tiles and its unshared scene, and nothing else", "[store]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t a = job_with_tiles(s, "digest-a", 4, 100);
  const std::int64_t b = job_with_tiles(s, "digest-a", 2, 100);  // shares the scene
  const std::int64_t c = job_with_tiles(s, "digest-c", 3, 100);

  SECTION("an unfinished job is refused, with its state, and keeps everything") {
    auto r = s.delete_job(a, kEnded);
    REQUIRE(r.ok());
    CHECK_FALSE(r.value().deleted);
    CHECK(r.value().state == "queued");
    CHECK(s.count_tiles(a).value() == 4);
  }
  SECTION("a done job goes; the scene it shares stays") {
    require_ok(s.set_job_state(a, store::kJobDone, 1700000200));
    auto r = s.delete_job(a, kEnded);
    REQUIRE(r.ok());
    CHECK(r.value().deleted);
    CHECK(r.value().tiles == 4);
    CHECK_FALSE(r.value().scene_deleted);
    CHECK_FALSE(s.get_job(a).value().has_value());
    CHECK(s.count_tiles(a).value() == 0);
    CHECK(s.get_scene("digest-a").value().has_value());
    CHECK(s.count_tiles(b).value() == 2);
    CHECK(s.count_tiles(c).value() == 3);
  }
  SECTION("the last job of a scene takes the scene with it") {
    require_ok(s.set_job_state(c, store::kJobCancelled, 1700000200));
    auto r = s.delete_job(c, kEnded);
    REQUIRE(r.ok());
    CHECK(r.value().scene_deleted);
    CHECK_FALSE(s.get_scene("digest-c").value().has_value());
  }
  SECTION("a missing job is an error naming it") {
    auto r = s.delete_job(999, kEnded);
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Contains("no job 999"));
  }
  CHECK(raw_query_text(tmp.db(), "PRAGMA foreign_key_check") == "");
}

TEST_CASE("ids of deleted jobs are never handed out again, across a reopen", "[store]") {
  StoreDir tmp;
  std::int64_t last = 0;
  {
    Store s = open_ok(tmp.path());
    make_job(s);
    last = make_job(s);
    require_ok(s.set_job_state(last, store::kJobDone, 1));
    REQUIRE(s.delete_job(last, kEnded).value().deleted);
  }
  Store s = open_ok(tmp.path());
  auto next = s.insert_job(sample_job());
  REQUIRE(next.ok());
  CHECK(next.value() == last + 1);
}

TEST_CASE("space of a deleted job goes back to the file system", "[store]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t keep = job_with_tiles(s, "digest-a", 4, kBenchTileBytes);
  const std::int64_t big = job_with_tiles(s, "digest-b", 64, kBenchTileBytes);  // 3 MiB
  require_ok(s.set_job_state(big, store::kJobDone, 1));
  REQUIRE(s.checkpoint().ok());
  // The database and the pixel files (store/pixel_files.h) together.
  const auto store_bytes = [&] {
    std::uintmax_t bytes = fs::file_size(tmp.db());
    for (const auto& file : fs::directory_iterator(tmp.path() + "/pixels")) bytes += file.file_size();
    return bytes;
  };
  const auto before = store_bytes();
  REQUIRE(s.delete_job(big, kEnded).value().deleted);
  auto after = s.reclaim_space();
  REQUIRE(after.ok());
  CHECK(after.value().free_pages == 0);
  const auto size = store_bytes();
  INFO("before " << before << " bytes, after " << size);
  CHECK(size + 60 * kBenchTileBytes < before);
  CHECK(s.count_tiles(keep).value() == 4);
}
