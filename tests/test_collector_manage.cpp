// Managing jobs through the collector's handler, without sockets (collector_testing.h): the
// ordered, compare-and-set job-state writes (a cancellation answered while a tile is stored must
// stay cancelled).
#include <cstdint>
#include <exception>
#include <string>
#include <string_view>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/lifecycle.h"
#include "collector_testing.h"

using namespace dtraced::testing;

namespace {

// Starts a request on the collector's loop without running it; `answers` gets the answer.
void start(Harness& h, Verb method, std::string target, std::string body, std::vector<Response>& answers) {
  boost::asio::co_spawn(h.collector.io_context(), h.collector.handle(make(method, std::move(target), std::move(body))),
                        [&answers](std::exception_ptr error, Response res) {
                          REQUIRE_FALSE(error);
                          answers.push_back(std::move(res));
                        });
}

// A job's state as a restarted collector reports it.
protocol::JobState state_after_restart(Harness& h, std::uint64_t job) {
  h.collector.stop();
  h.collector.run();
  auto again = must_create(h.config);
  require_ok(again->open());
  const Response res = again->handle_sync(make(Verb::get, fmt::format("/v1/jobs/{}", job)));
  REQUIRE(res.result() == Status::ok);
  return protocol::decode_job_status(res.body()).value().state;
}

}  // namespace

// ---- ordered state writes -------------------------------------------------------------------------

TEST_CASE("a state write never undoes a terminal state, except done after an unanswered cancel",
          "[collector][manage][store]") {
  TempDir dir;
  {
    Harness h(dir);
    h.submit();
    h.submit();
  }
  auto opened = store::Store::open((dir.path() / "state").string(), {.verify_integrity = false});
  REQUIRE(opened.ok());
  store::Store& s = opened.value();
  using coll::StateWrite;
  auto record = [&s](std::int64_t id, StateWrite w) {
    auto r = coll::record_state(s, static_cast<coll::JobId>(id), w, 1700000000);
    if (!r) FAIL(r.error().message);
    return r.value();
  };
  CHECK(record(1, StateWrite::kRendering).changed);
  CHECK(record(1, StateWrite::kCancelled).changed);
  // The late "rendering" of the race: refused, and the answered "cancelled" stays.
  const store::StateChange late = record(1, StateWrite::kRendering);
  CHECK_FALSE(late.changed);
  CHECK(late.state == "cancelled");
  CHECK_FALSE(record(1, StateWrite::kCancelled).changed);
  CHECK(record(1, StateWrite::kRequeued).changed);
  CHECK(s.get_job(1).value()->state == "queued");

  CHECK(record(2, StateWrite::kCancelled).changed);
  CHECK(record(2, StateWrite::kDone).changed);
  for (const StateWrite w : {StateWrite::kRendering, StateWrite::kCancelled, StateWrite::kRequeued}) {
    const store::StateChange after_done = record(2, w);
    CHECK_FALSE(after_done.changed);
    CHECK(after_done.state == "done");
  }
  CHECK_FALSE(s.change_job_state(99, coll::source_states(StateWrite::kDone), "done", 0).ok());
  CHECK_FALSE(s.change_job_state(1, {}, "done", 0).ok());
}

TEST_CASE("a cancellation answered while the job's first tile is stored stays cancelled after a restart",
          "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const protocol::Lease l = *h.lease();
  // Both start before the loop runs: the tile's commit is queued with the store writer first, the
  // cancellation's write second. The tile's answer, handled first, then posts the job's
  // "rendering" write, which the writer runs after the cancellation's.
  std::vector<Response> tile_answer;
  std::vector<Response> cancel_answer;
  start(h, Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, l.tile), payload(job, l.tile, l.rect), tile_answer);
  start(h, Verb::post, fmt::format("/v1/jobs/{}/cancel", job), {}, cancel_answer);
  h.collector.run_until_idle();
  REQUIRE(tile_answer.size() == 1);
  REQUIRE(cancel_answer.size() == 1);
  CHECK(protocol::decode_submit_result(tile_answer[0].body()).value() == protocol::SubmitResult::kStored);
  REQUIRE(cancel_answer[0].result() == Status::ok);
  REQUIRE(protocol::decode_job_status(cancel_answer[0].body()).value().state == protocol::JobState::kCancelled);

  const StoredState stored = stored_state(h.config);
  CHECK(stored.jobs.at(0).state == "cancelled");
  CHECK(stored.tiles.at(1).size() == 1);
  CHECK(state_after_restart(h, job) == protocol::JobState::kCancelled);
}
