// A finished one-shot collector telling its workers before it stops (collector/linger.h, stop.h):
// the pure linger tracker, the lease answer's kFinishedHeader, and the collector through its
// handler with the loop on a thread of its own and time on a ManualClock (collector_testing.h).
// Nothing here waits for real time to pass: the linger ends because every worker was told, or
// because the test moves the clock past its bound.
#include <chrono>
#include <future>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/use_future.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/linger.h"
#include "collector/workers.h"
#include "collector_testing.h"
#include "eventually.h"
#include "protocol/worker_messages.h"

using namespace dtraced::testing;
namespace collector = dtraced::collector;

namespace {

// `req` answered by the collector (as Harness::call does, with the request's own headers).
Response send(Harness& h, Request req) {
  if (!h.loop.valid()) return h.collector.handle_sync(std::move(req));
  auto answer =
      boost::asio::co_spawn(h.collector.io_context(), h.collector.handle(std::move(req)), boost::asio::use_future);
  REQUIRE(answer.wait_for(kBound) == std::future_status::ready);
  return answer.get();
}

struct LeaseAnswer {
  std::optional<protocol::Lease> lease;
  std::string finished_header;  // "" when absent
};

LeaseAnswer lease_as(Harness& h, std::string_view name) {
  const Response res = h.call(Verb::post, "/v1/lease", fmt::format(R"({{"worker": "{}", "threads": 1}})", name));
  REQUIRE(res.result() == Status::ok);
  auto reply = protocol::decode_lease_reply(res.body());
  REQUIRE(reply.ok());
  LeaseAnswer answer;
  if (auto* l = std::get_if<protocol::Lease>(&reply.value())) answer.lease = *l;
  const auto it =
      res.find(boost::beast::string_view(protocol::kFinishedHeader.data(), protocol::kFinishedHeader.size()));
  if (it != res.end()) answer.finished_header = std::string(it->value());
  return answer;
}

// Stores the leased tile as worker `name` sends it.
void put_as(Harness& h, std::string_view name, const protocol::Lease& l) {
  Request req = make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l.job, l.tile), payload(l.job, l.tile, l.rect));
  req.set(protocol::kWorkerHeader, name);
  REQUIRE(send(h, std::move(req)).result() == Status::ok);
}

// Leases and stores every tile as worker `name`; every answer before the end says nothing of it.
void render_all_as(Harness& h, std::string_view name) {
  for (;;) {
    const LeaseAnswer a = lease_as(h, name);
    CHECK(a.finished_header.empty());
    if (!a.lease) break;
    put_as(h, name, *a.lease);
  }
}

coll::CollectorConfig small_one_shot(const TempDir& dir, bool exit_when_done) {
  coll::CollectorConfig config = one_shot_config(dir);
  config.one_shot->overrides.width = 16;
  config.one_shot->overrides.tile_size = 8;  // 2 x 3 tiles
  config.exit_when_done = exit_when_done;
  return config;
}

bool exited(Harness& h) { return h.loop.wait_for(0s) == std::future_status::ready; }

// Moves the clock past the linger bound until run() returns; its exit code.
int exit_after_linger(Harness& h) {
  REQUIRE(eventually([&] {
    h.clock.advance(collector::linger_bound(h.config.queue));
    return exited(h);
  }));
  return h.loop.get();
}

}  // namespace

TEST_CASE("the finished header reads 1 as finished, 0 as not, and nothing else", "[protocol][exit_when_done]") {
  CHECK(protocol::parse_finished_header("1") == true);
  CHECK(protocol::parse_finished_header("0") == false);
  for (const std::string_view bad : {"", "true", "yes", "01", " 1", "1 ", "2", "-1"}) {
    INFO(bad);
    CHECK_FALSE(protocol::parse_finished_header(bad));
  }
}

TEST_CASE("a linger waits for every worker it was to tell, or for its deadline", "[collector][exit_when_done]") {
  const collector::WorkerId a{"a", "192.0.2.1"}, b{"b", "192.0.2.2"}, stranger{"c", "192.0.2.3"};
  const collector::TimePoint t0 = collector::TimePoint{} + 1h;
  collector::FinishedLinger linger({a, b}, t0 + 5s);
  CHECK_FALSE(linger.over(t0));
  linger.told(stranger);  // not waited for: changes nothing
  linger.told(a);
  CHECK(linger.untold() == 1);
  CHECK_FALSE(linger.over(t0 + 4s));
  CHECK(linger.over(t0 + 5s));  // b never asked again
  linger.told(b);
  CHECK(linger.everyone_told());
  CHECK(linger.over(t0));

  CHECK(collector::FinishedLinger({}, t0 + 5s).over(t0));  // nobody to wait for
}

TEST_CASE("the linger bound covers the longest retry-after the idle workers were given",
          "[collector][exit_when_done]") {
  coll::QueueConfig queue;  // max_retry_after 5 s (--max-idle-wait-ms)
  CHECK(collector::linger_bound(queue) == 10s);
  queue.max_retry_after = 500ms;
  CHECK(collector::linger_bound(queue) == collector::kFinishedLinger);
  queue.max_retry_after = 60s;
  CHECK(collector::linger_bound(queue) == 120s);
  // Whatever the ceiling, a worker told to wait it comes back (within 1.5 x, its jitter) before
  // the linger ends.
  for (const auto ms : {50, 500, 2000, 3333, 5000, 20000, 60000}) {
    queue.max_retry_after = std::chrono::milliseconds(ms);
    CHECK(collector::linger_bound(queue) >= queue.max_retry_after * 3 / 2);
  }
}

TEST_CASE("the workers to tell are those not quiet", "[collector][exit_when_done]") {
  collector::WorkerRegistry registry({.quiet_after = 60s, .forget_after = 1h, .max_workers = 16});
  const collector::TimePoint t0 = collector::TimePoint{} + 1h;
  registry.on_lease({"old", ""}, "", 1, t0);
  registry.on_lease({"recent", ""}, "", 1, t0 + 50s);
  registry.on_tile({"uploader", ""}, collector::TileOutcome::kStored, 1, t0 + 70s);
  const auto to_tell = collector::workers_to_tell(registry, t0 + 80s);
  CHECK(to_tell == std::vector<collector::WorkerId>{{"uploader", ""}, {"recent", ""}});
}

TEST_CASE("a finished one-shot collector answers finished until each recent worker was told, then exits 0",
          "[collector][service][exit_when_done]") {
  TempDir dir;
  Harness h(small_one_shot(dir, /*exit_when_done=*/true));
  h.start_loop();
  const LeaseAnswer first = lease_as(h, "b");  // b renders one tile, then a the rest
  REQUIRE(first.lease);
  put_as(h, "b", *first.lease);
  render_all_as(h, "a");
  // Once the image is written, lease answers say the collector has finished.
  REQUIRE(eventually([&] { return lease_as(h, "a").finished_header == "1"; }));
  CHECK(fs::exists(dir.path() / "out" / "shot.png"));
  const LeaseAnswer again = lease_as(h, "a");
  CHECK_FALSE(again.lease);
  CHECK(again.finished_header == "1");
  CHECK_FALSE(exited(h));  // b has not been told, and the clock has not moved
  CHECK(lease_as(h, "b").finished_header == "1");
  REQUIRE(h.loop.wait_for(kBound) == std::future_status::ready);
  CHECK(h.loop.get() == 0);
}

TEST_CASE("a cancelled one-shot job lingers too, and a worker that never asks again holds it only until the bound",
          "[collector][service][exit_when_done]") {
  TempDir dir;
  Harness h(small_one_shot(dir, /*exit_when_done=*/true));
  h.start_loop();
  REQUIRE(lease_as(h, "a").lease);
  REQUIRE(lease_as(h, "b").lease);
  REQUIRE(h.call(Verb::post, "/v1/jobs/1/cancel").result() == Status::ok);
  CHECK(lease_as(h, "a").finished_header == "1");
  CHECK_FALSE(exited(h));  // b is still to be told
  CHECK(exit_after_linger(h) == 1);
}

TEST_CASE("a finished one-shot collector that knows no worker exits at once", "[collector][service][exit_when_done]") {
  TempDir dir;
  Harness h(small_one_shot(dir, /*exit_when_done=*/true));
  h.start_loop();
  REQUIRE(h.call(Verb::post, "/v1/jobs/1/cancel").result() == Status::ok);
  // No clock moved: nothing to linger for.
  REQUIRE(h.loop.wait_for(kBound) == std::future_status::ready);
  CHECK(h.loop.get() == 1);
}

TEST_CASE("a collector that will not exit never says finished, with no work left or none yet",
          "[collector][service][exit_when_done]") {
  TempDir dir;
  SECTION("a long-running collector whose jobs are all done") {
    Harness h(dir);
    CHECK(lease_as(h, "a").finished_header.empty());  // nothing submitted yet
    const std::uint64_t job = h.submit();
    for (const protocol::Lease& l : h.lease_all()) h.put_ok(l);
    CHECK(h.status(job).state == protocol::JobState::kDone);
    const LeaseAnswer a = lease_as(h, "a");
    CHECK_FALSE(a.lease);
    CHECK(a.finished_header.empty());
  }
  SECTION("a one-shot collector without exit_when_done whose job is done") {
    Harness h(small_one_shot(dir, /*exit_when_done=*/false));
    render_all_as(h, "a");
    CHECK(h.status(1).state == protocol::JobState::kDone);
    CHECK(lease_as(h, "a").finished_header.empty());
  }
}
