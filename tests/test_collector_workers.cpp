// The worker registry (collector/workers.h) as a pure structure on a fake time line, the log
// throttle and histograms, then GET /v1/workers and /metrics through the collector's handler.
#include <chrono>
#include <regex>
#include <string>

#include <catch2/catch.hpp>

#include "collector/admission.h"
#include "collector/metrics.h"
#include "collector/workers.h"
#include "collector_testing.h"
#include "http/server.h"
#include "protocol/worker_messages.h"

namespace {

using namespace dtraced::testing;
using coll::TileOutcome;
using coll::WorkerId;
using coll::WorkerLimits;
using coll::WorkerRegistry;

const coll::TimePoint kStart = coll::TimePoint{} + std::chrono::hours(10);

const coll::WorkerView* find(const std::vector<coll::WorkerView>& list, const WorkerId& id) {
  for (const auto& v : list) {
    if (v.id == id) return &v;
  }
  return nullptr;
}

Request worker_request(Verb method, std::string target, std::string body, std::string_view name,
                       std::string_view peer) {
  Request req = make(method, std::move(target), std::move(body));
  if (!name.empty()) req.set(protocol::kWorkerHeader, name);
  req.set(dtraced::http::kPeerHeader, peer);
  return req;
}

protocol::WorkerList workers_of(Harness& h) {
  const Response res = h.call(Verb::get, "/v1/workers");
  REQUIRE(res.result() == Status::ok);
  auto list = protocol::decode_worker_list(res.body());
  if (!list) INFO(list.error().front().to_string());
  REQUIRE(list.ok());
  return list.value();
}

}  // namespace

TEST_CASE("the registry counts each worker by name and peer address", "[collector][workers]") {
  WorkerRegistry r;
  const WorkerId a{"render-1", "192.0.2.1"};
  const WorkerId a_elsewhere{"render-1", "192.0.2.2"};
  CHECK(r.on_lease(a, "avx2", 8, kStart));
  CHECK_FALSE(r.on_lease(a, "avx2", 8, kStart + 1s));
  CHECK(r.on_lease(a_elsewhere, "", 4, kStart + 2s));
  CHECK_FALSE(r.on_tile(a, TileOutcome::kStored, 640, kStart + 3s));
  r.on_tile(a, TileOutcome::kFaultyDuplicate, 0, kStart + 4s);
  r.on_tile(a, TileOutcome::kDuplicate, 0, kStart + 4s);
  r.on_tile(a, TileOutcome::kRefused, 0, kStart + 4s);

  const auto list = r.list(kStart + 5s);
  REQUIRE(list.size() == 2);
  CHECK(list[0].id == a);  // most recently seen first
  const coll::WorkerView* v = find(list, a);
  REQUIRE(v != nullptr);
  CHECK(v->isa == "avx2");
  CHECK(v->threads == 8);
  CHECK(v->leases == 2);
  CHECK(v->tiles == 1);
  CHECK(v->duplicates == 2);
  CHECK(v->faulty_duplicates == 1);
  CHECK(v->refused == 1);
  CHECK(v->recent_tiles == 1);
  CHECK(v->recent_rays == 640);
  CHECK(v->since_first_seen == 5s);
  CHECK(v->since_last_seen == 1s);
  CHECK_FALSE(v->quiet);
  const coll::WorkerView* other = find(list, a_elsewhere);
  REQUIRE(other != nullptr);
  CHECK(other->isa.empty());
  CHECK(other->threads == 4);
  CHECK(other->tiles == 0);
}

TEST_CASE("a worker unseen for a while is quiet, reported once, then forgotten", "[collector][workers]") {
  WorkerLimits limits;
  limits.quiet_after = 60s;
  limits.forget_after = 600s;
  WorkerRegistry r(limits);
  const WorkerId a{"a", "192.0.2.1"};
  const WorkerId b{"b", "192.0.2.1"};
  r.on_lease(a, "sse4", 2, kStart);
  r.on_lease(b, "sse4", 2, kStart);
  r.on_tile(a, TileOutcome::kStored, 10, kStart + 1s);

  CHECK(r.sweep(kStart + 59s).empty());
  r.on_lease(b, "sse4", 2, kStart + 59s);
  CHECK(r.sweep(kStart + 61s) == std::vector<WorkerId>{a});
  CHECK(r.sweep(kStart + 62s).empty());  // reported once
  auto list = r.list(kStart + 62s);
  CHECK(find(list, a)->quiet);
  CHECK_FALSE(find(list, b)->quiet);

  // Heard from again: active, and it can go quiet (and be reported) again.
  r.on_lease(a, "sse4", 2, kStart + 100s);
  CHECK_FALSE(find(r.list(kStart + 100s), a)->quiet);
  CHECK(r.sweep(kStart + 161s) == std::vector<WorkerId>{a, b});

  // Forgotten after forget_after; its counts stay in the retired sums.
  r.sweep(kStart + 100s + 600s);
  list = r.list(kStart + 700s);
  REQUIRE(list.size() == 0);
  CHECK(r.retired().tiles == 1);
  CHECK(r.retired().leases == 4);
}

TEST_CASE("recent tiles and rays count only the last window", "[collector][workers]") {
  WorkerRegistry r;
  const WorkerId a{"a", ""};
  r.on_tile(a, TileOutcome::kStored, 100, kStart);
  r.on_tile(a, TileOutcome::kStored, 100, kStart + coll::kRecentBucket);
  r.on_tile(a, TileOutcome::kDuplicate, 100, kStart + coll::kRecentBucket);  // not counted
  auto v = r.list(kStart + coll::kRecentBucket).front();
  CHECK(v.recent_tiles == 2);
  CHECK(v.recent_rays == 200);
  // A window later the first has left, the second not yet.
  v = r.list(kStart + coll::kRecentWindow).front();
  CHECK(v.recent_tiles == 1);
  CHECK(v.recent_rays == 100);
  v = r.list(kStart + coll::kRecentWindow + coll::kRecentBucket).front();
  CHECK(v.recent_tiles == 0);
  CHECK(v.tiles == 2);  // the totals stay
  // A ring slot reused after a full turn starts from zero.
  r.on_tile(a, TileOutcome::kStored, 7, kStart + coll::kRecentWindow * 3);
  v = r.list(kStart + coll::kRecentWindow * 3).front();
  CHECK(v.recent_tiles == 1);
  CHECK(v.recent_rays == 7);
}

TEST_CASE("past the cap, the least recently seen worker is evicted", "[collector][workers]") {
  WorkerLimits limits;
  limits.max_workers = 3;
  WorkerRegistry r(limits);
  for (int i = 0; i < 3; ++i) r.on_tile({std::to_string(i), ""}, TileOutcome::kStored, 1, kStart + i * 1s);
  r.on_lease({"0", ""}, "", 1, kStart + 10s);  // "1" is now the least recently seen
  CHECK(r.on_lease({"new", ""}, "", 1, kStart + 11s));
  CHECK(r.size() == 3);
  CHECK(r.evicted() == 1);
  const auto list = r.list(kStart + 12s);
  CHECK(find(list, {"1", ""}) == nullptr);
  CHECK(find(list, {"0", ""}) != nullptr);
  CHECK(find(list, {"new", ""}) != nullptr);
  CHECK(r.retired().tiles == 1);
  // Ten thousand distinct workers still leave three entries.
  for (int i = 0; i < 10'000; ++i) r.on_lease({fmt::format("w{}", i), ""}, "", 1, kStart + 20s + i * 1ms);
  CHECK(r.size() == 3);
}

TEST_CASE("a registry of max_workers N keeps N and evicts the least recently seen for the (N+1)th",
          "[collector][workers][limits]") {
  WorkerLimits limits;
  limits.max_workers = 100;
  WorkerRegistry r(limits);
  // Seen in the order 0..99, then the even ones again (leases and uploads alike move a worker).
  for (int i = 0; i < 100; ++i) CHECK(r.on_lease({fmt::format("w{}", i), ""}, "", 1, kStart + i * 1s));
  for (int i = 0; i < 100; i += 2) {
    if (i % 4 == 0) {
      CHECK_FALSE(r.on_lease({fmt::format("w{}", i), ""}, "", 1, kStart + 200s + i * 1s));
    } else {
      CHECK_FALSE(r.on_tile({fmt::format("w{}", i), ""}, TileOutcome::kStored, 1, kStart + 200s + i * 1s));
    }
  }
  CHECK(r.size() == 100);
  CHECK(r.evicted() == 0);
  // 50 newcomers evict exactly the odd ones, oldest first.
  for (int i = 0; i < 50; ++i) {
    CHECK(r.on_lease({fmt::format("new{}", i), ""}, "", 1, kStart + 400s + i * 1s));
    CHECK(r.evicted() == std::uint64_t(i + 1));
    CHECK(r.size() == 100);
    const auto list = r.list(kStart + 400s + i * 1s);
    CHECK(find(list, {fmt::format("w{}", 2 * i + 1), ""}) == nullptr);
    if (i + 1 < 50) CHECK(find(list, {fmt::format("w{}", 2 * i + 3), ""}) != nullptr);
  }
  const auto list = r.list(kStart + 500s);
  for (int i = 0; i < 100; i += 2) CHECK(find(list, {fmt::format("w{}", i), ""}) != nullptr);
  // Forgetting keeps the recency order right: after a sweep, the next eviction is the oldest left.
  r.sweep(kStart + 399s + limits.forget_after);  // forgets those seen before 399 s: the even ones
  CHECK(r.size() == 50);
  for (int i = 0; i < 51; ++i) r.on_lease({fmt::format("late{}", i), ""}, "", 1, kStart + 2h + i * 1s);
  CHECK(r.size() == 100);
  CHECK(r.evicted() == 51);
  CHECK(find(r.list(kStart + 3h), {"new0", ""}) == nullptr);
  CHECK(find(r.list(kStart + 3h), {"new1", ""}) != nullptr);
}

TEST_CASE("the default registry holds a 10,000-worker farm without evicting", "[collector][workers][limits]") {
  WorkerRegistry r;
  CHECK(r.limits().max_workers == coll::kDefaultMaxWorkers);
  for (int i = 0; i < 10'000; ++i) r.on_lease({fmt::format("host{}-77_{}", i / 8, i), "10.0.0.1"}, "", 8, kStart);
  CHECK(r.size() == 10'000);
  CHECK(r.evicted() == 0);
}

TEST_CASE("a log throttle lets one line through per interval and counts the rest", "[collector][admission]") {
  coll::LogThrottle throttle(10s);
  std::uint64_t held = 99;
  CHECK(throttle.allow(kStart, held));
  CHECK(held == 0);
  for (int i = 1; i <= 5; ++i) CHECK_FALSE(throttle.allow(kStart + i * 1s, held));
  CHECK(throttle.allow(kStart + 10s, held));
  CHECK(held == 5);
}

TEST_CASE("a histogram counts each value in the first bucket whose bound holds it", "[collector][metrics]") {
  coll::Histogram h{1, 10, 100};
  for (const double v : {0.5, 1.0, 5.0, 100.0, 1000.0}) h.observe(v);
  CHECK(h.cumulative(0) == 2);
  CHECK(h.cumulative(1) == 3);
  CHECK(h.cumulative(2) == 4);
  CHECK(h.count() == 5);
  CHECK(h.sum() == Approx(1106.5));
}

TEST_CASE("GET /v1/workers lists who leased and uploaded, with isa, threads and outcomes", "[collector][workers]") {
  TempDir dir;
  Harness h(dir);
  CHECK(workers_of(h).workers.empty());
  const std::uint64_t job = h.submit();

  Request lease = worker_request(Verb::post, "/v1/lease", R"({"worker": "box-1", "threads": 6})", "", "192.0.2.9");
  lease.set(protocol::kIsaHeader, "avx2");
  Response res = h.collector.handle_sync(std::move(lease));
  REQUIRE(res.result() == Status::ok);
  auto reply = protocol::decode_lease_reply(res.body());
  REQUIRE(reply.ok());
  const auto l = std::get<protocol::Lease>(reply.value());

  Request tile = worker_request(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, l.tile),
                                payload(job, l.tile, l.rect), "box-1", "192.0.2.9");
  tile.set(protocol::kRenderMsHeader, "1500");
  REQUIRE(h.collector.handle_sync(std::move(tile)).result() == Status::ok);
  // The same tile again with other pixels: a faulty duplicate. A bad payload: refused.
  Request again = worker_request(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, l.tile),
                                 payload(job, l.tile, l.rect, 0.5f), "box-1", "192.0.2.9");
  REQUIRE(h.collector.handle_sync(std::move(again)).result() == Status::ok);
  Request bad =
      worker_request(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, l.tile), "nonsense", "box-1", "192.0.2.9");
  REQUIRE(h.collector.handle_sync(std::move(bad)).result() == Status::bad_request);
  // A lease with a malformed isa header still counts; the isa is ignored.
  Request odd = worker_request(Verb::post, "/v1/lease", R"({"worker": "box-2", "threads": 1})", "", "192.0.2.10");
  odd.set(protocol::kIsaHeader, "AVX2\x01 or worse");
  REQUIRE(h.collector.handle_sync(std::move(odd)).result() == Status::ok);

  const protocol::WorkerList list = workers_of(h);
  CHECK(list.recent_window_s == 300);
  CHECK(list.quiet_after_s == 60);
  REQUIRE(list.workers.size() == 2);
  const protocol::WorkerInfo& w = list.workers[1].name == "box-1" ? list.workers[1] : list.workers[0];
  CHECK(w.name == "box-1");
  CHECK(w.peer == "192.0.2.9");
  CHECK(w.isa == "avx2");
  CHECK(w.threads == 6);
  CHECK(w.leases == 1);
  CHECK(w.tiles == 1);
  CHECK(w.duplicates == 1);
  CHECK(w.faulty_duplicates == 1);
  CHECK(w.refused == 1);
  CHECK(w.recent_tiles == 1);
  CHECK(w.recent_rays == std::uint64_t{l.rect.width} * l.rect.height * 1);
  CHECK_FALSE(w.quiet);
  const protocol::WorkerInfo& odd_one = list.workers[1].name == "box-2" ? list.workers[1] : list.workers[0];
  CHECK(odd_one.isa.empty());

  // Unseen for a minute: quiet; the render time reached the histogram.
  h.clock.advance(61s);
  for (const auto& seen : workers_of(h).workers) CHECK(seen.quiet);
  const coll::MetricsSnapshot m = h.metrics();
  CHECK(m.counters.tile_render_seconds.count() == 1);
  CHECK(m.counters.tile_render_seconds.sum() == 1.5);
  CHECK(m.counters.tile_upload_bytes.count() == 3);
}

TEST_CASE("GET /v1/workers refuses a wrong method, a query and a missing token", "[collector][workers]") {
  TempDir dir;
  Harness h(dir);
  Response res = h.call(Verb::post, "/v1/workers");
  CHECK(res.result() == Status::method_not_allowed);
  CHECK(res[boost::beast::http::field::allow] == "GET");
  res = h.call(Verb::get, "/v1/workers?all=1");
  CHECK(res.result() == Status::bad_request);
  res = h.call(Verb::get, "/v1/workers", "", "");
  CHECK(res.result() == Status::unauthorized);
  res = h.call(Verb::get, "/v1/workers/x");
  CHECK(res.result() == Status::not_found);
  CHECK(h.metrics().counters.auth_failures == 1);
}

TEST_CASE("/metrics has build info, process figures, histograms, every response class and bounded worker series",
          "[collector][metrics]") {
  TempDir dir;
  Harness h(dir);
  for (int i = 0; i < 30; ++i) {
    Request lease = worker_request(Verb::post, "/v1/lease", fmt::format(R"({{"worker": "w{}", "threads": 1}})", i), "",
                                   "192.0.2.1");
    REQUIRE(h.collector.handle_sync(std::move(lease)).result() == Status::ok);
    h.clock.advance(1s);
  }
  const Response res = h.call(Verb::get, "/metrics");
  REQUIRE(res.result() == Status::ok);
  const std::string& text = res.body();
  CHECK_THAT(text, Catch::Contains("dtraced_build_info{version=\""));
  CHECK_THAT(text, Catch::Contains("process_start_time_seconds "));
  CHECK_THAT(text, Catch::Contains("process_resident_memory_bytes "));
  CHECK_THAT(text, Catch::Contains("process_open_fds "));
  CHECK_THAT(text, Catch::Contains("dtraced_lease_duration_seconds_bucket{le=\"+Inf\"} 30"));
  CHECK_THAT(text, Catch::Contains("dtraced_lease_duration_seconds_count 30"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_tile_upload_bytes histogram"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_tile_render_seconds histogram"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_store_checkpoints_total counter"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_store_checkpoints_background_total counter"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_store_checkpoint_seconds_total counter"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_store_gather_waits_total counter"));
  CHECK_THAT(text, Catch::Contains("# TYPE dtraced_store_gather_timeouts_total counter"));
  CHECK_THAT(text, Catch::Contains("dtraced_http_responses_total{class=\"2xx\"}"));
  CHECK_THAT(text, Catch::Contains("dtraced_workers{state=\"active\"} 30"));
  // The 20 most recent by name, the 10 oldest as other.
  CHECK_THAT(text, Catch::Contains("dtraced_worker_leases_total{worker=\"w29@192.0.2.1\"} 1"));
  CHECK_THAT(text, Catch::Contains("dtraced_worker_leases_total{worker=\"w10@192.0.2.1\"} 1"));
  CHECK_THAT(text, !Catch::Contains("worker=\"w9@192.0.2.1\""));
  CHECK_THAT(text, Catch::Contains("dtraced_worker_leases_total{worker=\"other\"} 10"));
  // Every series belongs to a family with HELP and TYPE lines.
  std::size_t helps = 0;
  std::size_t types = 0;
  for (std::size_t at = 0; (at = text.find("# HELP ", at)) != std::string::npos; ++at) ++helps;
  for (std::size_t at = 0; (at = text.find("# TYPE ", at)) != std::string::npos; ++at) ++types;
  CHECK(helps == types);
}

TEST_CASE("the worker list survives a round trip and its decoder names bad fields", "[protocol][workers]") {
  protocol::WorkerList list;
  list.recent_window_s = 300;
  list.quiet_after_s = 60;
  protocol::WorkerInfo w;
  w.name = "n";
  w.peer = "::1";
  w.isa = "avx2";
  w.threads = 3;
  w.last_seen_s = 1.25;
  w.tiles = 4;
  list.workers.push_back(w);
  auto decoded = protocol::decode_worker_list(protocol::encode(list));
  REQUIRE(decoded.ok());
  CHECK(decoded.value() == list);

  auto bad = protocol::decode_worker_list(R"({"recent_window_s": 1, "quiet_after_s": 1, "workers": [{"name": 3}]})");
  REQUIRE_FALSE(bad.ok());
  CHECK(bad.error().front().path == "/workers/0/name");
  bad = protocol::decode_worker_list(R"({"recent_window_s": 1, "quiet_after_s": 1, "workers": [], "extra": 1})");
  REQUIRE_FALSE(bad.ok());
  CHECK(bad.error().front().path == "/extra");

  CHECK(protocol::parse_isa_header("avx512") == "avx512");
  CHECK_FALSE(protocol::parse_isa_header(""));
  CHECK_FALSE(protocol::parse_isa_header("AVX2"));
  CHECK_FALSE(protocol::parse_isa_header("a-very-long-isa-name-indeed"));
  CHECK(protocol::parse_render_ms_header("0") == 0u);
  CHECK(protocol::parse_render_ms_header("1500") == 1500u);
  CHECK_FALSE(protocol::parse_render_ms_header("-1"));
  CHECK_FALSE(protocol::parse_render_ms_header("1e3"));
  CHECK_FALSE(protocol::parse_render_ms_header("99999999999999"));
}

TEST_CASE("a job's status says when it has had no worker for a minute", "[collector][workers]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  CHECK_FALSE(h.status(job).no_worker_s);
  h.clock.advance(59s);
  CHECK_FALSE(h.status(job).no_worker_s);
  h.clock.advance(2s);
  auto gap = h.status(job).no_worker_s;
  REQUIRE(gap);
  CHECK(*gap == Approx(61).margin(1));

  // A lease is a worker: the gap starts again from it, and so does a stored tile.
  const auto l = h.lease();
  REQUIRE(l);
  CHECK_FALSE(h.status(job).no_worker_s);
  h.clock.advance(90s);
  gap = h.status(job).no_worker_s;
  REQUIRE(gap);
  CHECK(*gap == Approx(90).margin(1));
  CHECK(h.put_ok(*l) == protocol::SubmitResult::kStored);
  CHECK_FALSE(h.status(job).no_worker_s);

  // The list says it too; a cancelled job does not.
  h.clock.advance(120s);
  const Response listed = h.call(Verb::get, "/v1/jobs");
  auto list = protocol::decode_job_list(listed.body());
  REQUIRE(list.ok());
  REQUIRE(list.value().jobs.size() == 1);
  CHECK(list.value().jobs[0].no_worker_s);
  REQUIRE(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job)).result() == Status::ok);
  CHECK_FALSE(h.status(job).no_worker_s);
}

TEST_CASE("no_worker_s travels in a job status and may be absent or null", "[protocol][workers]") {
  protocol::JobStatus s;
  s.id = 3;
  s.output = "a.png";
  s.width = s.height = s.samples = 1;
  s.tiles_total = 1;
  s.digest = std::string(64, 'a');
  s.no_worker_s = 75.5;
  auto back = protocol::decode_job_status(protocol::encode(s));
  REQUIRE(back.ok());
  CHECK(back.value() == s);
  // An older collector's status has no such key.
  const std::regex field(R"(,"no_worker_s":[^,}]*)");
  const std::string older = std::regex_replace(protocol::encode(s), field, "");
  REQUIRE(older.find("no_worker_s") == std::string::npos);
  back = protocol::decode_job_status(older);
  REQUIRE(back.ok());
  CHECK_FALSE(back.value().no_worker_s);
  const std::string negative = std::regex_replace(protocol::encode(s), field, R"(,"no_worker_s":-1)");
  auto bad = protocol::decode_job_status(negative);
  REQUIRE_FALSE(bad.ok());
  CHECK(bad.error().front().path == "/no_worker_s");
}
