// Tests for dtraced::collector::WorkQueue with a fake clock: rotation, the re-offer bound and how
// it follows tile times, the copy cap, duplicates, priorities, cancel, restore, retry hints, and a
// simulated farm with a dead and a slow worker.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <optional>
#include <set>
#include <vector>

#include <catch2/catch.hpp>

#include "collector/queue.h"

namespace {

using namespace std::chrono_literals;
using namespace dtraced::collector;

// An arbitrary origin for the fake clock; only differences matter.
const TimePoint t0 = TimePoint{} + 1000h;

LeaseGrant must_lease(WorkQueue& q, TimePoint now) {
  const LeaseResult r = q.lease(now);
  REQUIRE(r.grant.has_value());
  CHECK(r.retry_after == 0ms);
  return *r.grant;
}

void must_not_lease(WorkQueue& q, TimePoint now) {
  const LeaseResult r = q.lease(now);
  if (r.grant) INFO("got job " << r.grant->job << " tile " << r.grant->tile);
  REQUIRE_FALSE(r.grant.has_value());
}

std::uint32_t outstanding(const WorkQueue& q, JobId job, TimePoint now) {
  const auto p = q.progress(job, now);
  REQUIRE(p.has_value());
  return p->leases_outstanding;
}

}  // namespace

TEST_CASE("tiles are leased front to back and rotate", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 4));
  for (TileIndex t = 0; t < 4; ++t) CHECK(must_lease(q, t0) == LeaseGrant{1, t});
  must_not_lease(q, t0 + 1s);

  // Once the bound has passed, the circle comes round again in the same order, minus stored tiles.
  CHECK(q.complete(1, 1, t0 + 100ms) == CompleteResult::kStored);
  REQUIRE(q.reoffer_bound(1) == 2s);
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 0});
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 2});
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 3});
  must_not_lease(q, t0 + 2s);
  CHECK(q.stats().leases == 7);
  CHECK(q.stats().reoffers == 3);
}

TEST_CASE("a leased tile is not re-offered before the bound, and is after it", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 1));
  REQUIRE(q.reoffer_bound(1) == 2s);  // no tile times yet: the floor
  must_lease(q, t0);
  must_not_lease(q, t0 + 1s);
  must_not_lease(q, t0 + 2s - 1ns);
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 0});
  // The bound runs from the newest lease.
  must_not_lease(q, t0 + 3999ms);
  CHECK(must_lease(q, t0 + 4s) == LeaseGrant{1, 0});
}

TEST_CASE("never more than max_copies leases of a tile are outstanding", "[queue]") {
  QueueConfig config;
  config.max_copies = 3;
  config.copy_expiry_factor = 10;  // leases stop counting after 10 x 2 s
  WorkQueue q(config);
  REQUIRE(q.add_job(1, 0, 1));

  must_lease(q, t0);
  must_lease(q, t0 + 2s);
  must_lease(q, t0 + 4s);
  CHECK(outstanding(q, 1, t0 + 4s) == 3);
  // Bound passed, but the cap holds until the first lease expires at t0 + 20 s.
  must_not_lease(q, t0 + 6s);
  must_not_lease(q, t0 + 20s - 1ns);
  CHECK(must_lease(q, t0 + 20s) == LeaseGrant{1, 0});
  CHECK(outstanding(q, 1, t0 + 20s) == 3);

  // Polled every 100 ms for a minute, the tile is never out more than 3 times at once.
  WorkQueue polled(config);
  REQUIRE(polled.add_job(1, 0, 1));
  std::uint32_t grants = 0;
  for (TimePoint now = t0; now < t0 + 60s; now += 100ms) {
    if (polled.lease(now).grant) ++grants;
    CHECK(outstanding(polled, 1, now) <= 3);
  }
  // Leases at 0, 2, 4 s; then one each time an old one expires: 20, 22, 24, 40, 42, 44 s.
  CHECK(grants == 9);
}

TEST_CASE("max_copies 1 never duplicates until a lease expires", "[queue]") {
  QueueConfig config;
  config.max_copies = 1;
  config.copy_expiry_factor = 5;
  WorkQueue q(config);
  REQUIRE(q.add_job(1, 0, 1));
  must_lease(q, t0);
  must_not_lease(q, t0 + 9999ms);
  must_lease(q, t0 + 10s);
}

TEST_CASE("the re-offer bound follows observed tile times", "[queue]") {
  WorkQueue q;

  SECTION("fast tiles keep the floor") {
    REQUIRE(q.add_job(1, 0, 100));
    for (int i = 0; i < 100; ++i) {
      const TimePoint now = t0 + i * 200ms;
      const LeaseGrant g = must_lease(q, now);
      CHECK(q.complete(g.job, g.tile, now + 100ms) == CompleteResult::kStored);
    }
    CHECK(q.is_done(1));
    CHECK(q.reoffer_bound(1) == 2s);
  }

  SECTION("slow tiles raise it to factor x p90") {
    REQUIRE(q.add_job(1, 0, 51));
    // Five tiles each of 1 s, 2 s, ..., 10 s, run one at a time: p90 of the 50 is 9 s.
    TimePoint now = t0;
    for (int seconds = 1; seconds <= 10; ++seconds) {
      for (int i = 0; i < 5; ++i) {
        const LeaseGrant g = must_lease(q, now);
        now += std::chrono::seconds(seconds);
        CHECK(q.complete(g.job, g.tile, now) == CompleteResult::kStored);
      }
    }
    CHECK(q.reoffer_bound(1) == 27s);

    // A tile leased now is left alone for 27 s, where the floor would have re-offered it at 2 s.
    const LeaseGrant g = must_lease(q, now);
    must_not_lease(q, now + 26s);
    CHECK(must_lease(q, now + 27s) == g);
  }

  SECTION("the window forgets old times") {
    QueueConfig config;
    config.window_size = 8;
    WorkQueue w(config);
    REQUIRE(w.add_job(1, 0, 20));
    TimePoint now = t0;
    for (int i = 0; i < 8; ++i) {
      const LeaseGrant g = must_lease(w, now);
      now += 10s;
      w.complete(g.job, g.tile, now);
    }
    CHECK(w.reoffer_bound(1) == 30s);
    for (int i = 0; i < 8; ++i) {
      const LeaseGrant g = must_lease(w, now);
      now += 100ms;
      w.complete(g.job, g.tile, now);
    }
    CHECK(w.reoffer_bound(1) == 2s);
  }

  SECTION("a ceiling caps it") {
    QueueConfig config;
    config.reoffer_ceiling = 1min;
    config.copy_expiry_factor = 1000;  // the lease is still outstanding after half an hour
    WorkQueue w(config);
    REQUIRE(w.add_job(1, 0, 2));
    const LeaseGrant g = must_lease(w, t0);
    w.complete(g.job, g.tile, t0 + 30min);
    CHECK(w.reoffer_bound(1) == 1min);
  }

  SECTION("times are measured from the oldest outstanding lease") {
    REQUIRE(q.add_job(1, 0, 1));
    must_lease(q, t0);
    must_lease(q, t0 + 2s);             // re-offered at the floor
    q.complete(1, 0, t0 + 2s + 500ms);  // which copy answered is unknown: count 2.5 s, not 0.5 s
    CHECK(q.reoffer_bound(1) == 7500ms);
  }

  SECTION("a result with no known lease teaches nothing") {
    REQUIRE(q.add_job(1, 0, 3));
    CHECK(q.complete(1, 1, t0 + 1h) == CompleteResult::kStored);  // e.g. leased before a restart
    CHECK(q.reoffer_bound(1) == 2s);
    must_lease(q, t0);
    CHECK(q.complete(1, 0, t0 + 1h) == CompleteResult::kStored);  // its lease expired long ago
    CHECK(q.reoffer_bound(1) == 2s);
  }
}

TEST_CASE("duplicate results are already done", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 2));
  const LeaseGrant a = must_lease(q, t0);
  CHECK(q.tile_status(1, a.tile) == TileStatus::kPending);
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 1});
  CHECK(must_lease(q, t0 + 2s) == a);  // re-offered: two copies out

  CHECK(q.complete(1, a.tile, t0 + 3s) == CompleteResult::kStored);
  CHECK(q.tile_status(1, a.tile) == TileStatus::kStored);
  CHECK(q.complete(1, a.tile, t0 + 4s) == CompleteResult::kAlreadyDone);
  CHECK(q.complete(1, 1, t0 + 4s) == CompleteResult::kStored);
  CHECK(q.is_done(1));
  CHECK(q.complete(1, 1, t0 + 5s) == CompleteResult::kAlreadyDone);  // after the job is done, too
  CHECK(q.tile_status(1, 0) == TileStatus::kStored);
  CHECK(q.stats().duplicates == 2);
  CHECK(q.stats().stored == 2);
}

TEST_CASE("results for unknown, cancelled or removed jobs are job gone", "[queue]") {
  WorkQueue q;
  CHECK(q.complete(9, 0, t0) == CompleteResult::kJobGone);
  CHECK(q.tile_status(9, 0) == TileStatus::kJobGone);

  REQUIRE(q.add_job(1, 0, 3));
  CHECK(q.complete(1, 3, t0) == CompleteResult::kJobGone);  // no such tile
  CHECK(q.tile_status(1, 3) == TileStatus::kNoSuchTile);

  must_lease(q, t0);
  REQUIRE(q.cancel(1));
  CHECK(q.complete(1, 0, t0 + 1s) == CompleteResult::kJobGone);
  CHECK(q.tile_status(1, 0) == TileStatus::kJobGone);

  REQUIRE(q.add_job(2, 0, 1));
  const LeaseGrant g = must_lease(q, t0);
  REQUIRE(q.remove_job(2));
  CHECK(q.complete(g.job, g.tile, t0 + 1s) == CompleteResult::kJobGone);
}

TEST_CASE("higher priority first, then submission order", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 2));
  REQUIRE(q.add_job(2, 5, 2));
  REQUIRE(q.add_job(3, 5, 1));
  REQUIRE(q.add_job(4, -3, 1));
  const std::vector<LeaseGrant> expected = {{2, 0}, {2, 1}, {3, 0}, {1, 0}, {1, 1}, {4, 0}};
  for (const LeaseGrant& e : expected) CHECK(must_lease(q, t0) == e);
  must_not_lease(q, t0);

  // Once the bound passes, the high-priority job's tiles come first again.
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{2, 0});
}

TEST_CASE("a lower-priority job gets work while the higher one has only tiles out", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 10, 2));
  REQUIRE(q.add_job(2, 0, 100));
  CHECK(must_lease(q, t0) == LeaseGrant{1, 0});
  CHECK(must_lease(q, t0) == LeaseGrant{1, 1});
  CHECK(must_lease(q, t0 + 1s) == LeaseGrant{2, 0});
  CHECK(must_lease(q, t0 + 1s) == LeaseGrant{2, 1});
  // The high-priority job's re-offers pre-empt the low one as soon as they are due.
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{1, 0});
  CHECK(q.complete(1, 1, t0 + 2s) == CompleteResult::kStored);
  CHECK(must_lease(q, t0 + 2s) == LeaseGrant{2, 2});
}

TEST_CASE("cancel removes a job's work", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 10, 5));
  REQUIRE(q.add_job(2, 0, 1));
  must_lease(q, t0);
  REQUIRE(q.cancel(1));
  CHECK_FALSE(q.cancel(1));
  CHECK(must_lease(q, t0) == LeaseGrant{2, 0});
  must_not_lease(q, t0 + 1s);  // job 2's tile is the only work left, and it is out
  const auto p = q.progress(1, t0);
  REQUIRE(p.has_value());
  CHECK(p->cancelled);
  CHECK(p->tiles_total == 5);
  CHECK_FALSE(q.is_done(1));
  CHECK(q.stats().active_jobs == 1);

  REQUIRE(q.remove_job(1));
  CHECK_FALSE(q.progress(1, t0).has_value());
  CHECK_FALSE(q.remove_job(1));
  CHECK_FALSE(q.cancel(1));

  // A done job cannot be cancelled.
  REQUIRE(q.complete(2, 0, t0 + 1s) == CompleteResult::kStored);
  CHECK_FALSE(q.cancel(2));
  CHECK(q.is_done(2));
}

TEST_CASE("a paused job hands out nothing, accepts results, and resumes where it was", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 5, 3));
  REQUIRE(q.add_job(2, 0, 2));
  CHECK(must_lease(q, t0) == LeaseGrant{1, 0});
  REQUIRE(q.set_paused(1, true));
  CHECK_FALSE(q.set_paused(1, true));  // already paused
  CHECK(q.stats().active_jobs == 1);
  // The lower-priority job gets the work now.
  CHECK(must_lease(q, t0) == LeaseGrant{2, 0});
  CHECK(must_lease(q, t0) == LeaseGrant{2, 1});
  CHECK(q.complete(2, 0, t0 + 500ms) == CompleteResult::kStored);
  CHECK(q.complete(2, 1, t0 + 500ms) == CompleteResult::kStored);
  must_not_lease(q, t0 + 1h);  // job 1's tile out is not re-offered either
  // The tile out before the pause still completes.
  CHECK(q.complete(1, 0, t0 + 1s) == CompleteResult::kStored);
  CHECK(q.tile_status(1, 0) == TileStatus::kStored);
  CHECK_FALSE(q.is_done(1));
  REQUIRE(q.set_paused(1, false));
  CHECK(must_lease(q, t0 + 2h) == LeaseGrant{1, 1});
  CHECK(must_lease(q, t0 + 2h) == LeaseGrant{1, 2});
  // A paused job can be cancelled; a cancelled one is not paused or resumed.
  REQUIRE(q.add_job(3, 0, 2));
  REQUIRE(q.set_paused(3, true));
  REQUIRE(q.cancel(3));
  CHECK_FALSE(q.set_paused(3, false));
  CHECK_FALSE(q.set_paused(99, true));
}

TEST_CASE("the last tile out when a job was paused completes it", "[queue]") {
  WorkQueue q;
  REQUIRE(q.add_job(1, 0, 1));
  CHECK(must_lease(q, t0) == LeaseGrant{1, 0});
  REQUIRE(q.set_paused(1, true));
  CHECK(q.complete(1, 0, t0 + 1s) == CompleteResult::kStored);
  CHECK(q.is_done(1));
  REQUIRE(q.set_paused(1, false));  // resuming a done job puts nothing back in the order
  CHECK(q.stats().active_jobs == 0);
  must_not_lease(q, t0 + 2s);
}

TEST_CASE("restoring a job skips its stored tiles", "[queue]") {
  WorkQueue q;
  const std::vector<TileIndex> stored = {4, 0, 2, 2};
  REQUIRE(q.add_job(7, 0, 5, stored));
  const auto p = q.progress(7, t0);
  REQUIRE(p.has_value());
  CHECK(p->tiles_done == 3);
  CHECK(q.tile_status(7, 2) == TileStatus::kStored);
  CHECK(q.complete(7, 0, t0) == CompleteResult::kAlreadyDone);
  CHECK(must_lease(q, t0) == LeaseGrant{7, 1});
  CHECK(must_lease(q, t0) == LeaseGrant{7, 3});
  must_not_lease(q, t0);

  const std::vector<TileIndex> all = {0, 1};
  REQUIRE(q.add_job(8, 0, 2, all));
  CHECK(q.is_done(8));
  CHECK(q.stats().active_jobs == 1);

  CHECK_FALSE(q.add_job(7, 0, 5));  // id in use
  CHECK_FALSE(q.add_job(9, 0, 0));  // no tiles
  CHECK_FALSE(q.add_job(9, 0, dtraced::collector::kMaxQueueTiles + 1));
  const std::vector<TileIndex> out_of_range = {5};
  CHECK_FALSE(q.add_job(9, 0, 5, out_of_range));
  CHECK_FALSE(q.progress(9, t0).has_value());
}

TEST_CASE("with nothing eligible, lease suggests when to ask again", "[queue]") {
  // The clamping logic, with a longer upper bound than the default.
  QueueConfig slow;
  slow.max_retry_after = 5s;
  WorkQueue q(slow);
  CHECK(q.lease(t0).retry_after == 5s);  // no work at all: the longest wait

  REQUIRE(q.add_job(1, 0, 2));
  must_lease(q, t0);
  must_lease(q, t0 + 300ms);
  CHECK(q.lease(t0 + 500ms).retry_after == 1500ms);  // tile 0 is due at t0 + 2 s
  CHECK(q.lease(t0 + 1999ms).retry_after == 50ms);   // 1 ms away: the shortest wait
  CHECK(q.lease(t0 + 1999999999ns).retry_after == 50ms);

  // Rounded up to whole milliseconds, so the worker never comes back too early.
  QueueConfig config = slow;
  config.min_retry_after = 1ms;
  WorkQueue fine(config);
  REQUIRE(fine.add_job(1, 0, 1));
  must_lease(fine, t0);
  CHECK(fine.lease(t0 + 1s + 500us).retry_after == 1000ms);

  // At the copy cap, the wait runs to the oldest lease's expiry, clamped.
  WorkQueue capped(slow);
  REQUIRE(capped.add_job(1, 0, 1));
  must_lease(capped, t0);
  must_lease(capped, t0 + 2s);
  must_lease(capped, t0 + 4s);
  CHECK(capped.lease(t0 + 6s).retry_after == 5s);
  CHECK(capped.lease(t0 + 19s).retry_after == 1s);

  // The default ceiling is 5 s (--max-idle-wait-ms); the lease handler shortens it to 5 ms a
  // known worker, so a small farm's idle workers still come back within half a second.
  WorkQueue idle;
  CHECK(idle.lease(t0).retry_after == 5s);
}

TEST_CASE("queue configuration is checked", "[queue]") {
  CHECK(check_queue_config({}).empty());
  QueueConfig c;
  c.max_copies = 0;
  CHECK(check_queue_config(c) == dtraced::util::Errors{{"must be in [1, 16]", "max_copies"}});
  c = {};
  c.reoffer_floor = 0s;
  CHECK(check_queue_config(c).at(0).path == "reoffer_floor");
  c = {};
  c.reoffer_factor = 0.5;
  CHECK(check_queue_config(c).at(0).path == "reoffer_factor");
  c = {};
  c.min_retry_after = 10s;
  CHECK(check_queue_config(c).at(0).path == "min_retry_after");
  // Every problem at once.
  c.max_copies = 0;
  c.window_size = 0;
  CHECK(check_queue_config(c).size() == 3);
}

// ---- a simulated farm ----------------------------------------------------------------------

namespace {

struct SimWorker {
  Duration tile_time;             // how long each tile takes this worker
  std::size_t slots = 1;          // tiles held at once (threads, or a pipeline)
  std::optional<int> dies_after;  // leases taken before it dies (never completes, never asks again)

  struct Slot {
    LeaseGrant grant;
    TimePoint done_at;
  };
  std::vector<Slot> held;
  TimePoint next_ask{};
  int leases = 0;
};

struct SimResult {
  std::uint64_t leases = 0;
  std::uint64_t duplicates = 0;
  Duration elapsed{};
  bool done = false;
};

// Runs the workers against one job on a 1 ms tick until it is done (or 10 simulated minutes).
SimResult simulate(WorkQueue& q, JobId job, std::vector<SimWorker> workers) {
  SimResult r;
  for (TimePoint now = t0; now < t0 + 10min; now += 1ms) {
    for (SimWorker& w : workers) {
      const bool dead = w.dies_after && w.leases >= *w.dies_after;
      if (!dead) {
        std::erase_if(w.held, [&](const SimWorker::Slot& s) {
          if (s.done_at > now) return false;
          if (q.complete(s.grant.job, s.grant.tile, now) == CompleteResult::kAlreadyDone) ++r.duplicates;
          return true;
        });
      }
      while (!dead && w.held.size() < w.slots && now >= w.next_ask && !(w.dies_after && w.leases >= *w.dies_after)) {
        const LeaseResult l = q.lease(now);
        if (!l.grant) {
          w.next_ask = now + l.retry_after;
          break;
        }
        ++w.leases;
        w.held.push_back({*l.grant, now + w.tile_time});
      }
    }
    if (q.is_done(job)) {
      r.done = true;
      r.elapsed = now - t0;
      break;
    }
  }
  r.leases = q.stats().leases;
  return r;
}

}  // namespace

TEST_CASE("a farm with a dead worker finishes with bounded duplicate work", "[queue][sim]") {
  WorkQueue q;
  constexpr TileIndex kTiles = 100;
  REQUIRE(q.add_job(1, 0, kTiles));

  // Three live workers (one 4x slower than the others) and one that takes two tiles and dies.
  std::vector<SimWorker> workers(4);
  workers[0].tile_time = 100ms;
  workers[1].tile_time = 100ms;
  workers[2].tile_time = 400ms;
  workers[3].tile_time = 100ms;
  workers[3].slots = 2;
  workers[3].dies_after = 2;
  const SimResult r = simulate(q, 1, workers);

  REQUIRE(r.done);
  // Why kTiles + 2 at most: a tile is re-offered only once its newest lease is at least the bound
  // old, and the bound never drops below the 2 s floor. Every live worker returns a tile within
  // 400 ms, so no live worker's tile is ever re-offered; only the dead worker's two tiles are, and
  // each re-offer goes to a live worker that returns it well within the next 2 s.
  CHECK(r.leases <= kTiles + 2);
  CHECK(r.leases == kTiles + 2);
  CHECK(r.duplicates == 0);
  // The dead worker's tiles are covered at the tail, one bound after they were leased.
  CHECK(r.elapsed < 6s);
}

TEST_CASE("a straggler is covered at the tail without duplicating the whole tail", "[queue][sim]") {
  WorkQueue q;
  constexpr TileIndex kTiles = 100;
  REQUIRE(q.add_job(1, 0, kTiles));

  // Three fast workers with two threads each, and one that takes 6 s a tile: 60 times slower.
  std::vector<SimWorker> workers(4);
  for (int i = 0; i < 3; ++i) {
    workers[i].tile_time = 100ms;
    workers[i].slots = 2;
  }
  workers[3].tile_time = 6s;
  const SimResult r = simulate(q, 1, workers);

  REQUIRE(r.done);
  // The straggler holds one tile at a time and its tiles are the only ones ever older than the
  // bound (2 s floor; fast tiles take 100 ms). While never-leased tiles remain at the front it is
  // not even looked at; at the tail its current tile is re-offered once and finished by a fast
  // worker. So at most one duplicate lease per straggler tile, and it gets only a handful of
  // tiles in a job the others finish in about two seconds.
  CHECK(r.leases <= kTiles + 2);
  CHECK(r.elapsed < 3s);  // not waiting 6 s for the straggler
}

// WorkQueue::focus: a region's tiles go to the front of their job's queue, in the order given,
// and nothing but the order changes.

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
