// dtraced::worker, unit by unit, without sockets: backoff bounds and jitter, the scene cache and
// its verification, configuration, the retry gate on a util::ManualClock (a backoff ends when the
// test moves the clock, not after real time), and what a collector's answers mean.
#include <sched.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <deque>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "async/async.h"
#include "http/client.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "protocol/worker_messages.h"
#include "render/tile.h"
#include "scene/digest.h"
#include "util/clock.h"
#include "util/cpus.h"
#include "worker/answers.h"
#include "worker/backoff.h"
#include "worker/config.h"
#include "worker/in_hand.h"
#include "worker/log_limiter.h"
#include "worker/retry_gate.h"
#include "worker/scene_cache.h"
#include "worker/worker.h"
#include "worker_testing.h"

namespace net = boost::asio;
using namespace dtraced;
using namespace dtraced::testing;
using worker::Backoff;
using worker::SceneCache;
using worker::WorkerConfig;

// ---- backoff -------------------------------------------------------------------------------------

TEST_CASE("backoff caps double from the initial delay up to the maximum and stay there", "[worker][backoff]") {
  const Backoff backoff(100ms, 10s);
  CHECK(backoff.cap(0) == 100ms);
  CHECK(backoff.cap(1) == 200ms);
  CHECK(backoff.cap(2) == 400ms);
  CHECK(backoff.cap(6) == 6400ms);
  CHECK(backoff.cap(7) == 10s);
  CHECK(backoff.cap(1000) == 10s);
  CHECK(backoff.cap(std::numeric_limits<std::uint32_t>::max()) == 10s);
  for (std::uint32_t n = 0; n < 200; ++n) {
    CHECK(backoff.cap(n) <= backoff.cap(n + 1));
    CHECK(backoff.cap(n) <= 10s);
  }
  // A maximum that is not a power-of-two multiple of the initial delay is reached exactly.
  const Backoff odd(3ms, 100ms);
  CHECK(odd.cap(5) == 96ms);
  CHECK(odd.cap(6) == 100ms);
  const Backoff flat(50ms, 50ms);
  CHECK(flat.cap(0) == 50ms);
  CHECK(flat.cap(9) == 50ms);
}

TEST_CASE("backoff delays are full jitter within [0, cap] and follow the seed", "[worker][backoff]") {
  const Backoff backoff(100ms, 10s);
  std::mt19937_64 rng(1234);
  for (std::uint32_t n : {0u, 1u, 3u, 7u, 50u}) {
    const auto cap = backoff.cap(n);
    auto low = cap, high = 0ms;
    for (int i = 0; i < 2000; ++i) {
      const auto d = backoff.delay(n, rng);
      REQUIRE(d >= 0ms);
      REQUIRE(d <= cap);
      low = std::min(low, d);
      high = std::max(high, d);
    }
    // Spread over the window, not bunched at one end.
    CHECK(low < cap / 4);
    CHECK(high > cap * 3 / 4);
  }
  std::mt19937_64 a(99), b(99), c(100);
  std::vector<std::int64_t> da, db, dc;
  for (int i = 0; i < 20; ++i) {
    da.push_back(backoff.delay(10, a).count());
    db.push_back(backoff.delay(10, b).count());
    dc.push_back(backoff.delay(10, c).count());
  }
  CHECK(da == db);
  CHECK(da != dc);
}

TEST_CASE("retry-after jitter never comes back sooner than asked, nor much later", "[worker][backoff]") {
  std::mt19937_64 rng(7);
  for (int i = 0; i < 1000; ++i) {
    const auto d = worker::jittered_retry_after(500ms, rng);
    REQUIRE(d >= 500ms);
    REQUIRE(d <= 750ms);
    const auto zero = worker::jittered_retry_after(0ms, rng);
    REQUIRE(zero >= worker::kMinRetryAfter);
    REQUIRE(zero <= worker::kMinRetryAfter * 3 / 2);
  }
}

TEST_CASE("retry-after has a floor a collector cannot spin a worker under, and a ceiling", "[worker][backoff]") {
  // A collector answering 0 ms (or 1 ms) must not get more than 20 lease requests a second from
  // a worker; one answering an hour must not park it for an hour.
  CHECK(worker::kMinRetryAfter >= 50ms);
  CHECK(worker::kMaxRetryAfter <= 60s);
  std::mt19937_64 rng(7);
  for (int i = 0; i < 1000; ++i) {
    for (const auto asked : {0ms, 1ms, 49ms}) REQUIRE(worker::jittered_retry_after(asked, rng) >= 50ms);
    const auto huge = worker::jittered_retry_after(std::chrono::milliseconds(std::chrono::hours(1)), rng);
    REQUIRE(huge >= worker::kMaxRetryAfter);
    REQUIRE(huge <= worker::kMaxRetryAfter * 3 / 2);
  }
}

// ---- log limiter ---------------------------------------------------------------------------------

TEST_CASE("identical log lines are written once, then once per interval with a count of the rest",
          "[worker][log_limiter]") {
  worker::LogLimiter limiter(30s);
  util::ManualClock clock;
  const util::TimePoint t0 = clock.now();
  CHECK(limiter.admit("refused 7", t0) == std::optional<std::uint64_t>(0));
  // 2,100 refusals a second for 15 s: nothing more is written...
  std::uint64_t written = 0;
  for (int ms = 1; ms < 15'000; ms += 1)
    written += limiter.admit("refused 7", t0 + std::chrono::milliseconds(ms)) ? 1 : 0;
  CHECK(written == 0);
  // ...while another key is written at once.
  CHECK(limiter.admit("gone 8", t0 + 1s) == std::optional<std::uint64_t>(0));
  // The first occurrence once the interval is over is written, with the count held back.
  CHECK_FALSE(limiter.admit("refused 7", t0 + 30s - 1ms));
  CHECK(limiter.admit("refused 7", t0 + 30s) == std::optional<std::uint64_t>(15'000));
  CHECK_FALSE(limiter.admit("refused 7", t0 + 31s));
  CHECK(limiter.admit("refused 7", t0 + 90s) == std::optional<std::uint64_t>(1));
  CHECK(worker::held_back_suffix(0).empty());
  CHECK_THAT(worker::held_back_suffix(15'000), Catch::Contains("15000 more like it"));
}

TEST_CASE("the log limiter remembers a bounded number of keys, forgetting the oldest", "[worker][log_limiter]") {
  worker::LogLimiter limiter(30s);
  const util::TimePoint t0 = util::ManualClock().now();
  for (std::size_t i = 0; i < worker::kMaxLoggedKeys + 10; ++i) {
    REQUIRE(limiter.admit(fmt::format("key {}", i), t0 + std::chrono::milliseconds(i)) ==
            std::optional<std::uint64_t>(0));
  }
  // The first keys were forgotten: written again as new; the latest are still held back.
  CHECK(limiter.admit("key 0", t0 + 1s) == std::optional<std::uint64_t>(0));
  CHECK_FALSE(limiter.admit(fmt::format("key {}", worker::kMaxLoggedKeys + 9), t0 + 1s));
}

// ---- scene cache -------------------------------------------------------------------------------

namespace {

worker::FramesPtr prepared(const scene::SceneDesc& desc) {
  return std::make_shared<const worker::SceneFrames>(render::AnimatedScene::prepare(desc));
}

}  // namespace

TEST_CASE("the scene cache is bounded and evicts the least recently used scene", "[worker][scene_cache]") {
  SceneCache cache(2);
  const worker::FramesPtr a = prepared(other_scene(0.5)), b = prepared(other_scene(0.6)),
                          c = prepared(other_scene(0.7));
  cache.insert("a", a);
  cache.insert("b", b);
  CHECK(cache.size() == 2);
  CHECK(cache.find("a") == a);  // a is now the most recently used
  cache.insert("c", c);         // evicts b
  CHECK(cache.size() == 2);
  CHECK(cache.contains("a"));
  CHECK_FALSE(cache.contains("b"));
  CHECK(cache.find("b") == nullptr);
  CHECK(cache.find("c") == c);

  // contains() does not count as a use: a stays the least recently used and goes next.
  CHECK(cache.contains("a"));
  cache.insert("b", b);
  CHECK_FALSE(cache.contains("a"));
  CHECK(cache.contains("b"));
  CHECK(cache.contains("c"));

  // Inserting a cached digest replaces it and makes it the most recently used.
  cache.insert("c", a);
  CHECK(cache.find("c") == a);
  cache.insert("d", b);
  CHECK(cache.contains("c"));
  CHECK_FALSE(cache.contains("b"));
  CHECK(cache.size() == 2);
}

TEST_CASE("an evicted scene stays alive while a render still uses it", "[worker][scene_cache]") {
  SceneCache cache(1);
  worker::FramesPtr in_use = prepared(other_scene(0.5));
  std::weak_ptr<const worker::SceneFrames> watch = in_use;
  cache.insert("a", in_use);
  cache.insert("b", prepared(other_scene(0.6)));
  CHECK_FALSE(cache.contains("a"));
  CHECK_FALSE(watch.expired());
  in_use.reset();
  CHECK(watch.expired());
}

TEST_CASE("prepare_scene builds a scene whose body matches its digest and refuses any other", "[worker][scene_cache]") {
  const scene::SceneDesc desc = load_tiny_scene();
  const std::string canonical = scene::canonical_json(desc);
  const std::string digest = scene::scene_digest(desc);

  SECTION("the canonical body renders exactly as the scene built locally") {
    const worker::PreparedScene prepared = worker::prepare_scene(canonical, digest, accel::best_isa());
    REQUIRE(prepared.scene != nullptr);
    CHECK(prepared.error.empty());
    const scene::TileRect rect{16, 0, 16, 16};
    CHECK(same_bits(prepared.scene->render(desc.render, rect).rgb,
                    render::render_tile(*build(desc), desc.render, rect).rgb));
  }
  SECTION("a body with other whitespace but the same scene is accepted") {
    CHECK(worker::prepare_scene(kTinyScene, digest, accel::best_isa()).scene != nullptr);
  }
  SECTION("a tampered body is refused") {
    std::string tampered = canonical;
    const std::size_t at = tampered.find("\"radius\":1");
    REQUIRE(at != std::string::npos);
    tampered.replace(at, 10, "\"radius\":2");
    const worker::PreparedScene prepared = worker::prepare_scene(tampered, digest, accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("another scene"));
  }
  SECTION("a body that does not load is refused") {
    const worker::PreparedScene prepared = worker::prepare_scene(canonical.substr(0, 40), digest, accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("does not load"));
  }
  SECTION("a valid scene under another scene's digest is refused") {
    const std::string other = scene::scene_digest(other_scene(0.5));
    CHECK(worker::prepare_scene(canonical, other, accel::best_isa()).scene == nullptr);
  }
  SECTION("a scene naming a mesh file is refused, whatever file it names") {
    // A worker never reads its own disk on a scene's behalf; canonical scenes carry meshes inline.
    const std::string with_file =
        R"({"camera": {}, "scene_objects": [{"type": "mesh", "file": "/etc/hostname"}], "scene_lights": []})";
    const worker::PreparedScene prepared = worker::prepare_scene(with_file, digest, accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("/scene_objects/0/file") && Catch::Contains("inline"));
  }
}

// ---- configuration -------------------------------------------------------------------------------

TEST_CASE("worker configuration is validated field by field", "[worker][config]") {
  const auto mentions = [](const util::Errors& errors, std::string_view field) {
    for (const util::Error& e : errors) {
      if (e.path == field && !e.message.empty() && e.to_string().starts_with(std::string(field) + ": ")) return true;
    }
    return false;
  };
  const util::Errors defaults = worker::validate(WorkerConfig{});
  CHECK(mentions(defaults, "collector_url"));
  CHECK(mentions(defaults, "token"));
  CHECK(defaults.size() == 2);

  const WorkerConfig good = test_config(7878);
  CHECK(worker::validate(good).empty());

  struct Case {
    std::string_view field;
    std::function<void(WorkerConfig&)> change;
  };
  const std::vector<Case> cases = {
      {"collector_url", [](WorkerConfig& c) { c.collector_url = "ftp://example.org"; }},
      {"ca_file", [](WorkerConfig& c) { c.collector_url = "https://example.org"; }},
      {"collector_url", [](WorkerConfig& c) { c.collector_url = "http://host/path"; }},
      {"token", [](WorkerConfig& c) { c.token = "two words"; }},
      {"token", [](WorkerConfig& c) { c.token = "line\n"; }},
      {"token", [](WorkerConfig& c) { c.token = std::string(worker::kMaxTokenBytes + 1, 'x'); }},
      {"name", [](WorkerConfig& c) { c.name = "tab\there"; }},
      {"name", [](WorkerConfig& c) { c.name = std::string(protocol::kMaxWorkerNameBytes + 1, 'n'); }},
      {"threads", [](WorkerConfig& c) { c.threads = protocol::kMaxWorkerThreads + 1; }},
      {"scene_cache", [](WorkerConfig& c) { c.scene_cache = 0; }},
      {"scene_cache", [](WorkerConfig& c) { c.scene_cache = worker::kMaxSceneCache + 1; }},
      {"grace", [](WorkerConfig& c) { c.grace = worker::kMaxGrace + 1s; }},
      {"grace", [](WorkerConfig& c) { c.grace = -1s; }},
      {"timeouts.connect", [](WorkerConfig& c) { c.timeouts.connect = 0ms; }},
      {"timeouts.read", [](WorkerConfig& c) { c.timeouts.read = worker::kMaxClientTimeout + 1ms; }},
      {"timeouts.handshake", [](WorkerConfig& c) { c.timeouts.handshake = 0ms; }},
      {"backoff_initial", [](WorkerConfig& c) { c.backoff_initial = 0ms; }},
      {"backoff_max", [](WorkerConfig& c) { c.backoff_max = c.backoff_initial - 1ms; }},
      {"max_unacknowledged", [](WorkerConfig& c) { c.max_unacknowledged = worker::kMaxUnacknowledged + 1; }},
  };
  for (const Case& c : cases) {
    WorkerConfig config = good;
    c.change(config);
    const util::Errors errors = worker::validate(config);
    INFO(c.field);
    CHECK(errors.size() == 1);
    CHECK(mentions(errors, c.field));
  }

  // Worker::create refuses what validate() refuses, with the same errors, and builds nothing.
  WorkerConfig bad = good;
  bad.scene_cache = 0;
  bad.token.clear();
  const auto refused = worker::Worker::create(bad);
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error() == worker::validate(bad));
  CHECK(refused.error().size() == 2);
  CHECK(worker::Worker::create(good).ok());
}

TEST_CASE("worker ca_file is read by create, its problems naming the file", "[worker][config]") {
  WorkerConfig config = test_config(7878);
  config.collector_url = "https://127.0.0.1:7878";
  config.ca_file = "/nonexistent/dtraced/ca.pem";
  CHECK(worker::validate(config).empty());
  auto refused = worker::Worker::create(config);
  REQUIRE_FALSE(refused.ok());
  REQUIRE(refused.error().size() == 1);
  CHECK(refused.error().front().path == "ca_file");
  CHECK_THAT(refused.error().front().to_string(), Catch::Contains("/nonexistent/dtraced/ca.pem"));

  config.ca_file = "/dev/null";  // readable, but no certificate in it
  refused = worker::Worker::create(config);
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error().front().path == "ca_file");
  CHECK_THAT(refused.error().front().to_string(), Catch::Contains("the CA in /dev/null is empty"));

  // Plain HTTP reads no CA file.
  config.collector_url = "http://127.0.0.1:7878";
  config.ca_file = "/nonexistent/dtraced/ca.pem";
  CHECK(worker::Worker::create(config).ok());
}

TEST_CASE("worker defaults are resolved from the host", "[worker][config]") {
  WorkerConfig config = test_config(7878);
  config.name.clear();
  config.threads = 0;
  config.max_unacknowledged = 0;
  const WorkerConfig resolved = worker::resolve_defaults(config);
  CHECK(resolved.threads >= 1);
  CHECK(resolved.max_unacknowledged == worker::kInHandPerThread * resolved.threads);
  CHECK_FALSE(resolved.name.empty());
  CHECK(resolved.name.size() <= protocol::kMaxWorkerNameBytes);
  CHECK(resolved.name == worker::default_worker_name());
  CHECK(worker::validate(resolved).empty());
}

TEST_CASE("the default worker name tells Slurm array tasks apart", "[worker][config]") {
  // A stand-in environment: the variables in `vars`, nothing else.
  const auto env_of = [](std::map<std::string, std::string> vars) {
    return [vars = std::move(vars)](const char* key) -> const char* {
      const auto it = vars.find(key);
      return it == vars.end() ? nullptr : it->second.c_str();
    };
  };
  // Outside Slurm: HOST-PID.
  const std::string plain = worker::default_worker_name(env_of({}));
  CHECK(plain.ends_with(fmt::format("-{}", ::getpid())));
  const std::string host = plain.substr(0, plain.size() - fmt::format("-{}", ::getpid()).size());
  CHECK_FALSE(host.empty());
  // A task of a job array: HOST-JOB_TASK, whatever SLURM_JOB_ID says (each task has its own).
  CHECK(worker::default_worker_name(
            env_of({{"SLURM_ARRAY_JOB_ID", "4242"}, {"SLURM_ARRAY_TASK_ID", "7"}, {"SLURM_JOB_ID", "4249"}})) ==
        host + "-4242_7");
  // A plain job: HOST-JOB; a step of several tasks adds the task's rank.
  CHECK(worker::default_worker_name(env_of({{"SLURM_JOB_ID", "77"}})) == host + "-77");
  CHECK(worker::default_worker_name(env_of({{"SLURM_JOB_ID", "77"}, {"SLURM_NTASKS", "1"}, {"SLURM_PROCID", "0"}})) ==
        host + "-77");
  CHECK(worker::default_worker_name(env_of({{"SLURM_JOB_ID", "77"}, {"SLURM_NTASKS", "4"}, {"SLURM_PROCID", "3"}})) ==
        host + "-77.3");
  // An array id without its task is no array: the job id names it.
  CHECK(worker::default_worker_name(env_of({{"SLURM_ARRAY_JOB_ID", "4242"}, {"SLURM_JOB_ID", "4249"}})) ==
        host + "-4249");
  // Whatever the variables hold, the name stays a valid one: printable, no spaces, bounded.
  const std::string odd = worker::default_worker_name(
      env_of({{"SLURM_ARRAY_JOB_ID", std::string(300, 'x') + " \t"}, {"SLURM_ARRAY_TASK_ID", "1 2"}}));
  CHECK(odd.size() <= protocol::kMaxWorkerNameBytes);
  CHECK(odd.find(' ') == std::string::npos);
  WorkerConfig config = test_config(7878);
  config.name = odd;
  CHECK(worker::validate(config).empty());
}

TEST_CASE("the default thread count is the CPUs of the affinity mask", "[worker][config]") {
  // On a thread of its own narrowed to one CPU (as `taskset -c N` or a Slurm allocation narrows a
  // process), every-core means that one CPU.
  std::uint32_t narrowed = 0, resolved = 0;
  bool pinned = false;
  std::thread probe([&] {
    cpu_set_t set;
    CPU_ZERO(&set);
    if (::sched_getaffinity(0, sizeof set, &set) != 0) return;  // no Catch2 assertions off the test's thread
    int first = 0;
    while (!CPU_ISSET(first, &set)) ++first;
    cpu_set_t one;
    CPU_ZERO(&one);
    CPU_SET(first, &one);
    pinned = ::sched_setaffinity(0, sizeof one, &one) == 0;
    narrowed = util::usable_cpus();
    WorkerConfig config = test_config(7878);
    config.threads = 0;
    resolved = worker::resolve_defaults(config).threads;
  });
  probe.join();
  REQUIRE(pinned);
  CHECK(narrowed == 1);
  CHECK(resolved == 1);
  // This thread's own mask is the process's: at least one CPU, at most the machine's.
  CHECK(util::usable_cpus() >= 1);
  CHECK(util::usable_cpus() <= std::max(1u, std::thread::hardware_concurrency()));
}

TEST_CASE("exit_when_idle and max_runtime are bounded", "[worker][config]") {
  WorkerConfig config = test_config(7878);
  config.exit_when_idle = worker::kMaxExitWhenIdle;
  config.max_runtime = worker::kMaxRuntime;
  CHECK(worker::validate(config).empty());
  config.exit_when_idle = worker::kMaxExitWhenIdle + 1s;
  config.max_runtime = worker::kMaxRuntime + 1s;
  const util::Errors errors = worker::validate(config);
  REQUIRE(errors.size() == 2);
  CHECK(errors[0].path == "exit_when_idle");
  CHECK(errors[1].path == "max_runtime");
}

TEST_CASE("start_jitter is bounded, and the start delay drawn is within [0, start_jitter]",
          "[worker][config][limits]") {
  WorkerConfig config = test_config(7878);
  CHECK(config.start_jitter == 0ms);  // off by default
  config.start_jitter = worker::kMaxStartJitter;
  CHECK(worker::validate(config).empty());
  config.start_jitter = worker::kMaxStartJitter + 1ms;
  const util::Errors errors = worker::validate(config);
  REQUIRE(errors.size() == 1);
  CHECK(errors[0].path == "start_jitter");

  std::mt19937_64 rng(12345);
  CHECK(worker::start_delay(0ms, rng) == 0ms);
  for (const auto max : {1ms, 7ms, 1000ms, worker::kMaxStartJitter}) {
    std::chrono::milliseconds lowest = max, highest = 0ms;
    for (int i = 0; i < 2000; ++i) {
      const auto d = worker::start_delay(max, rng);
      REQUIRE(d >= 0ms);
      REQUIRE(d <= max);
      lowest = std::min(lowest, d);
      highest = std::max(highest, d);
    }
    // Spread over the range, not stuck at one end (2,000 draws: a failure here is not chance).
    CHECK(lowest <= max / 10);
    CHECK(highest >= max - max / 10);
  }
  // Two workers seeded differently start at different times.
  std::mt19937_64 a(1), b(2);
  CHECK(worker::start_delay(60'000ms, a) != worker::start_delay(60'000ms, b));
}

// ---- tiles in hand -------------------------------------------------------------------------------

TEST_CASE("the tiles in hand are bounded by count, and the rendered ones also by bytes", "[worker][in_hand]") {
  net::io_context io;
  worker::InHand in_hand(io.get_executor(), /*limit=*/3, /*byte_limit=*/1000);
  worker::InHand::Reservation a = in_hand.reserve();
  worker::InHand::Reservation b = in_hand.reserve();
  CHECK_FALSE(in_hand.full());
  a.hold(600);  // rendered: its bytes count until it is released
  CHECK(in_hand.bytes() == 600);
  CHECK_FALSE(in_hand.full());
  b.hold(400);  // 1000 bytes awaiting acknowledgement: full with 2 of 3 tiles
  CHECK(in_hand.full());
  worker::InHand::Reservation moved = std::move(a);  // the bytes move with the reservation
  CHECK(in_hand.bytes() == 1000);
  moved.reset();
  CHECK(in_hand.count() == 1);
  CHECK(in_hand.bytes() == 400);
  CHECK_FALSE(in_hand.full());
  worker::InHand::Reservation c = in_hand.reserve();
  worker::InHand::Reservation d = in_hand.reserve();
  CHECK(in_hand.full());  // 3 tiles, 400 bytes: the count bound
  CHECK(in_hand.peak() == 3);
  b.reset();
  c.reset();
  d.reset();
  CHECK(in_hand.count() == 0);
  CHECK(in_hand.bytes() == 0);
}

// ---- the retry gate, on a ManualClock ------------------------------------------------------------

namespace {

// A RetryGate on an io_context that the test runs by hand, and requests that wait at it. Nothing
// here waits on real time: a request gets out when the test has moved the clock far enough.
struct GateRig {
  static constexpr std::uint64_t kSeed = 5;

  // A request at the gate: `attempt` is set once the gate lets it out (nullopt: stopped).
  struct Request {
    bool done = false;
    std::optional<worker::RetryGate::Attempt> attempt;
  };

  explicit GateRig(Backoff b = Backoff(100ms, 400ms)) : backoff(b), gate(io.get_executor(), clock, b, rng) {}

  // Every coroutine ends while the gate and its requests are still there, even after a failed
  // REQUIRE left some waiting.
  ~GateRig() {
    stop.set();
    settle();
  }

  // A new request at the gate, run until it waits or is let out.
  Request& enter() {
    Request* r = &requests.emplace_back();  // a deque: it stays where it is
    net::co_spawn(
        io,
        [this, r]() -> async::Awaitable<> {
          std::optional<worker::RetryGate::Attempt> got = co_await gate.enter(stop);
          if (got) r->attempt.emplace(std::move(*got));  // an Attempt moves, but is not assigned
          r->done = true;
        },
        async::log_failure("a request at the gate"));
    settle();
    return *r;
  }

  // Runs the loop until every coroutine waits (for the clock, the gate or the stop).
  void settle() {
    io.restart();
    io.poll();
  }

  // Whether `r` waits at the gate until exactly `deadline` on the clock: still waiting 1 ms before
  // it, let out at it.
  bool waits_until(const Request& r, util::TimePoint deadline) {
    if (r.done || clock.next_deadline() != deadline) return false;
    clock.advance_to(deadline - 1ms);
    settle();
    if (r.done) return false;
    clock.advance_to(deadline);
    settle();
    return r.done;
  }

  // The delays the gate draws, in order: the same generator from the same seed.
  std::vector<std::chrono::milliseconds> delays(std::uint32_t n) const {
    std::mt19937_64 replica(kSeed);
    std::vector<std::chrono::milliseconds> out;
    for (std::uint32_t failures = 0; failures < n; ++failures) out.push_back(backoff.delay(failures, replica));
    return out;
  }

  Backoff backoff;
  util::ManualClock clock;
  net::io_context io;
  std::mt19937_64 rng{kSeed};
  async::Event stop{io.get_executor()};
  worker::RetryGate gate;
  std::deque<Request> requests;  // after the gate: their Attempts go back to it
};

}  // namespace

TEST_CASE("after a failure the next request waits on the clock until its jittered backoff is over",
          "[worker][retry_gate]") {
  GateRig rig;
  const auto d = rig.delays(1).at(0);
  REQUIRE(d > 1ms);  // the seed draws a real wait, so that "not before" means something

  GateRig::Request& first = rig.enter();
  REQUIRE(first.done);  // nothing has failed: out at once, and not as a probe
  CHECK_FALSE(first.attempt->probe());
  const auto failed_at = rig.clock.now();
  CHECK(rig.gate.failed(*first.attempt) == 1);

  GateRig::Request& second = rig.enter();
  REQUIRE(rig.waits_until(second, failed_at + d));
  CHECK(second.attempt->probe());
  CHECK(rig.clock.sleepers() == 0);
}

TEST_CASE("requests in flight together fail as one round and back off once", "[worker][retry_gate]") {
  GateRig rig;
  GateRig::Request& a = rig.enter();
  GateRig::Request& b = rig.enter();
  REQUIRE((a.done && b.done));
  const auto failed_at = rig.clock.now();
  CHECK(rig.gate.failed(*a.attempt) == 1);
  rig.clock.advance(1ms);
  CHECK(rig.gate.failed(*b.attempt) == 0);  // the same outage: no second, longer backoff

  const auto d = rig.delays(1).at(0);
  REQUIRE(d > 1ms);
  GateRig::Request& next = rig.enter();
  CHECK(rig.waits_until(next, failed_at + d));  // the first failure's backoff, unchanged
}

TEST_CASE("while the collector fails, one probe at a time goes out, oldest first, and a success frees all",
          "[worker][retry_gate]") {
  GateRig rig;
  GateRig::Request& first = rig.enter();
  CHECK(rig.gate.failed(*first.attempt) == 1);
  first.attempt.reset();

  GateRig::Request& a = rig.enter();
  GateRig::Request& b = rig.enter();
  GateRig::Request& c = rig.enter();
  rig.clock.advance(rig.backoff.cap(0));
  rig.settle();
  REQUIRE(a.done);  // the oldest request probes; the others wait for its outcome
  CHECK(a.attempt->probe());
  CHECK_FALSE(b.done);
  CHECK_FALSE(c.done);

  // The probe fails: the next backoff is drawn from the doubled window, and b probes after it.
  CHECK(rig.gate.failed(*a.attempt) == 2);
  rig.clock.advance(rig.backoff.cap(1));
  rig.settle();
  REQUIRE(b.done);
  CHECK(b.attempt->probe());
  CHECK_FALSE(c.done);

  // The collector answers: the failures end, and every request waiting goes out at once.
  CHECK(rig.gate.succeeded(*b.attempt) == 2);
  rig.settle();
  REQUIRE(c.done);
  CHECK_FALSE(c.attempt->probe());
  GateRig::Request& d = rig.enter();
  CHECK(d.done);
  CHECK(rig.clock.sleepers() == 0);
}

TEST_CASE("a collector without work holds requests for its retry-after, then lets one ask at a time",
          "[worker][retry_gate]") {
  GateRig rig;
  rig.gate.idle_for(50ms);
  const auto idle_from = rig.clock.now();
  GateRig::Request& a = rig.enter();
  GateRig::Request& b = rig.enter();
  REQUIRE(rig.waits_until(a, idle_from + 50ms));
  CHECK(a.attempt->probe());
  CHECK_FALSE(b.done);

  rig.gate.busy();  // work again: no more probing
  rig.settle();
  REQUIRE(b.done);
  CHECK_FALSE(b.attempt->probe());
}

TEST_CASE("refused tiles hold leases back for a backoff that grows until a tile is accepted", "[worker][retry_gate]") {
  GateRig rig(Backoff(100ms, 10s));
  // Leases succeed (the collector answers them) but their tiles are refused: without refusals
  // counting on their own, the gate would let the next lease out at once, forever.
  std::vector<std::chrono::milliseconds> waits;
  for (std::uint32_t n = 1; n <= 12; ++n) {
    GateRig::Request& lease = rig.enter();
    const util::TimePoint asked_at = rig.clock.now();
    if (!lease.done) {
      const std::optional<util::TimePoint> wake = rig.clock.next_deadline();
      REQUIRE(wake);
      REQUIRE(rig.waits_until(lease, *wake));
    }
    REQUIRE(lease.done);
    CHECK(lease.attempt->probe() == (n > 1));  // one at a time once a tile was refused
    waits.push_back(std::chrono::duration_cast<std::chrono::milliseconds>(rig.clock.now() - asked_at));
    CHECK(rig.gate.succeeded(*lease.attempt) == 0);  // the lease itself was answered
    CHECK(rig.gate.refused() == n);
  }
  // The waits are the backoff delays of 0, 1, 2, ... refusals in a row (same generator, same
  // seed), so their caps double up to the maximum.
  const auto expected = rig.delays(11);
  for (std::size_t i = 1; i < waits.size(); ++i) CHECK(waits[i] == expected[i - 1]);
  std::chrono::milliseconds total{0};
  for (const auto w : waits) total += w;
  CHECK(total >= 10s);  // 12 refusals take seconds, not microseconds

  // An accepted tile ends the refusals: every request goes out at once again.
  rig.gate.refused();
  CHECK(rig.gate.accepted() == 13);
  GateRig::Request& a = rig.enter();
  GateRig::Request& b = rig.enter();
  CHECK((a.done && b.done));
  CHECK_FALSE(a.attempt->probe());
  CHECK(rig.gate.accepted() == 0);
}

TEST_CASE("a stop ends every wait at the gate and forgets its wake on the clock", "[worker][retry_gate]") {
  GateRig rig(Backoff(10s, 10s));
  GateRig::Request& first = rig.enter();
  CHECK(rig.gate.failed(*first.attempt) == 1);
  first.attempt.reset();

  REQUIRE(rig.delays(1).at(0) > 0ms);

  GateRig::Request& waiting = rig.enter();
  REQUIRE(rig.clock.sleepers() == 1);
  rig.stop.set();
  rig.settle();
  REQUIRE(waiting.done);
  CHECK_FALSE(waiting.attempt.has_value());
  CHECK(rig.clock.sleepers() == 0);
}

// ---- what the collector's answers mean -----------------------------------------------------------

namespace {

http::ClientResult answer(http::Response response) {
  http::ClientResult result;
  result.response = std::move(response);
  return result;
}

http::ClientResult json_answer(http::Status status, std::string body) {
  return answer(http::make_text_response(status, std::move(body), http::kJsonContentType));
}

http::ClientResult refused() {
  http::ClientResult result;
  result.error = http::ClientError::kConnect;
  result.message = "connecting to 127.0.0.1:1: connection refused";
  return result;
}

}  // namespace

TEST_CASE("a submission's answer decides whether its tile is kept, dropped or sent again", "[worker][answers]") {
  using worker::classify_submit;
  using worker::SubmitVerdict;
  const auto verdict = [](const http::ClientResult& r) { return classify_submit(r).verdict; };

  CHECK(verdict(json_answer(http::Status::ok, protocol::encode(protocol::SubmitResult::kStored))) ==
        SubmitVerdict::kAcknowledged);
  CHECK(
      classify_submit(json_answer(http::Status::ok, protocol::encode(protocol::SubmitResult::kAlreadyDone))).message ==
      "already_done");
  CHECK(verdict(json_answer(http::Status::ok, protocol::encode(protocol::SubmitResult::kJobGone))) ==
        SubmitVerdict::kJobGone);
  CHECK(verdict(answer(http::make_error(http::Status::gone, "job 7 was cancelled"))) == SubmitVerdict::kJobGone);

  // The collector's state, not the tile's: kept and sent again.
  CHECK(verdict(refused()) == SubmitVerdict::kRetry);
  CHECK(classify_submit(refused()).message == refused().message);
  for (const http::Status status : {http::Status::request_timeout, http::Status::too_many_requests,
                                    http::Status::internal_server_error, http::Status::service_unavailable}) {
    INFO(static_cast<unsigned>(status));
    CHECK(verdict(answer(http::make_error(status, "later"))) == SubmitVerdict::kRetry);
  }
  const auto unauthorized = classify_submit(answer(http::make_error(http::Status::unauthorized, "wrong token")));
  CHECK(unauthorized.verdict == SubmitVerdict::kRetry);
  CHECK(unauthorized.token_rejected);
  // Probably stored, but it cannot be known: sending it again is harmless.
  CHECK(verdict(json_answer(http::Status::ok, "{\"result\": 3}")) == SubmitVerdict::kRetry);
  CHECK(verdict(answer(http::make_text_response(http::Status::found, ""))) == SubmitVerdict::kRetry);

  // Any other 4xx says the tile itself is wrong: sending it again cannot help.
  const auto bad = classify_submit(answer(http::make_error(http::Status::bad_request, "too many pixels", "/rgb")));
  CHECK(bad.verdict == SubmitVerdict::kRejected);
  CHECK(bad.message == "HTTP 400: too many pixels (at /rgb)");
  CHECK(verdict(answer(http::make_error(http::Status::not_found, "no such tile"))) == SubmitVerdict::kRejected);
}

TEST_CASE("a lease answer is a lease, a retry-after, or a failure to retry with backoff", "[worker][answers]") {
  using worker::classify_lease;
  const scene::SceneDesc desc = load_tiny_scene();
  const protocol::Lease lease{kJob, scene::scene_digest(desc), 1, scene::TileRect{16, 0, 16, 16}, desc.render};

  const auto leased = classify_lease(json_answer(http::Status::ok, protocol::encode(protocol::LeaseReply{lease})));
  CHECK(leased.error.empty());
  CHECK(leased.lease == lease);
  CHECK_FALSE(leased.retry_after);

  const auto idle =
      classify_lease(json_answer(http::Status::ok, protocol::encode(protocol::LeaseReply{protocol::RetryAfter{250}})));
  CHECK(idle.error.empty());
  CHECK_FALSE(idle.lease);
  CHECK(idle.retry_after == 250ms);

  const auto rejected = classify_lease(answer(http::make_error(http::Status::unauthorized, "wrong token")));
  CHECK(rejected.token_rejected);
  CHECK(rejected.error == "credential rejected (HTTP 401: wrong token)");
  CHECK(classify_lease(refused()).error == refused().message);
  CHECK(classify_lease(answer(http::make_error(http::Status::service_unavailable, "busy"))).error == "HTTP 503: busy");
  CHECK_THAT(classify_lease(json_answer(http::Status::ok, "{\"lease\": 1}")).error,
             Catch::StartsWith("malformed lease reply: "));
}

TEST_CASE("a gone answer is a refusal only for a job leased again after it was answered gone", "[worker][answers]") {
  worker::GoneAnswers answers;
  CHECK_FALSE(answers.refusal(7, /*marked=*/false));  // the news: job 7 ended
  CHECK_FALSE(answers.refusal(7, /*marked=*/true));   // tiles in flight when it came
  CHECK(answers.refusal(7, /*marked=*/false));        // leased again since, and still gone
  CHECK(answers.refusal(7, /*marked=*/false));
  CHECK_FALSE(answers.refusal(8, /*marked=*/false));  // another job's end
  // Memory is bounded: a job forgotten is news again.
  for (std::uint64_t job = 100; job < 100 + worker::kRememberedGoneJobs; ++job) answers.refusal(job, false);
  CHECK_FALSE(answers.refusal(7, /*marked=*/false));
}

TEST_CASE("an unexpected answer is quoted short and printable in the logs", "[worker][answers]") {
  CHECK(worker::describe_answer(http::make_text_response(http::Status::bad_gateway, "")) == "HTTP 502");
  const std::string body = "bad\x01gate\n" + std::string(500, 'x');
  const std::string quoted = worker::describe_answer(http::make_text_response(http::Status::bad_gateway, body));
  CHECK(quoted.starts_with("HTTP 502: bad?gate?xxx"));
  CHECK(quoted.size() == std::string_view("HTTP 502: ").size() + worker::kMaxQuotedBodyBytes);
  CHECK(worker::should_log_failure(1));
  CHECK_FALSE(worker::should_log_failure(0));
  CHECK_FALSE(worker::should_log_failure(2));
  CHECK(worker::should_log_failure(worker::kLogEveryNthFailure));
}

TEST_CASE("a retry-after says the collector has finished only when its header is exactly 1", "[worker][answers]") {
  using worker::classify_lease;
  auto idle = [](std::optional<std::string_view> header) {
    http::Response res = http::make_text_response(
        http::Status::ok, protocol::encode(protocol::LeaseReply{protocol::RetryAfter{250}}), http::kJsonContentType);
    if (header) res.set(protocol::kFinishedHeader, *header);
    return classify_lease(answer(std::move(res)));
  };
  const auto finished = idle("1");
  CHECK(finished.error.empty());
  CHECK(finished.retry_after == 250ms);
  CHECK(finished.collector_finished);
  // Not finished, and still an ordinary retry-after: no header (an older collector), "0", or any
  // value that is not exactly "1" (a garbled header never ends a worker).
  for (const std::optional<std::string_view> value :
       {std::optional<std::string_view>{}, std::optional<std::string_view>{"0"},
        std::optional<std::string_view>{"true"}, std::optional<std::string_view>{""},
        std::optional<std::string_view>{"01"}}) {
    INFO(value.value_or("(none)"));
    const auto other = idle(value);
    CHECK(other.error.empty());
    CHECK(other.retry_after == 250ms);
    CHECK_FALSE(other.collector_finished);
  }
  // A lease is a lease, whatever headers come with it.
  const scene::SceneDesc desc = load_tiny_scene();
  http::Response leased =
      http::make_text_response(http::Status::ok,
                               protocol::encode(protocol::LeaseReply{protocol::Lease{
                                   kJob, scene::scene_digest(desc), 0, scene::TileRect{0, 0, 16, 16}, desc.render}}),
                               http::kJsonContentType);
  leased.set(protocol::kFinishedHeader, "1");
  const auto lease = classify_lease(answer(std::move(leased)));
  CHECK(lease.lease);
  CHECK_FALSE(lease.collector_finished);
}
