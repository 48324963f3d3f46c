// Managing jobs through the collector's handler, without sockets (collector_testing.h): the
// ordered, compare-and-set job-state writes (a cancellation answered while a tile is stored must
// stay cancelled), and the management endpoints.
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

// ---- priority ---------------------------------------------------------------------------------

TEST_CASE("a priority changed later reorders the queue and survives a restart", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t first = h.submit(R"(, "width": 8, "height": 8)");
  const std::uint64_t second = h.submit(R"(, "width": 8, "height": 8)");
  const Response res = h.call(Verb::post, fmt::format("/v1/jobs/{}/priority", second), R"({"priority": 7})");
  REQUIRE(res.result() == Status::ok);
  CHECK(protocol::decode_job_status(res.body()).value().priority == 7);
  CHECK(stored_state(h.config).jobs.at(1).priority == 7);
  auto leases = h.lease_all();
  REQUIRE(leases.size() == 2);
  CHECK(leases[0].job == second);
  CHECK(leases[1].job == first);

  h.collector.stop();
  h.collector.run();
  auto again = must_create(h.config);
  require_ok(again->open());
  const Response status = again->handle_sync(make(Verb::get, fmt::format("/v1/jobs/{}", second)));
  CHECK(protocol::decode_job_status(status.body()).value().priority == 7);
}

TEST_CASE("bad priority requests get 400, 404 or 409 naming the problem, and change nothing", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit(R"(, "width": 8, "height": 8)");
  const std::string target = fmt::format("/v1/jobs/{}/priority", job);
  struct Case {
    std::string body;
    std::string field;
  };
  for (const Case& bad : {Case{"", ""}, Case{"{}", "/priority"}, Case{R"({"priority": 1.5})", "/priority"},
                          Case{R"({"priority": 1001})", "/priority"}, Case{R"({"priority": "3"})", "/priority"},
                          Case{R"({"priority": 3, "prio": 4})", "/prio"}}) {
    INFO(bad.body);
    const Response res = h.call(Verb::post, target, bad.body);
    CHECK(res.result() == Status::bad_request);
    if (!bad.field.empty()) CHECK(error_of(res).field == bad.field);
  }
  CHECK(h.call(Verb::post, "/v1/jobs/99/priority", R"({"priority": 1})").result() == Status::not_found);
  CHECK(h.call(Verb::get, target).result() == Status::method_not_allowed);
  CHECK(stored_state(h.config).jobs.at(0).priority == 0);

  for (const auto& l : h.lease_all()) h.put_ok(l);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  const Response done = h.call(Verb::post, target, R"({"priority": 1})");
  CHECK(done.result() == Status::conflict);
  CHECK_THAT(error_of(done).error, Catch::Contains("is done"));
}

// ---- requeue ----------------------------------------------------------------------------------

TEST_CASE("a requeued job keeps its stored tiles, leases only the others, and finishes", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const protocol::Lease a = *h.lease();
  REQUIRE(h.put_ok(a) == protocol::SubmitResult::kStored);
  REQUIRE(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job)).result() == Status::ok);

  const Response res = h.call(Verb::post, fmt::format("/v1/jobs/{}/requeue", job));
  REQUIRE(res.result() == Status::ok);
  const protocol::JobStatus requeued = protocol::decode_job_status(res.body()).value();
  CHECK(requeued.state == protocol::JobState::kRendering);
  CHECK(requeued.tiles_done == 1);
  CHECK(stored_state(h.config).jobs.at(0).state == "queued");

  const auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - 1);
  for (const auto& l : leases) {
    CHECK(l.tile != a.tile);
    CHECK(h.put_ok(l) == protocol::SubmitResult::kStored);
  }
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  CHECK(stored_state(h.config).jobs.at(0).state == "done");
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all_tiles()).rgb);
}

TEST_CASE("requeue refuses a job that is not cancelled with 409, and an unknown one with 404", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const Response queued = h.call(Verb::post, fmt::format("/v1/jobs/{}/requeue", job));
  CHECK(queued.result() == Status::conflict);
  CHECK_THAT(error_of(queued).error, Catch::Contains("is queued; only a cancelled job can be requeued"));
  CHECK(h.call(Verb::post, "/v1/jobs/42/requeue").result() == Status::not_found);
  CHECK(h.call(Verb::post, fmt::format("/v1/jobs/{}/requeue?now=1", job)).result() == Status::bad_request);
  CHECK(stored_state(h.config).jobs.at(0).state == "queued");
}

// ---- listing ----------------------------------------------------------------------------------

TEST_CASE("the job list filters by state and keeps the newest N", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t a = h.submit();
  const std::uint64_t b = h.submit();
  const std::uint64_t c = h.submit();
  REQUIRE(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", b)).result() == Status::ok);
  auto ids = [&h](const std::string& query) {
    const Response res = h.call(Verb::get, "/v1/jobs" + query);
    REQUIRE(res.result() == Status::ok);
    std::vector<std::uint64_t> out;
    const auto list = protocol::decode_job_list(res.body());
    REQUIRE(list.ok());
    for (const auto& s : list.value().jobs) out.push_back(s.id);
    return out;
  };
  CHECK(ids("") == std::vector<std::uint64_t>{a, b, c});
  CHECK(ids("?state=queued") == std::vector<std::uint64_t>{a, c});
  CHECK(ids("?state=cancelled") == std::vector<std::uint64_t>{b});
  CHECK(ids("?limit=2") == std::vector<std::uint64_t>{b, c});
  CHECK(ids("?state=queued&limit=1") == std::vector<std::uint64_t>{c});
  CHECK(ids("?state=done").empty());

  struct Case {
    std::string query;
    std::string field;
  };
  for (const Case& bad : {Case{"?state=suspended", "/state"}, Case{"?limit=0", "/limit"}, Case{"?limit=-1", "/limit"},
                          Case{"?limit=10001", "/limit"}, Case{"?limit=1.5", "/limit"}, Case{"?limit=", "/limit"},
                          Case{"?state=done&state=queued", "/state"}, Case{"?sort=id", "/sort"}}) {
    INFO(bad.query);
    const Response res = h.call(Verb::get, "/v1/jobs" + bad.query);
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).field == bad.field);
  }
}
