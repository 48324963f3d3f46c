// WorkQueue::focus with a fake clock: a region's tiles go to the front of their job's queue, in
// the order given, and nothing but the order changes.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <set>
#include <vector>

#include <catch2/catch.hpp>

#include "collector/queue.h"

namespace {

using namespace std::chrono_literals;
using namespace dtraced::collector;

const TimePoint t0 = TimePoint{} + 1000h;

LeaseGrant must_lease(WorkQueue& q, TimePoint now) {
  const LeaseResult r = q.lease(now);
  REQUIRE(r.grant.has_value());
  return *r.grant;
}

}  // namespace

TEST_CASE("focus: the next leases are exactly the focused tiles, in the order given", "[queue][focus]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 16));
  const std::vector<TileIndex> region{9, 5, 10, 6};
  CHECK(q.focus(1, region) == 4);
  for (const TileIndex t : region) CHECK(must_lease(q, t0) == LeaseGrant{1, t});
  // Then the rest, in their old order.
  for (const TileIndex t : {0, 1, 2, 3, 4, 7, 8, 11}) CHECK(must_lease(q, t0) == LeaseGrant{1, TileIndex(t)});
}

TEST_CASE("focus: stored, leased, skipped and repeated tiles are not moved", "[queue][focus]") {
  WorkQueue q;
  const std::vector<TileIndex> skipped{3};
  REQUIRE(q.add_job(1, 0, 8, std::vector<TileIndex>{}, skipped));
  CHECK(must_lease(q, t0) == LeaseGrant{1, 0});  // leased, outstanding
  CHECK(must_lease(q, t0) == LeaseGrant{1, 1});
  CHECK(q.complete(1, 1, t0 + 1ms) == CompleteResult::kStored);  // stored
  const std::vector<TileIndex> region{7, 0, 1, 3, 7, 6, 99};
  CHECK(q.focus(1, region) == 2);  // 7 and 6 only
  CHECK(q.has_lease(1, 0, t0 + 1ms));
  CHECK_FALSE(q.has_lease(1, 7, t0 + 1ms));
  CHECK(must_lease(q, t0 + 1ms) == LeaseGrant{1, 7});
  CHECK(must_lease(q, t0 + 1ms) == LeaseGrant{1, 6});
  CHECK(must_lease(q, t0 + 1ms) == LeaseGrant{1, 2});
  CHECK(q.focus(1, region) == 0);  // everything named is leased or stored now
  CHECK(q.focus(2, region) == 0);  // unknown job
}

TEST_CASE("focus: other jobs keep their order and a focused job still completes", "[queue][focus]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 5, 4));  // higher priority: served first whatever job 2's order
  REQUIRE(q.add_job(2, 0, 6));
  const std::vector<TileIndex> region{5, 4};
  CHECK(q.focus(2, region) == 2);
  for (TileIndex t = 0; t < 4; ++t) CHECK(must_lease(q, t0) == LeaseGrant{1, t});
  std::vector<TileIndex> order;
  for (int i = 0; i < 6; ++i) order.push_back(must_lease(q, t0).tile);
  CHECK(order == std::vector<TileIndex>{5, 4, 0, 1, 2, 3});
  for (TileIndex t = 0; t < 4; ++t) CHECK(q.complete(1, t, t0 + 1s) == CompleteResult::kStored);
  for (const TileIndex t : order) CHECK(q.complete(2, t, t0 + 1s) == CompleteResult::kStored);
  CHECK(q.is_done(1));
  CHECK(q.is_done(2));
  CHECK(q.focus(2, region) == 0);  // done
  CHECK(q.stats().stored == 10);
  CHECK(q.stats().reoffers == 0);
}
