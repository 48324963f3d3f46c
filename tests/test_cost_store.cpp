// Tests for the tile costs the store keeps with a job (StoredJob::tile_costs, table
// job_tile_costs): written with the job and read back by every job query, absent for a job
// without them, deleted with the job, and the table is added to a database made before it.
#include <string_view>

#include <catch2/catch.hpp>

#include "store_testing.h"

using namespace dtraced::testing;
namespace store = dtraced::store;

namespace {

constexpr std::string_view kQueued[] = {store::kJobQueued};

}  // namespace

TEST_CASE("a job's tile costs are stored, read back and deleted with it", "[store][cost]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  require_ok(s.put_scene("digest-a", R"({"scene":1})"));
  StoredJob with = sample_job();
  with.tile_costs = {1, 2, 3, 4, 5, 6, 7, 8};
  const auto a = s.insert_job(with);
  REQUIRE(a.ok());
  const auto b = s.insert_job(sample_job());
  REQUIRE(b.ok());

  const auto got = s.get_job(a.value());
  REQUIRE(got.ok());
  REQUIRE(got.value());
  CHECK(got.value()->tile_costs == with.tile_costs);
  const auto plain = s.get_job(b.value());
  REQUIRE(plain.ok());
  REQUIRE(plain.value());
  CHECK(plain.value()->tile_costs.empty());
  const auto all = s.list_jobs();
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == 2);
  CHECK(all.value()[0].tile_costs == with.tile_costs);
  CHECK(all.value()[1].tile_costs.empty());

  const auto deleted = s.delete_job(a.value(), kQueued);
  if (!deleted) FAIL(deleted.error().message);
  CHECK(deleted.value().deleted);
  CHECK(raw_query_text(tmp.db(), "SELECT count(*) FROM job_tile_costs") == "0");
}

TEST_CASE("a database without the tile costs table gets it at open and keeps its jobs", "[store][cost]") {
  StoreDir tmp;
  std::int64_t job = 0;
  {
    Store s = open_ok(tmp.path());
    job = make_job(s);
  }
  // As a file made before the table existed (or by an older dtraced after its own delete).
  raw_exec(tmp.db(), "DROP TABLE job_tile_costs");
  Store s = open_ok(tmp.path());
  const auto got = s.get_job(job);
  REQUIRE(got.ok());
  REQUIRE(got.value());
  CHECK(got.value()->tile_costs.empty());
  CHECK(raw_query_text(tmp.db(), "SELECT count(*) FROM job_tile_costs") == "0");
  CHECK(raw_query_text(tmp.db(), "SELECT value FROM meta WHERE key = 'schema_version'") ==
        std::to_string(store::kSchemaVersion));
}
