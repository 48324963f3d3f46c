// The cost order of a farm job through the collector: a job submitted with tile costs is leased
// costliest tile first, and a restarted collector resumes its unfinished tiles in the same order
// (the costs are stored with the job); a job without costs keeps row order.
#include <cstdint>
#include <vector>

#include <catch2/catch.hpp>

#include "collector_testing.h"

using namespace dtraced::testing;

namespace {

// kScene is 32 x 24 in tiles of 8: 4 x 3 tiles. Costs, and the order they give (descending, ties
// in row order).
constexpr std::string_view kCosts = R"(, "tile_costs": [1, 9, 0, 3, 5, 5, 0, 2, 7, 0, 4, 8])";
const std::vector<std::uint32_t> kCostOrder = {1, 11, 8, 4, 5, 10, 3, 7, 0, 2, 6, 9};

std::vector<std::uint32_t> tiles_of(const std::vector<protocol::Lease>& leases) {
  std::vector<std::uint32_t> out;
  for (const protocol::Lease& l : leases) out.push_back(l.tile);
  return out;
}

}  // namespace

TEST_CASE("a job with tile costs is leased costliest first, and after a restart in the same order",
          "[collector][service][cost]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::uint64_t job = 0;
  {
    Harness h(config);
    job = h.submit(kCosts);
    std::vector<protocol::Lease> first;
    for (int i = 0; i < 4; ++i) {
      auto l = h.lease();
      REQUIRE(l);
      first.push_back(*l);
    }
    CHECK(tiles_of(first) == std::vector<std::uint32_t>(kCostOrder.begin(), kCostOrder.begin() + 4));
    // Two of them stored; the other two were out when the collector went away.
    REQUIRE(h.put_ok(first[0]) == protocol::SubmitResult::kStored);
    REQUIRE(h.put_ok(first[2]) == protocol::SubmitResult::kStored);
  }
  Harness h(config);
  CHECK(h.status(job).tiles_done == 2);
  // Every unfinished tile, in the cost order (tiles 11 and 4, leased before, included).
  std::vector<std::uint32_t> rest;
  for (const std::uint32_t t : kCostOrder) {
    if (t != 1 && t != 8) rest.push_back(t);
  }
  CHECK(tiles_of(h.lease_all()) == rest);
}

TEST_CASE("a job without tile costs keeps row order across a restart", "[collector][service][cost]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  {
    Harness h(config);
    h.submit();
    auto l = h.lease();
    REQUIRE(l);
    CHECK(l->tile == 0);
    REQUIRE(h.put_ok(*l) == protocol::SubmitResult::kStored);
  }
  Harness h(config);
  CHECK(tiles_of(h.lease_all()) == std::vector<std::uint32_t>{1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11});
}

TEST_CASE("a submission with the wrong number of tile costs is refused, naming the field",
          "[collector][service][cost]") {
  TempDir dir;
  Harness h(make_config(dir));
  const Response res = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "tile_costs": [1, 2, 3])"));
  CHECK(res.result() == Status::bad_request);
  CHECK(res.body().find("/tile_costs") != std::string::npos);
}
