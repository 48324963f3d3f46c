// dtraced::worker, whole workers against a fake collector (tests/fake_collector.h: an http::Server
// on 127.0.0.1) that fails in chosen ways: absent, 500s, a 503 scene, 503 submissions, a restart,
// a gone job, a bad token, a tampered scene, requests it never answers.
//
// Each worker runs on a util::ManualClock. Its backoffs, "retry after" waits and grace period end
// when the test moves the clock (ClockDriver below), so no test waits for one in real time, and a
// test can say exactly how long the worker slept. Real time is only the bound (kBound) on events
// that come over loopback sockets; nothing asserts on timing.
#include <signal.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>

#include "fake_collector.h"
#include "render/tile.h"
#include "util/clock.h"
#include "worker/backoff.h"
#include "worker/config.h"
#include "worker/worker.h"
#include "worker_testing.h"

namespace dtraced::testing {
namespace {

using worker::WorkerStats;

// What must hold of any worker once it has stopped: nothing left in hand, every rendered tile
// accounted for exactly once.
void check_stopped_cleanly(const WorkerStats& s) {
  CHECK(s.started);
  CHECK(s.stopping);
  CHECK(s.tiles_held == 0);
  CHECK(s.tiles_in_hand == 0);
  CHECK(s.tiles_rendered == s.tiles_submitted + s.tiles_dropped + s.tiles_rejected + s.tiles_abandoned);
}

// How often the driver looks again at a condition that only a counter shows, in real time.
constexpr auto kPoll = 2ms;

// Moves a ManualClock for a worker under test: until a condition holds, whenever the worker
// sleeps on the clock, it moves the clock to the earliest deadline, one at a time, but never past
// `limit` (so that a grace period the test means to keep is not skipped by accident). Time passing
// while the worker sleeps is a schedule a real clock could produce; a request over loopback
// takes no time on this clock.
class ClockDriver {
 public:
  explicit ClockDriver(util::ManualClock& clock) : clock_(clock) {}

  // Whether `condition` held within kBound of real time.
  bool until(const std::function<bool()>& condition, util::TimePoint limit = util::TimePoint::max()) {
    const auto give_up = std::chrono::steady_clock::now() + kBound;
    while (!condition()) {
      if (std::chrono::steady_clock::now() > give_up) return false;
      const std::optional<util::TimePoint> next = clock_.next_deadline();
      if (next && *next <= limit) {
        clock_.advance_to(*next);
        moves_.push_back(*next);
        continue;
      }
      // Nothing to move yet: wait for the worker to sleep on the clock, or look again.
      clock_.wait_for_sleepers(clock_.sleepers() + 1, kPoll);
    }
    return true;
  }

  // Every deadline the clock was moved to, in order.
  const std::vector<util::TimePoint>& moves() const { return moves_; }

 private:
  util::ManualClock& clock_;
  std::vector<util::TimePoint> moves_;
};

// A Worker on a ManualClock, running on a thread of its own.
class RunningWorker {
 public:
  explicit RunningWorker(const worker::WorkerConfig& config, worker::RunOptions options = {})
      : worker_(create(config, clock_)), start_(clock_.now()) {
    std::packaged_task<bool()> task([this, options] { return worker_->run(options); });
    result_ = task.get_future();
    thread_ = std::thread(std::move(task));
  }

  ~RunningWorker() {
    worker_->request_stop();
    // A test that failed half-way may leave tiles in hand: let their grace period pass.
    driver_.until([this] { return finished(); });
    if (thread_.joinable()) thread_.join();
  }

  WorkerStats stats() const { return worker_->stats(); }
  const worker::WorkerConfig& config() const { return worker_->config(); }
  util::ManualClock& clock() { return clock_; }
  util::TimePoint start() const { return start_; }
  const std::vector<util::TimePoint>& moves() const { return driver_.moves(); }

  // Drives the clock until `condition` holds; false if it did not within kBound.
  bool until(const std::function<bool()>& condition, util::TimePoint limit = util::TimePoint::max()) {
    return driver_.until(condition, limit);
  }

  void request_stop() {
    stop_asked_at_ = clock_.now();
    worker_->request_stop();
  }
  // When the grace period after request_stop() ends, at the earliest.
  util::TimePoint grace_end() const { return stop_asked_at_ + config().grace; }

  // Drives the clock (never past `limit`) until run() returns; its result, or nullopt if it did
  // not return within kBound.
  std::optional<bool> wait(util::TimePoint limit) {
    if (!driver_.until([this] { return finished(); }, limit)) return std::nullopt;
    thread_.join();
    return result_.get();
  }
  // After request_stop(): wait() short of the end of the grace period.
  std::optional<bool> wait() { return wait(grace_end() - 1ms); }

  // Requests a stop, waits for run() to return true without the grace period running out, and
  // checks that the worker stopped cleanly.
  WorkerStats stop_cleanly() {
    request_stop();
    REQUIRE(wait() == std::optional<bool>(true));
    const WorkerStats s = stats();
    check_stopped_cleanly(s);
    return s;
  }

 private:
  static std::unique_ptr<worker::Worker> create(const worker::WorkerConfig& config, const util::Clock& clock) {
    auto created = worker::Worker::create(config, clock);
    REQUIRE(created.ok());
    return std::move(created).value();
  }

  // Whether run() has returned (its result may have been taken already).
  bool finished() const { return !result_.valid() || result_.wait_for(0s) == std::future_status::ready; }

  util::ManualClock clock_;  // outlives the worker
  ClockDriver driver_{clock_};
  std::unique_ptr<worker::Worker> worker_;
  const util::TimePoint start_;
  util::TimePoint stop_asked_at_;
  std::future<bool> result_;
  std::thread thread_;
};

// The usual setting: a fake collector with `rules` on an ephemeral port, and a worker asking it.
struct Farm {
  explicit Farm(FakeRules rules = {}, const std::function<void(worker::WorkerConfig&)>& configure = {})
      : fake(std::move(rules)), server(0, fake.handler()), worker(config_for(server.port(), configure)) {}

  static worker::WorkerConfig config_for(std::uint16_t port,
                                         const std::function<void(worker::WorkerConfig&)>& configure) {
    worker::WorkerConfig config = test_config(port);
    if (configure) configure(config);
    return config;
  }

  FakeCollector fake;
  RunningServer server;
  RunningWorker worker;
};

// Every tile stored once, with the pixels (and, for an adaptive job, the sample counts) of a
// local render_tile of the same rectangle.
void check_pixels(const FakeCollector& fake) {
  const FakeCounts counts = fake.counts();
  const worker::ScenePtr scene = build(fake.desc());
  const std::vector<std::vector<float>> pixels = fake.pixels();
  const std::vector<std::vector<std::uint32_t>> spp = fake.spp();
  for (std::size_t t = 0; t < fake.rects().size(); ++t) {
    INFO("tile " << t);
    CHECK(counts.stored[t] == 1);
    const render::Tile local = render::render_tile(*scene, fake.desc().render, fake.rects()[t]);
    CHECK(same_bits(pixels[t], local.rgb));
    CHECK(spp[t] == local.spp);
  }
  for (const std::string& problem : counts.problems) FAIL_CHECK(problem);
}

// The deadlines a worker whose lease requests all fail sleeps until, from `start`: each failure
// in a row draws the next delay of the worker's jitter generator (same seed), and a delay of 0 is
// no sleep. The first `n` of them.
std::vector<util::TimePoint> backoff_deadlines(const worker::WorkerConfig& config, util::TimePoint start,
                                               std::size_t n) {
  const worker::Backoff backoff(config.backoff_initial, config.backoff_max);
  std::mt19937_64 replica(config.jitter_seed);
  std::vector<util::TimePoint> deadlines;
  util::TimePoint t = start;
  for (std::uint32_t failures = 0; deadlines.size() < n && failures < 10'000; ++failures) {
    const auto d = backoff.delay(failures, replica);
    if (d == 0ms) continue;
    t += d;
    deadlines.push_back(t);
  }
  return deadlines;
}

}  // namespace
}  // namespace dtraced::testing

using namespace dtraced;
using namespace dtraced::testing;

TEST_CASE("a worker started before its collector renders every tile, through refusals and 5xx answers",
          "[worker][end_to_end]") {
  FakeCollector fake({.failing_leases = 2, .failing_scene_fetches = 1, .fail_first_submit = {1}});
  const std::uint16_t port = unused_port();
  RunningWorker worker(test_config(port));

  // Nobody listens yet: the worker keeps asking, with backoff.
  REQUIRE(worker.until([&] { return worker.stats().lease_failures >= 3; }));
  CHECK(worker.stats().tiles_rendered == 0);

  RunningServer server(port, fake.handler());
  REQUIRE(worker.until([&] { return fake.all_stored(); }));
  const WorkerStats s = worker.stop_cleanly();

  check_pixels(fake);
  const FakeCounts counts = fake.counts();
  CHECK(s.tiles_submitted == counts.acknowledged);
  CHECK(s.tiles_rendered >= 4);
  CHECK(s.tiles_dropped == 0);
  CHECK(s.tiles_rejected == 0);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.submit_retries >= 1);
  CHECK(counts.submit_requests[1] >= 2);
  CHECK(s.scenes_fetched == 1);  // the failed fetch is retried once, then the cache serves
  CHECK(s.scenes_rejected == 0);
  CHECK(s.tiles_in_hand_peak <= 4);
  CHECK(counts.unauthorized == 0);
}

TEST_CASE("rendered tiles are kept across a collector restart and submitted to the new one", "[worker][end_to_end]") {
  FakeCollector fake({.submits_unavailable = true});
  const std::uint16_t port = unused_port();
  std::optional<RunningServer> server;
  server.emplace(port, fake.handler());
  RunningWorker worker(test_config(port));

  // Every tile rendered and offered, none taken; with four tiles in hand the worker stops leasing.
  REQUIRE(worker.until([&] { return fake.every_tile_submitted(); }));
  REQUIRE(worker.until([&] { return worker.stats().tiles_held == 4; }));

  server.reset();  // the collector goes away: connections are refused
  const std::uint64_t retries = worker.stats().submit_retries;
  REQUIRE(worker.until([&] { return worker.stats().submit_retries >= retries + 2; }));
  CHECK(worker.stats().tiles_held == 4);

  fake.set_rules([](FakeRules& r) { r.submits_unavailable = false; });
  server.emplace(port, fake.handler());
  REQUIRE(worker.until([&] { return fake.all_stored(); }));
  const WorkerStats s = worker.stop_cleanly();

  check_pixels(fake);
  CHECK(s.tiles_submitted == fake.counts().acknowledged);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_in_hand_peak <= 4);
}

TEST_CASE("a job gone drops its tiles without retrying them", "[worker][end_to_end]") {
  Farm farm({.job_gone = true});
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] {
    const WorkerStats s = worker.stats();
    return s.tiles_dropped >= 1 && s.tiles_held == 0 && s.tiles_rendered == s.tiles_dropped;
  }));
  const WorkerStats s = worker.stop_cleanly();

  CHECK(s.tiles_submitted == 0);
  CHECK(s.submit_retries == 0);
  CHECK(s.tiles_rendered == s.tiles_dropped);
  std::uint64_t submits = 0;
  for (const std::uint64_t n : farm.fake.counts().submit_requests) submits += n;
  CHECK(submits <= s.tiles_rendered);
  CHECK(farm.fake.counts().problems.empty());
}

TEST_CASE("a stop submits what is in hand within the grace period", "[worker][end_to_end]") {
  Farm farm({.submits_unavailable = true});
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return worker.stats().tiles_held >= 1; }));
  worker.request_stop();
  REQUIRE(worker.until([&] { return worker.stats().stopping; }));
  farm.fake.set_rules([](FakeRules& r) { r.submits_unavailable = false; });
  // The clock moves through the submissions' backoffs, but never to the end of the grace period.
  REQUIRE(worker.wait() == std::optional<bool>(true));
  CHECK(worker.clock().now() < worker.grace_end());

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_submitted == s.tiles_rendered);
  CHECK(s.tiles_submitted == farm.fake.counts().acknowledged);
  CHECK(farm.fake.counts().problems.empty());
}

TEST_CASE("when the grace period runs out, unacknowledged tiles are abandoned and the worker exits",
          "[worker][end_to_end]") {
  Farm farm({.submits_unavailable = true}, [](worker::WorkerConfig& c) { c.grace = 0s; });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return worker.stats().tiles_held >= 1; }));
  const WorkerStats s = worker.stop_cleanly();

  CHECK(s.tiles_submitted == 0);
  CHECK(s.tiles_abandoned == s.tiles_rendered);
  CHECK(s.tiles_abandoned >= 1);
}

TEST_CASE("a rejected token is retried with backoff and nothing is rendered", "[worker][end_to_end]") {
  Farm farm({.reject_token = true});
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return worker.stats().lease_failures >= 5; }));

  // Each failure in a row is followed by exactly the jittered backoff the seed draws, on the
  // clock: the requests of the first round fail together and back off once, and while it fails
  // one request at a time probes the collector.
  const std::vector<util::TimePoint> moves = worker.moves();
  REQUIRE(moves.size() >= 2);
  CHECK(moves == backoff_deadlines(worker.config(), worker.start(), moves.size()));

  const WorkerStats s = worker.stop_cleanly();
  CHECK(s.tiles_rendered == 0);
  CHECK(farm.fake.counts().leases == 0);
  CHECK(farm.fake.counts().unauthorized >= 5);
}

TEST_CASE("a scene that does not match its digest is refused and nothing is rendered", "[worker][end_to_end]") {
  Farm farm({.tamper_scene = true});
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return worker.stats().scenes_rejected >= 2; }));
  const WorkerStats s = worker.stop_cleanly();

  CHECK(s.tiles_rendered == 0);
  CHECK(s.scenes_fetched == 0);
  CHECK(s.leases_dropped >= 2);
}

// The worker's read timeout is far longer than kBound: only cancellation can end these requests.
TEST_CASE("a stop cancels a lease request the collector never answers", "[worker][end_to_end]") {
  Farm farm({.hang_leases = true}, [](worker::WorkerConfig& c) { c.timeouts.read = worker::kMaxClientTimeout; });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return farm.fake.counts().hung >= 1; }));
  const WorkerStats s = worker.stop_cleanly();
  CHECK(s.tiles_rendered == 0);
}

TEST_CASE("the end of the grace period cancels submissions the collector never answers", "[worker][end_to_end]") {
  Farm farm({.hang_submits = true}, [](worker::WorkerConfig& c) {
    c.timeouts.read = worker::kMaxClientTimeout;
    c.grace = 60s;
  });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return farm.fake.counts().hung >= 1; }));
  worker.request_stop();
  // The stop takes effect before the clock moves again, so the grace period ends at grace_end().
  REQUIRE(worker.until([&] { return worker.stats().stopping; }, worker.clock().now()));
  // All that is left to wait for is the end of the grace period: the worker sleeps until then.
  REQUIRE(worker.until([&] { return worker.clock().next_deadline() == worker.grace_end(); }, worker.grace_end() - 1ms));
  CHECK(worker.stats().tiles_abandoned == 0);
  CHECK(worker.stats().tiles_held >= 1);

  REQUIRE(worker.wait(worker.grace_end() + 1ms) == std::optional<bool>(true));
  CHECK(worker.clock().now() == worker.grace_end());  // not a moment sooner
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_submitted == 0);
  CHECK(s.tiles_abandoned == s.tiles_rendered);
  CHECK(s.tiles_abandoned >= 1);
}

TEST_CASE("SIGTERM stops a worker that waits for an absent collector", "[worker][end_to_end]") {
  RunningWorker worker(test_config(unused_port()),
                       worker::RunOptions{.stop_on_signals = true, .notify_systemd = false});
  REQUIRE(worker.until([&] { return worker.stats().started && worker.stats().lease_failures >= 1; }));
  const util::TimePoint grace_end = worker.clock().now() + worker.config().grace;
  REQUIRE(::kill(::getpid(), SIGTERM) == 0);
  REQUIRE(worker.wait(grace_end - 1ms) == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_rendered == 0);
}

TEST_CASE("with start_jitter a worker waits before its first request, and a stop during the wait exits at once",
          "[worker][end_to_end][limits]") {
  SECTION("a stop during the wait: no request, exit true, well before the wait or a grace period ends") {
    Farm farm({}, [](worker::WorkerConfig& c) {
      c.start_jitter = 3'600'000ms;  // an hour: the clock is never moved that far
      c.jitter_seed = 7;
    });
    RunningWorker& worker = farm.worker;
    std::mt19937_64 replica(7);
    const auto delay = worker::start_delay(3'600'000ms, replica);
    REQUIRE(delay > 1s);  // the seed's delay, as the worker draws it first
    // The worker sleeps on the clock (its start delay) and asks nothing meanwhile.
    REQUIRE(worker.until([&] { return worker.stats().started && worker.clock().sleepers() >= 1; }, worker.start()));
    CHECK(worker.clock().next_deadline() == std::optional<util::TimePoint>(worker.start() + delay));
    CHECK(farm.fake.counts().lease_requests == 0);
    worker.request_stop();
    // Not a moment of the wait, nor of the grace period, passes on the clock.
    REQUIRE(worker.wait(worker.start()) == std::optional<bool>(true));
    const WorkerStats s = worker.stats();
    check_stopped_cleanly(s);
    CHECK(s.tiles_rendered == 0);
    CHECK(farm.fake.counts().lease_requests == 0);
    CHECK(worker.clock().now() == worker.start());
  }
  SECTION("the wait over, the worker renders the job as usual") {
    Farm farm({}, [](worker::WorkerConfig& c) {
      c.start_jitter = 20'000ms;
      c.jitter_seed = 11;
    });
    RunningWorker& worker = farm.worker;
    std::mt19937_64 replica(11);
    const auto delay = worker::start_delay(20'000ms, replica);
    REQUIRE(worker.until([&] { return farm.fake.all_stored(); }));
    // Its first move of the clock was to the end of the start delay.
    REQUIRE_FALSE(worker.moves().empty());
    CHECK(worker.moves().front() == worker.start() + delay);
    worker.stop_cleanly();
    check_pixels(farm.fake);
  }
}

TEST_CASE("an adaptive job's tiles carry their per-pixel sample counts", "[worker][end_to_end][adaptive]") {
  scene::SceneDesc desc = load_tiny_scene();
  desc.render.samples = 16;
  desc.render.min_samples = 4;
  desc.render.error_target = 0.05;
  FakeCollector fake({}, desc);
  const std::uint16_t port = unused_port();
  RunningServer server(port, fake.handler());
  RunningWorker worker(test_config(port));
  REQUIRE(worker.until([&] { return fake.all_stored(); }));
  worker.stop_cleanly();
  check_pixels(fake);  // counts equal to a local render's
  // Some pixels stopped early (the background), some did not (the outline): counts are real.
  std::set<std::uint32_t> seen;
  for (const auto& tile : fake.spp()) {
    REQUIRE(tile.size() == std::size_t{kTileSize} * kTileSize);
    seen.insert(tile.begin(), tile.end());
  }
  CHECK(seen.contains(4));
  CHECK(seen.contains(16));
}

// ---- a collector that refuses every tile it leases ------------------------------------------------

namespace {

// While it lives, what the process writes to stderr (the worker's log) goes to a temporary file.
class CapturedStderr {
 public:
  CapturedStderr() : file_(std::tmpfile()) {
    REQUIRE(file_ != nullptr);
    std::fflush(stderr);
    saved_ = ::dup(STDERR_FILENO);
    REQUIRE(saved_ >= 0);
    REQUIRE(::dup2(::fileno(file_), STDERR_FILENO) == STDERR_FILENO);
  }
  CapturedStderr(const CapturedStderr&) = delete;
  CapturedStderr& operator=(const CapturedStderr&) = delete;
  ~CapturedStderr() {
    restore();
    std::fclose(file_);
  }

  // Gives stderr back, and returns the lines written to it meanwhile.
  std::vector<std::string> lines() {
    restore();
    std::rewind(file_);
    std::vector<std::string> out;
    std::string line;
    for (int c = std::fgetc(file_); c != EOF; c = std::fgetc(file_)) {
      if (c != '\n') {
        line.push_back(static_cast<char>(c));
        continue;
      }
      out.push_back(std::exchange(line, {}));
    }
    return out;
  }

 private:
  void restore() {
    if (saved_ < 0) return;
    ::dup2(saved_, STDERR_FILENO);
    ::close(saved_);
    saved_ = -1;
  }

  std::FILE* file_;
  int saved_ = -1;
};

// What a worker with the default backoffs did in kRefusedFor of simulated time against a
// collector that leases every tile again and again and takes none.
struct RefusedRun {
  bool lasted = false;                               // the clock reached kRefusedFor before kSpinRequests
  std::map<std::int64_t, std::uint64_t> per_second;  // requests per simulated second
  std::uint64_t requests = 0;
  std::vector<std::string> log;
  WorkerStats stats;
};

constexpr auto kRefusedFor = 10min;
// A worker that spins sends these long before its clock moves: the run ends there, failed.
constexpr std::uint64_t kSpinRequests = 5000;

RefusedRun run_refused(FakeRules rules) {
  rules.reoffer_after = 0;  // every lease request gets a tile: the collector "keeps leasing"
  RefusedRun run;
  CapturedStderr captured;
  {
    FakeCollector fake(rules);
    RunningServer server(0, fake.handler());
    RunningWorker worker(Farm::config_for(server.port(), [](worker::WorkerConfig& c) {
      c.backoff_initial = worker::WorkerConfig{}.backoff_initial;
      c.backoff_max = worker::WorkerConfig{}.backoff_max;
    }));
    fake.stamp_with(worker.clock());
    const util::TimePoint start = worker.start();
    run.lasted = worker.until([&] {
      return worker.clock().now() >= start + kRefusedFor || fake.counts().request_times.size() >= kSpinRequests;
    });
    run.lasted = run.lasted && worker.clock().now() >= start + kRefusedFor;
    run.stats = worker.stop_cleanly();
    // Requests before stamp_with() carry TimePoint::min(): they count in the first second.
    for (const util::TimePoint t : fake.counts().request_times) {
      ++run.per_second[std::chrono::duration_cast<std::chrono::seconds>(std::max(t, start) - start).count()];
      ++run.requests;
    }
    CHECK(fake.counts().problems.empty());
  }
  run.log = captured.lines();
  return run;
}

// Asserts that a refused worker backed off and logged a few lines, not one per refusal.
void check_backed_off(const RefusedRun& run, std::string_view what) {
  std::uint64_t busiest = 0;
  for (const auto& [second, n] : run.per_second) busiest = std::max(busiest, n);
  INFO(run.requests << " requests, at most " << busiest << " in one simulated second, " << run.log.size()
                    << " log lines");
  REQUIRE(run.lasted);
  // Backoff caps 0.1, 0.2, 0.4, ... 10 s with full jitter: the tiles in hand and a burst of a few
  // refusals at the start (the hot loop sent 2,100 requests in a second), then one refusal every
  // 5 s on average, a lease and a submission each.
  CHECK(busiest <= 60);
  CHECK(run.requests <= 600);
  std::uint64_t last_five_minutes = 0;
  for (const auto& [second, n] : run.per_second) last_five_minutes += second >= 300 ? n : 0;
  CHECK(last_five_minutes <= 300);
  // Still trying: the worker is slowed, not stuck.
  CHECK(run.requests >= 20);
  // The refusal is logged once, then with a count at most every kLogRepeatEvery (30 s), plus the
  // lines of start and stop.
  std::size_t refusals_logged = 0;
  for (const std::string& line : run.log) refusals_logged += line.find(what) != std::string::npos ? 1 : 0;
  CHECK(refusals_logged >= 1);
  CHECK(refusals_logged <= 1 + 10min / 30s);
  CHECK(run.log.size() <= refusals_logged + 10);
}

}  // namespace

TEST_CASE("a worker whose every tile is refused backs off and logs each refusal once per interval",
          "[worker][end_to_end][refusals]") {
  const RefusedRun run = run_refused({.refuse_submits = 422});
  check_backed_off(run, "refused tile");
  CHECK(run.stats.tiles_rejected >= 10);
  CHECK(run.stats.tiles_submitted == 0);
}

TEST_CASE("a worker leased again and again a job the collector says is gone backs off",
          "[worker][end_to_end][refusals]") {
  const RefusedRun run = run_refused({.job_gone = true, .lease_after_gone = true});
  check_backed_off(run, "is gone");
  CHECK(run.stats.tiles_dropped >= 10);
  CHECK(run.stats.tiles_submitted == 0);
}

TEST_CASE("with exit_when_done a worker submits what it has and exits when its collector says it has finished",
          "[worker][end_to_end][exit_when_done]") {
  Farm farm({}, [](worker::WorkerConfig& c) { c.exit_when_done = true; });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return farm.fake.all_stored(); }));
  CHECK_FALSE(worker.stats().stopping);  // "retry after" alone is no reason to leave
  // The job is over and the collector is going away: the next lease answer says so.
  farm.fake.set_rules([](FakeRules& r) { r.finished_header = "1"; });
  // The stop comes after now, so its grace period ends after now + grace: never move the clock
  // that far, or a submission still on its way in real time would be abandoned.
  REQUIRE(worker.wait(worker.clock().now() + worker.config().grace - 1ms) == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.collector_finished);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_submitted == farm.fake.counts().acknowledged);
  check_pixels(farm.fake);
}

TEST_CASE("without exit_when_done, or with a garbled header, a finished answer is only a retry-after",
          "[worker][end_to_end][exit_when_done]") {
  struct Case {
    bool exit_when_done;
    std::string_view header;
  };
  for (const Case& c : {Case{false, "1"}, Case{true, "yes"}}) {
    INFO("exit_when_done " << c.exit_when_done << ", header '" << c.header << "'");
    Farm farm({.finished_header = c.header}, [&c](worker::WorkerConfig& w) { w.exit_when_done = c.exit_when_done; });
    RunningWorker& worker = farm.worker;
    // The worker keeps asking, through many such answers after its last tile.
    REQUIRE(worker.until([&] { return farm.fake.all_stored() && farm.fake.counts().retry_answers >= 20; }));
    CHECK_FALSE(worker.stats().stopping);
    CHECK_FALSE(worker.stats().collector_finished);
    const WorkerStats s = worker.stop_cleanly();
    CHECK_FALSE(s.collector_finished);
    check_pixels(farm.fake);
  }
}

TEST_CASE("with exit_when_idle a worker renders the whole job, then exits once it has had no work that long",
          "[worker][end_to_end][exit_when_idle]") {
  Farm farm({}, [](worker::WorkerConfig& c) { c.exit_when_idle = 30s; });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return farm.fake.all_stored(); }));
  CHECK_FALSE(worker.stats().stopping);  // it had work until now
  const util::TimePoint done = worker.clock().now();
  // Not past the grace period of a stop that comes after `done` (see the exit_when_done case).
  REQUIRE(worker.wait(done + worker.config().grace - 1ms) == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.stopped_idle);
  CHECK_FALSE(s.stopped_runtime);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_submitted == farm.fake.counts().acknowledged);
  // It asked again and again meanwhile, and left no sooner than 30 s after its last tile (whose
  // render ended at or after the start; the clock does not stop exactly there, so the start is the
  // bound a test can see).
  CHECK(farm.fake.counts().retry_answers >= 2);
  CHECK(worker.clock().now() >= worker.start() + 30s);
  check_pixels(farm.fake);
}

TEST_CASE("exit_when_idle does not count time with work, nor time the collector cannot be reached",
          "[worker][end_to_end][exit_when_idle]") {
  // Every lease fails for a while (500): that is not "no work", so the worker keeps waiting
  // however long the failures last, then renders the job, and only then is idle.
  Farm farm({.failing_leases = 40}, [](worker::WorkerConfig& c) {
    c.exit_when_idle = 1s;
    c.backoff_initial = 100ms;
    c.backoff_max = 2s;
  });
  RunningWorker& worker = farm.worker;
  REQUIRE(worker.until([&] { return farm.fake.all_stored(); }));
  CHECK_FALSE(worker.stats().stopping);
  CHECK(worker.clock().now() >= worker.start() + 1s);  // the failures lasted longer than the idle limit
  REQUIRE(worker.wait(worker.clock().now() + worker.config().grace - 1ms) == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.stopped_idle);
  check_pixels(farm.fake);
}

TEST_CASE("with max_runtime a worker stops leasing when its time is up and submits what it has",
          "[worker][end_to_end][max_runtime]") {
  // Leases of the one job keep coming back (re-offered), so only the run time ends the worker.
  Farm farm({.submits_unavailable = true}, [](worker::WorkerConfig& c) {
    c.max_runtime = 10s;
    c.grace = 60s;
  });
  RunningWorker& worker = farm.worker;
  // The clock does not reach the end of the run time while the worker renders.
  REQUIRE(worker.until([&] { return worker.stats().tiles_rendered >= 2; }, worker.start() + 10s - 1ms));
  CHECK_FALSE(worker.stats().stopping);
  // Its submissions succeed again once it has stopped leasing: it submits them in the grace period.
  REQUIRE(worker.until([&] { return worker.stats().stopping; }));
  CHECK(worker.clock().now() >= worker.start() + 10s);
  CHECK(worker.stats().stopped_runtime);
  farm.fake.set_rules([](FakeRules& r) { r.submits_unavailable = false; });
  REQUIRE(worker.wait(worker.start() + 10s + 60s - 1ms) == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK_FALSE(s.stopped_idle);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_submitted >= 2);
}
