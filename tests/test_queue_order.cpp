// Tests for the cost order of the work queue: WorkQueue::add_job's explicit lease order (and its
// validation), collector::lease_order (descending cost per frame, ties in row order, frames in
// order), the costs' store blob, and that restored, skipped and released tiles keep to the order.
#include <chrono>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include <catch2/catch.hpp>

#include "collector/jobs.h"
#include "collector/queue.h"

namespace {

using namespace std::chrono_literals;
using namespace dtraced::collector;

const TimePoint t0 = TimePoint{} + 1000h;

// Every tile the queue hands out now, in order, until it has nothing eligible.
std::vector<TileIndex> drain(WorkQueue& q, TimePoint now, std::string_view holder = {}) {
  std::vector<TileIndex> out;
  for (;;) {
    const LeaseResult r = q.lease(now, holder);
    if (!r.grant) return out;
    out.push_back(r.grant->tile);
  }
}

}  // namespace

TEST_CASE("lease_order sorts each frame by descending cost, ties in row order", "[queue][cost]") {
  const std::vector<float> costs = {1, 5, 3, 5, 0};
  CHECK(lease_order(costs, 1) == std::vector<TileIndex>{1, 3, 2, 0, 4});
  // Frames stay in order, each in the same order of its own indices.
  CHECK(lease_order(costs, 2) == std::vector<TileIndex>{1, 3, 2, 0, 4, 6, 8, 7, 5, 9});
  CHECK(lease_order({}, 3).empty());
  // All equal: row order.
  const std::vector<float> flat(4, 2.0f);
  CHECK(lease_order(flat, 1) == std::vector<TileIndex>{0, 1, 2, 3});
}

TEST_CASE("a job added with an order leases in that order", "[queue][cost]") {
  WorkQueue q;
  const std::vector<TileIndex> order = {3, 0, 2, 1};
  REQUIRE(q.add_job(1, 0, 4, {}, {}, order));
  CHECK(drain(q, t0) == order);
  // Re-offers after the bound come round in the same order.
  CHECK(drain(q, t0 + 2s) == order);
}

TEST_CASE("an order that is not a permutation of the tiles is refused", "[queue][cost]") {
  WorkQueue q;
  const std::vector<TileIndex> short_order = {0, 1, 2};
  const std::vector<TileIndex> repeated = {0, 1, 1, 3};
  const std::vector<TileIndex> out_of_range = {0, 1, 2, 4};
  CHECK_FALSE(q.add_job(1, 0, 4, {}, {}, short_order));
  CHECK_FALSE(q.add_job(1, 0, 4, {}, {}, repeated));
  CHECK_FALSE(q.add_job(1, 0, 4, {}, {}, out_of_range));
  CHECK_FALSE(q.progress(1, t0).has_value());  // nothing added
  const std::vector<TileIndex> good = {1, 0, 3, 2};
  CHECK(q.add_job(1, 0, 4, {}, {}, good));
}

TEST_CASE("a restored job with an order leases its unfinished tiles in that order", "[queue][cost]") {
  // What a restarted collector does: the same order (from the stored costs), stored and skipped
  // tiles passed over.
  WorkQueue q;
  const std::vector<TileIndex> order = {5, 2, 4, 0, 1, 3};
  const std::vector<TileIndex> stored = {2, 1};
  const std::vector<TileIndex> skipped = {4};
  REQUIRE(q.add_job(7, 0, 6, stored, skipped, order));
  CHECK(drain(q, t0) == std::vector<TileIndex>{5, 0, 3});
  CHECK(q.progress(7, t0)->tiles_total == 5);
  CHECK(q.progress(7, t0)->tiles_done == 2);
}

TEST_CASE("released tiles go first, in the cost order", "[queue][cost]") {
  WorkQueue q;
  const std::vector<TileIndex> order = {4, 3, 2, 1, 0};
  REQUIRE(q.add_job(1, 0, 5, {}, {}, order));
  CHECK(q.lease(t0, "a").grant->tile == 4);
  CHECK(q.lease(t0, "b").grant->tile == 3);
  CHECK(q.lease(t0, "a").grant->tile == 2);
  CHECK(q.release_holder("a") == 2);
  CHECK(drain(q, t0) == std::vector<TileIndex>{4, 2, 1, 0});
}

TEST_CASE("queue_job leases by cost when the record has costs that fit, else in row order", "[queue][cost]") {
  JobRecord rec;
  rec.id = 3;
  rec.settings.width = 40;
  rec.settings.height = 20;
  rec.tile_size = 10;  // 4 x 2 tiles
  REQUIRE(init_frames(rec));
  rec.tile_costs = {0, 9, 1, 1, 8, 0, 0, 7};
  {
    WorkQueue q;
    REQUIRE(queue_job(q, rec));
    CHECK(drain(q, t0) == std::vector<TileIndex>{1, 4, 7, 2, 3, 0, 5, 6});
  }
  {
    JobRecord wrong = rec;
    wrong.tile_costs.pop_back();  // not one per tile: ignored
    WorkQueue q;
    REQUIRE(queue_job(q, wrong));
    CHECK(drain(q, t0) == std::vector<TileIndex>{0, 1, 2, 3, 4, 5, 6, 7});
  }
  {
    JobRecord none = rec;
    none.tile_costs.clear();
    WorkQueue q;
    REQUIRE(queue_job(q, none));
    CHECK(drain(q, t0) == std::vector<TileIndex>{0, 1, 2, 3, 4, 5, 6, 7});
  }
}

TEST_CASE("a sequence leases frame by frame, each frame by cost", "[queue][cost]") {
  JobRecord rec;
  rec.id = 4;
  rec.settings.width = 20;
  rec.settings.height = 10;
  rec.settings.frames = dtraced::scene::FrameRange{1, 3, 1};
  rec.tile_size = 10;  // 2 tiles a frame, 3 frames
  REQUIRE(init_frames(rec));
  REQUIRE(rec.tile_indices == 6);
  rec.tile_costs = {1, 2};
  WorkQueue q;
  REQUIRE(queue_job(q, rec));
  CHECK(drain(q, t0) == std::vector<TileIndex>{1, 0, 3, 2, 5, 4});
}

TEST_CASE("tile costs round-trip through their store blob and bad blobs are refused", "[queue][cost]") {
  const std::vector<float> costs = {0.0f, 1.5f, 3e20f, 7.0f};
  const dtraced::store::Blob blob = costs_to_blob(costs);
  CHECK(blob.size() == 16);
  const auto back = blob_to_costs(blob, 4);
  REQUIRE(back.has_value());
  CHECK(*back == costs);
  CHECK_FALSE(blob_to_costs(blob, 3).has_value());  // not one per tile
  dtraced::store::Blob odd = blob;
  odd.pop_back();
  CHECK_FALSE(blob_to_costs(odd, 4).has_value());
  const std::vector<float> negative = {1.0f, -1.0f};
  CHECK_FALSE(blob_to_costs(costs_to_blob(negative), 2).has_value());
  const std::vector<float> nan = {std::numeric_limits<float>::quiet_NaN(), 1.0f};
  CHECK_FALSE(blob_to_costs(costs_to_blob(nan), 2).has_value());
  CHECK(costs_to_blob({}).empty());
}
