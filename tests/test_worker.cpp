// dtraced::worker: backoff bounds, the scene cache and its verification, configuration, and whole
// workers against a fake collector (http::Server on 127.0.0.1, ephemeral port) that fails in
// chosen ways: absent, 500s, a 503 scene, 503 submissions, a restart, a gone job, a bad token, a
// tampered scene. Every wait is bounded (kBound) and waits for an event or a counter, never for a
// guessed amount of time; nothing asserts on timing.
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstring>
#include <functional>
#include <future>
#include <limits>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <variant>
#include <vector>

#include <boost/asio/as_tuple.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/asio/use_future.hpp>
#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "http/server.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "worker/backoff.h"
#include "worker/config.h"
#include "worker/scene_cache.h"
#include "worker/worker.h"

namespace {

namespace net = boost::asio;
using namespace std::chrono_literals;
using dtraced::http::Request;
using dtraced::http::Response;
using dtraced::http::Server;
using dtraced::http::Status;
using dtraced::worker::Backoff;
using dtraced::worker::RunOptions;
using dtraced::worker::SceneCache;
using dtraced::worker::ScenePtr;
using dtraced::worker::Worker;
using dtraced::worker::WorkerConfig;
using dtraced::worker::WorkerStats;

// The longest any single wait in these tests may take before the test fails instead of hanging.
constexpr auto kBound = 30s;
constexpr std::string_view kToken = "test-token-0123456789";
constexpr std::uint64_t kJob = 7;
constexpr std::uint32_t kTileSize = 16;

// 32 x 32 pixels in 16-pixel tiles: four tiles. Two samples and a reflective sphere, so the
// sampling hash and the secondary rays are both exercised.
constexpr std::string_view kTinyScene = R"({
  "camera": {"position": [0, 0.5, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 40},
  "render": {"width": 32, "height": 32, "samples": 2, "max_depth": 3, "background": [0.1, 0.2, 0.3], "seed": 11},
  "scene_objects": [
    {"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0], "material": {"color": [0.8, 0.8, 0.8]}},
    {"type": "sphere", "loc": [0, 0, 0], "radius": 1,
     "material": {"color": [0.9, 0.3, 0.2], "specular": 0.3, "reflectivity": 0.2}}
  ],
  "scene_lights": [{"type": "point", "loc": [4, 5, 5], "intensity": 60}]
})";

dtraced::scene::SceneDesc load_tiny_scene() {
  dtraced::scene::LoadResult loaded = dtraced::scene::load_scene_string(kTinyScene, "tiny");
  REQUIRE(loaded.ok());
  return *loaded.scene;
}

// The same scene with the sphere's radius changed: another digest.
dtraced::scene::SceneDesc other_scene(double radius) {
  dtraced::scene::SceneDesc desc = load_tiny_scene();
  desc.objects.at(1).sphere.radius = radius;
  return desc;
}

ScenePtr build(const dtraced::scene::SceneDesc& desc) {
  return std::make_shared<const dtraced::render::RenderScene>(dtraced::render::RenderScene::build(desc));
}

bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

// Polls `condition` until it holds or kBound passes: for state only visible through a counter.
bool eventually(const std::function<bool()>& condition) {
  const auto deadline = std::chrono::steady_clock::now() + kBound;
  while (!condition()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(2ms);
  }
  return true;
}

// A port nobody listens on (just released by the kernel; another process grabbing it in between
// is possible but not on a test machine's loopback in practice).
std::uint16_t unused_port() {
  net::io_context io;
  net::ip::tcp::acceptor acceptor(io, net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));
  return acceptor.local_endpoint().port();
}

// ---- the fake collector ------------------------------------------------------------------------

struct FakeRules {
  bool reject_token = false;                  // every request: 401
  int failing_leases = 0;                     // the first N lease requests: 500
  int failing_scene_fetches = 0;              // the first N scene fetches: 503
  bool tamper_scene = false;                  // serve another scene under the digest
  std::set<std::uint32_t> fail_first_submit;  // these tiles' first submission: 503
  bool submits_unavailable = false;           // every submission: 503
  bool job_gone = false;                      // submissions: 410; after the first, no more leases
  bool hang_leases = false;                   // lease requests get no answer until the server stops
  bool hang_submits = false;                  // submissions get no answer until the server stops
  // A tile leased but not stored is offered again after this many "retry after" answers (the
  // fake's stand-in for the real queue's re-offer bound; the worker drops leases it cannot use).
  std::uint32_t reoffer_after = 3;
};

struct FakeCounts {
  std::uint64_t lease_requests = 0;
  std::uint64_t leases = 0;
  std::uint64_t scene_requests = 0;
  std::uint64_t unauthorized = 0;
  std::uint64_t acknowledged = 0;  // 200 stored or already_done
  std::uint64_t already_done = 0;
  std::uint64_t gone_answers = 0;
  std::uint64_t hung = 0;                      // requests left without an answer
  std::vector<std::uint64_t> submit_requests;  // per tile
  std::vector<std::uint64_t> stored;           // per tile: how often "stored" was answered
  std::vector<std::string> problems;           // anything the worker sent that it should not have
};

// One job (kJob) of the tiny scene. The handler's state is guarded by a mutex: the server runs it
// on its own thread and the test reads it from the main thread.
class FakeCollector {
 public:
  explicit FakeCollector(dtraced::scene::SceneDesc desc = load_tiny_scene())
      : desc_(std::move(desc)),
        canonical_(dtraced::scene::canonical_json(desc_)),
        digest_(dtraced::scene::scene_digest(desc_)),
        rects_(dtraced::scene::TileGrid(desc_.render.width, desc_.render.height, kTileSize).all()) {
    REQUIRE(rects_.size() == 4);
    counts_.submit_requests.assign(rects_.size(), 0);
    counts_.stored.assign(rects_.size(), 0);
    leased_.assign(rects_.size(), false);
    idle_since_lease_.assign(rects_.size(), 0);
    pixels_.resize(rects_.size());
    spp_.resize(rects_.size());
  }

  Server::Handler handler() {
    return [this](Request req) -> net::awaitable<Response> {
      if (should_hang(req)) {
        // Until the server's stop cancels this handler.
        net::steady_timer never(co_await net::this_coro::executor, net::steady_timer::time_point::max());
        co_await never.async_wait(net::as_tuple(net::use_awaitable));
        co_return dtraced::http::make_error(Status::service_unavailable, "stopping");
      }
      co_return handle(req);
    };
  }

  void set_rules(const std::function<void(FakeRules&)>& change) {
    std::lock_guard lock(mu_);
    change(rules_);
  }

  FakeCounts counts() const {
    std::lock_guard lock(mu_);
    return counts_;
  }

  bool all_stored() const {
    std::lock_guard lock(mu_);
    for (const std::uint64_t n : counts_.stored) {
      if (n == 0) return false;
    }
    return true;
  }

  bool every_tile_submitted() const {
    std::lock_guard lock(mu_);
    for (const std::uint64_t n : counts_.submit_requests) {
      if (n == 0) return false;
    }
    return true;
  }

  std::vector<std::vector<float>> pixels() const {
    std::lock_guard lock(mu_);
    return pixels_;
  }

  std::vector<std::vector<std::uint32_t>> spp() const {
    std::lock_guard lock(mu_);
    return spp_;
  }

  const std::vector<dtraced::scene::TileRect>& rects() const { return rects_; }
  const dtraced::scene::SceneDesc& desc() const { return desc_; }

 private:
  Response handle(const Request& req) {
    std::lock_guard lock(mu_);
    const std::string expected = fmt::format("Bearer {}", kToken);
    if (rules_.reject_token || req[boost::beast::http::field::authorization] != expected) {
      ++counts_.unauthorized;
      return dtraced::http::make_error(Status::unauthorized, "missing or wrong token");
    }
    const std::string_view target = req.target();
    const std::string tile_prefix = fmt::format("/v1/jobs/{}/tiles/", kJob);
    if (req.method() == dtraced::http::Verb::post && target == "/v1/lease") return lease(req);
    if (req.method() == dtraced::http::Verb::get && target.starts_with("/v1/scenes/")) {
      return scene(target.substr(std::string_view("/v1/scenes/").size()));
    }
    if (req.method() == dtraced::http::Verb::put && target.starts_with(tile_prefix)) {
      return submit(target.substr(tile_prefix.size()), req.body());
    }
    counts_.problems.push_back(fmt::format("unexpected request {} {}", std::string(req.method_string()), target));
    return dtraced::http::make_error(Status::not_found, "no such route");
  }

  bool should_hang(const Request& req) {
    std::lock_guard lock(mu_);
    if (rules_.hang_leases && req.target() == "/v1/lease") {
      ++counts_.hung;
      return true;
    }
    if (rules_.hang_submits && req.method() == dtraced::http::Verb::put) {
      ++counts_.hung;
      return true;
    }
    return false;
  }

  static Response json(Status status, std::string body) {
    return dtraced::http::make_text_response(status, std::move(body), dtraced::http::kJsonContentType);
  }

  Response lease(const Request& req) {
    ++counts_.lease_requests;
    const auto decoded = dtraced::protocol::decode_lease_request(req.body());
    if (!decoded || decoded.value().worker != "test-worker" || decoded.value().threads != 2) {
      counts_.problems.push_back(fmt::format("bad lease request: {}", req.body()));
      return dtraced::http::make_error(Status::bad_request, "bad lease request");
    }
    if (rules_.failing_leases > 0) {
      --rules_.failing_leases;
      return dtraced::http::make_error(Status::internal_server_error, "failing on purpose");
    }
    std::optional<std::uint32_t> tile;
    if (!(rules_.job_gone && counts_.gone_answers > 0)) {
      for (std::uint32_t t = 0; t < rects_.size() && !tile; ++t) {
        if (!leased_[t]) tile = t;
      }
      for (std::uint32_t t = 0; t < rects_.size() && !tile; ++t) {
        if (counts_.stored[t] == 0 && idle_since_lease_[t] >= rules_.reoffer_after) tile = t;
      }
    }
    if (!tile) {
      for (std::uint32_t t = 0; t < rects_.size(); ++t) ++idle_since_lease_[t];
      return json(Status::ok,
                  dtraced::protocol::encode(dtraced::protocol::LeaseReply{dtraced::protocol::RetryAfter{5}}));
    }
    leased_[*tile] = true;
    idle_since_lease_[*tile] = 0;
    ++counts_.leases;
    dtraced::protocol::Lease lease{kJob, digest_, *tile, rects_[*tile], desc_.render};
    return json(Status::ok, dtraced::protocol::encode(dtraced::protocol::LeaseReply{lease}));
  }

  Response scene(std::string_view digest) {
    ++counts_.scene_requests;
    if (digest != digest_) {
      counts_.problems.push_back(fmt::format("fetch of unknown scene {}", digest));
      return dtraced::http::make_error(Status::not_found, "no such scene");
    }
    if (rules_.failing_scene_fetches > 0) {
      --rules_.failing_scene_fetches;
      return dtraced::http::make_error(Status::service_unavailable, "failing on purpose");
    }
    if (rules_.tamper_scene) return json(Status::ok, dtraced::scene::canonical_json(other_scene(0.5)));
    return json(Status::ok, canonical_);
  }

  Response submit(std::string_view tile_text, const std::string& body) {
    std::uint32_t t = 0;
    try {
      t = static_cast<std::uint32_t>(std::stoul(std::string(tile_text)));
    } catch (const std::exception&) {
      t = std::numeric_limits<std::uint32_t>::max();
    }
    if (t >= rects_.size()) {
      counts_.problems.push_back(fmt::format("submission of unknown tile {}", tile_text));
      return dtraced::http::make_error(Status::not_found, "no such tile");
    }
    const bool first = counts_.submit_requests[t]++ == 0;
    if (rules_.job_gone) {
      ++counts_.gone_answers;
      return json(Status::gone, dtraced::protocol::encode(dtraced::protocol::SubmitResult::kJobGone));
    }
    if (rules_.submits_unavailable || (first && rules_.fail_first_submit.contains(t))) {
      return dtraced::http::make_error(Status::service_unavailable, "failing on purpose");
    }
    auto decoded = dtraced::protocol::decode_tile_payload(body);
    if (const auto* failure = std::get_if<dtraced::protocol::TilePayloadFailure>(&decoded)) {
      counts_.problems.push_back(fmt::format("tile {}: bad payload: {}", t, failure->message));
      return dtraced::http::make_error(Status::bad_request, failure->message);
    }
    dtraced::protocol::TilePayload& payload = std::get<dtraced::protocol::TilePayload>(decoded);
    if (payload.job != kJob || payload.tile != t || !(payload.rect == rects_[t])) {
      counts_.problems.push_back(fmt::format("tile {}: payload names job {} tile {}", t, payload.job, payload.tile));
      return dtraced::http::make_error(Status::bad_request, "payload does not match the tile");
    }
    ++counts_.acknowledged;
    if (counts_.stored[t] > 0) {
      ++counts_.already_done;
      if (!same_bits(pixels_[t], payload.rgb)) counts_.problems.push_back(fmt::format("tile {}: duplicate differs", t));
      return json(Status::ok, dtraced::protocol::encode(dtraced::protocol::SubmitResult::kAlreadyDone));
    }
    ++counts_.stored[t];
    pixels_[t] = std::move(payload.rgb);
    spp_[t] = std::move(payload.spp);
    return json(Status::ok, dtraced::protocol::encode(dtraced::protocol::SubmitResult::kStored));
  }

  const dtraced::scene::SceneDesc desc_;
  const std::string canonical_;
  const std::string digest_;
  const std::vector<dtraced::scene::TileRect> rects_;

  mutable std::mutex mu_;
  FakeRules rules_;
  FakeCounts counts_;
  std::vector<bool> leased_;
  std::vector<std::uint32_t> idle_since_lease_;
  std::vector<std::vector<float>> pixels_;
  std::vector<std::vector<std::uint32_t>> spp_;  // per tile: the counts it carried (adaptive jobs)
};

// An http::Server on 127.0.0.1:port with its io_context on a thread of its own; destroying it
// stops the server (connections refused from then on).
class RunningServer {
 public:
  RunningServer(std::uint16_t port, Server::Handler handler)
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), port, limits(), std::move(handler)) {
    REQUIRE(!server_.start());
    REQUIRE(server_.port() != 0);
    thread_ = std::thread([this] { io_.run(); });
  }

  ~RunningServer() {
    std::future<void> stopped = net::co_spawn(io_, server_.stop(0ms), net::use_future);
    stopped.wait_for(kBound);
    work_.reset();
    io_.stop();
    thread_.join();
  }

  std::uint16_t port() const { return server_.port(); }

 private:
  static dtraced::http::ServerLimits limits() {
    dtraced::http::ServerLimits limits;
    limits.read_timeout = kBound;
    limits.write_timeout = kBound;
    limits.idle_keepalive_timeout = kBound;
    return limits;
  }

  net::io_context io_;
  net::executor_work_guard<net::io_context::executor_type> work_ = net::make_work_guard(io_);
  Server server_;
  std::thread thread_;
};

WorkerConfig test_config(std::uint16_t port) {
  WorkerConfig config;
  config.collector_url = fmt::format("http://127.0.0.1:{}", port);
  config.token = std::string(kToken);
  config.name = "test-worker";
  config.threads = 2;
  config.scene_cache = 2;
  config.grace = 60s;
  config.timeouts = {kBound, kBound, kBound};
  config.backoff_initial = 2ms;
  config.backoff_max = 40ms;
  config.max_unacknowledged = 4;
  config.jitter_seed = 42;
  return config;
}

// A Worker running on a thread of its own.
class RunningWorker {
 public:
  explicit RunningWorker(const WorkerConfig& config, RunOptions options = {}) : worker_(create(config)) {
    std::packaged_task<bool()> task([this, options] { return worker_->run(options); });
    result_ = task.get_future();
    thread_ = std::thread(std::move(task));
  }

  ~RunningWorker() {
    worker_->request_stop();
    if (thread_.joinable()) thread_.join();
  }

  WorkerStats stats() const { return worker_->stats(); }
  void request_stop() { worker_->request_stop(); }

  // Waits (at most kBound) for run() to return; its result, or nullopt if it did not return.
  std::optional<bool> wait() {
    if (result_.wait_for(kBound) != std::future_status::ready) return std::nullopt;
    thread_.join();
    return result_.get();
  }

  // Requests a stop and waits for run() to return.
  std::optional<bool> stop() {
    request_stop();
    return wait();
  }

 private:
  static std::unique_ptr<Worker> create(const WorkerConfig& config) {
    auto created = Worker::create(config);
    REQUIRE(created.ok());
    return std::move(created).value();
  }

  std::unique_ptr<Worker> worker_;
  std::future<bool> result_;
  std::thread thread_;
};

// What must hold of any worker once it has stopped: nothing left in hand, every rendered tile
// accounted for exactly once.
void check_stopped_cleanly(const WorkerStats& s) {
  CHECK(s.started);
  CHECK(s.stopping);
  CHECK(s.tiles_held == 0);
  CHECK(s.tiles_in_hand == 0);
  CHECK(s.tiles_rendered == s.tiles_submitted + s.tiles_dropped + s.tiles_rejected + s.tiles_abandoned);
}

// Every tile stored once, with the pixels (and, for an adaptive job, the sample counts) of a
// local render_tile of the same rectangle.
void check_pixels(const FakeCollector& fake) {
  const FakeCounts counts = fake.counts();
  const ScenePtr scene = build(fake.desc());
  const std::vector<std::vector<float>> pixels = fake.pixels();
  const std::vector<std::vector<std::uint32_t>> spp = fake.spp();
  for (std::size_t t = 0; t < fake.rects().size(); ++t) {
    INFO("tile " << t);
    CHECK(counts.stored[t] == 1);
    const dtraced::render::Tile local = dtraced::render::render_tile(*scene, fake.desc().render, fake.rects()[t]);
    CHECK(same_bits(pixels[t], local.rgb));
    CHECK(spp[t] == local.spp);
  }
  for (const std::string& problem : counts.problems) FAIL_CHECK(problem);
}

}  // namespace

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
    const auto d = dtraced::worker::jittered_retry_after(500ms, rng);
    REQUIRE(d >= 500ms);
    REQUIRE(d <= 750ms);
    const auto zero = dtraced::worker::jittered_retry_after(0ms, rng);
    REQUIRE(zero >= dtraced::worker::kMinRetryAfter);
    REQUIRE(zero <= dtraced::worker::kMinRetryAfter * 3 / 2);
  }
}

// ---- scene cache -------------------------------------------------------------------------------

TEST_CASE("the scene cache is bounded and evicts the least recently used scene", "[worker][scene_cache]") {
  SceneCache cache(2);
  const ScenePtr a = build(other_scene(0.5)), b = build(other_scene(0.6)), c = build(other_scene(0.7));
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
  ScenePtr in_use = build(other_scene(0.5));
  std::weak_ptr<const dtraced::render::RenderScene> watch = in_use;
  cache.insert("a", in_use);
  cache.insert("b", build(other_scene(0.6)));
  CHECK_FALSE(cache.contains("a"));
  CHECK_FALSE(watch.expired());
  in_use.reset();
  CHECK(watch.expired());
}

TEST_CASE("prepare_scene builds a scene whose body matches its digest and refuses any other", "[worker][scene_cache]") {
  const dtraced::scene::SceneDesc desc = load_tiny_scene();
  const std::string canonical = dtraced::scene::canonical_json(desc);
  const std::string digest = dtraced::scene::scene_digest(desc);

  SECTION("the canonical body renders exactly as the scene built locally") {
    const dtraced::worker::PreparedScene prepared =
        dtraced::worker::prepare_scene(canonical, digest, dtraced::accel::best_isa());
    REQUIRE(prepared.scene != nullptr);
    CHECK(prepared.error.empty());
    const dtraced::scene::TileRect rect{16, 0, 16, 16};
    CHECK(same_bits(dtraced::render::render_tile(*prepared.scene, desc.render, rect).rgb,
                    dtraced::render::render_tile(*build(desc), desc.render, rect).rgb));
  }
  SECTION("a body with other whitespace but the same scene is accepted") {
    CHECK(dtraced::worker::prepare_scene(kTinyScene, digest, dtraced::accel::best_isa()).scene != nullptr);
  }
  SECTION("a tampered body is refused") {
    std::string tampered = canonical;
    const std::size_t at = tampered.find("\"radius\":1");
    REQUIRE(at != std::string::npos);
    tampered.replace(at, 10, "\"radius\":2");
    const dtraced::worker::PreparedScene prepared =
        dtraced::worker::prepare_scene(tampered, digest, dtraced::accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("another scene"));
  }
  SECTION("a body that does not load is refused") {
    const dtraced::worker::PreparedScene prepared =
        dtraced::worker::prepare_scene(canonical.substr(0, 40), digest, dtraced::accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("does not load"));
  }
  SECTION("a valid scene under another scene's digest is refused") {
    const std::string other = dtraced::scene::scene_digest(other_scene(0.5));
    CHECK(dtraced::worker::prepare_scene(canonical, other, dtraced::accel::best_isa()).scene == nullptr);
  }
  SECTION("a scene naming a mesh file is refused, whatever file it names") {
    // A worker never reads its own disk on a scene's behalf; canonical scenes carry meshes inline.
    const std::string with_file =
        R"({"camera": {}, "scene_objects": [{"type": "mesh", "file": "/etc/hostname"}], "scene_lights": []})";
    const dtraced::worker::PreparedScene prepared =
        dtraced::worker::prepare_scene(with_file, digest, dtraced::accel::best_isa());
    CHECK(prepared.scene == nullptr);
    CHECK_THAT(prepared.error, Catch::Contains("/scene_objects/0/file") && Catch::Contains("inline"));
  }
}

// ---- configuration -------------------------------------------------------------------------------

TEST_CASE("worker configuration is validated field by field", "[worker][config]") {
  const auto mentions = [](const dtraced::util::Errors& errors, std::string_view field) {
    for (const dtraced::util::Error& e : errors) {
      if (e.path == field && !e.message.empty() && e.to_string().starts_with(std::string(field) + ": ")) return true;
    }
    return false;
  };
  const dtraced::util::Errors defaults = dtraced::worker::validate(WorkerConfig{});
  CHECK(mentions(defaults, "collector_url"));
  CHECK(mentions(defaults, "token"));
  CHECK(defaults.size() == 2);

  const WorkerConfig good = test_config(7878);
  CHECK(dtraced::worker::validate(good).empty());

  struct Case {
    std::string_view field;
    std::function<void(WorkerConfig&)> change;
  };
  const std::vector<Case> cases = {
      {"collector_url", [](WorkerConfig& c) { c.collector_url = "https://example.org"; }},
      {"collector_url", [](WorkerConfig& c) { c.collector_url = "http://host/path"; }},
      {"token", [](WorkerConfig& c) { c.token = "two words"; }},
      {"token", [](WorkerConfig& c) { c.token = "line\n"; }},
      {"token", [](WorkerConfig& c) { c.token = std::string(dtraced::worker::kMaxTokenBytes + 1, 'x'); }},
      {"name", [](WorkerConfig& c) { c.name = "tab\there"; }},
      {"name", [](WorkerConfig& c) { c.name = std::string(dtraced::protocol::kMaxWorkerNameBytes + 1, 'n'); }},
      {"threads", [](WorkerConfig& c) { c.threads = dtraced::protocol::kMaxWorkerThreads + 1; }},
      {"scene_cache", [](WorkerConfig& c) { c.scene_cache = 0; }},
      {"scene_cache", [](WorkerConfig& c) { c.scene_cache = dtraced::worker::kMaxSceneCache + 1; }},
      {"grace", [](WorkerConfig& c) { c.grace = dtraced::worker::kMaxGrace + 1s; }},
      {"grace", [](WorkerConfig& c) { c.grace = -1s; }},
      {"timeouts.connect", [](WorkerConfig& c) { c.timeouts.connect = 0ms; }},
      {"timeouts.read", [](WorkerConfig& c) { c.timeouts.read = dtraced::worker::kMaxClientTimeout + 1ms; }},
      {"backoff_initial", [](WorkerConfig& c) { c.backoff_initial = 0ms; }},
      {"backoff_max", [](WorkerConfig& c) { c.backoff_max = c.backoff_initial - 1ms; }},
      {"max_unacknowledged", [](WorkerConfig& c) { c.max_unacknowledged = dtraced::worker::kMaxUnacknowledged + 1; }},
  };
  for (const Case& c : cases) {
    WorkerConfig config = good;
    c.change(config);
    const dtraced::util::Errors errors = dtraced::worker::validate(config);
    INFO(c.field);
    CHECK(errors.size() == 1);
    CHECK(mentions(errors, c.field));
  }

  // Worker::create refuses what validate() refuses, with the same errors, and builds nothing.
  WorkerConfig bad = good;
  bad.scene_cache = 0;
  bad.token.clear();
  const auto refused = Worker::create(bad);
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error() == dtraced::worker::validate(bad));
  CHECK(refused.error().size() == 2);
  CHECK(Worker::create(good).ok());
}

TEST_CASE("worker defaults are resolved from the host", "[worker][config]") {
  WorkerConfig config = test_config(7878);
  config.name.clear();
  config.threads = 0;
  config.max_unacknowledged = 0;
  const WorkerConfig resolved = dtraced::worker::resolve_defaults(config);
  CHECK(resolved.threads >= 1);
  CHECK(resolved.max_unacknowledged == dtraced::worker::kInHandPerThread * resolved.threads);
  CHECK_FALSE(resolved.name.empty());
  CHECK(resolved.name.size() <= dtraced::protocol::kMaxWorkerNameBytes);
  CHECK(resolved.name.ends_with(fmt::format("-{}", ::getpid())));
  CHECK(dtraced::worker::validate(resolved).empty());
}

// ---- whole workers against a fake collector --------------------------------------------------------

TEST_CASE("a worker started before its collector renders every tile, through refusals and 5xx answers",
          "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) {
    r.failing_leases = 2;
    r.failing_scene_fetches = 1;
    r.fail_first_submit = {1};
  });
  const std::uint16_t port = unused_port();
  RunningWorker worker(test_config(port));

  // Nobody listens yet: the worker keeps asking, with backoff.
  REQUIRE(eventually([&] { return worker.stats().lease_failures >= 3; }));
  CHECK(worker.stats().tiles_rendered == 0);

  RunningServer server(port, fake.handler());
  REQUIRE(eventually([&] { return fake.all_stored(); }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
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
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.submits_unavailable = true; });
  const std::uint16_t port = unused_port();
  std::optional<RunningServer> server;
  server.emplace(port, fake.handler());
  RunningWorker worker(test_config(port));

  // Every tile rendered and offered, none taken; with four tiles in hand the worker stops leasing.
  REQUIRE(eventually([&] { return fake.every_tile_submitted(); }));
  REQUIRE(eventually([&] { return worker.stats().tiles_held == 4; }));

  server.reset();  // the collector goes away: connections are refused
  const std::uint64_t retries = worker.stats().submit_retries;
  REQUIRE(eventually([&] { return worker.stats().submit_retries >= retries + 2; }));
  CHECK(worker.stats().tiles_held == 4);

  fake.set_rules([](FakeRules& r) { r.submits_unavailable = false; });
  server.emplace(port, fake.handler());
  REQUIRE(eventually([&] { return fake.all_stored(); }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  check_pixels(fake);
  CHECK(s.tiles_submitted == fake.counts().acknowledged);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_in_hand_peak <= 4);
}

TEST_CASE("a job gone drops its tiles without retrying them", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.job_gone = true; });
  RunningServer server(0, fake.handler());
  RunningWorker worker(test_config(server.port()));

  REQUIRE(eventually([&] {
    const WorkerStats s = worker.stats();
    return s.tiles_dropped >= 1 && s.tiles_held == 0 && s.tiles_rendered == s.tiles_dropped;
  }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_submitted == 0);
  CHECK(s.submit_retries == 0);
  CHECK(s.tiles_rendered == s.tiles_dropped);
  std::uint64_t submits = 0;
  for (const std::uint64_t n : fake.counts().submit_requests) submits += n;
  CHECK(submits <= s.tiles_rendered);
  CHECK(fake.counts().problems.empty());
}

TEST_CASE("a stop submits what is in hand within the grace period", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.submits_unavailable = true; });
  RunningServer server(0, fake.handler());
  RunningWorker worker(test_config(server.port()));

  REQUIRE(eventually([&] { return worker.stats().tiles_held >= 1; }));
  worker.request_stop();
  REQUIRE(eventually([&] { return worker.stats().stopping; }));
  fake.set_rules([](FakeRules& r) { r.submits_unavailable = false; });
  REQUIRE(worker.wait() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_abandoned == 0);
  CHECK(s.tiles_submitted == s.tiles_rendered);
  CHECK(s.tiles_submitted == fake.counts().acknowledged);
  CHECK(fake.counts().problems.empty());
}

TEST_CASE("when the grace period runs out, unacknowledged tiles are abandoned and the worker exits",
          "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.submits_unavailable = true; });
  RunningServer server(0, fake.handler());
  WorkerConfig config = test_config(server.port());
  config.grace = 0s;
  RunningWorker worker(config);

  REQUIRE(eventually([&] { return worker.stats().tiles_held >= 1; }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_submitted == 0);
  CHECK(s.tiles_abandoned == s.tiles_rendered);
  CHECK(s.tiles_abandoned >= 1);
}

TEST_CASE("a rejected token is retried with backoff and nothing is rendered", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.reject_token = true; });
  RunningServer server(0, fake.handler());
  RunningWorker worker(test_config(server.port()));

  REQUIRE(eventually([&] { return worker.stats().lease_failures >= 3; }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_rendered == 0);
  CHECK(fake.counts().leases == 0);
  CHECK(fake.counts().unauthorized >= 3);
}

TEST_CASE("a scene that does not match its digest is refused and nothing is rendered", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.tamper_scene = true; });
  RunningServer server(0, fake.handler());
  RunningWorker worker(test_config(server.port()));

  REQUIRE(eventually([&] { return worker.stats().scenes_rejected >= 2; }));
  REQUIRE(worker.stop() == std::optional<bool>(true));

  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_rendered == 0);
  CHECK(s.scenes_fetched == 0);
  CHECK(s.leases_dropped >= 2);
}

// The worker's read timeout is far longer than kBound: only cancellation can end these requests.
TEST_CASE("a stop cancels a lease request the collector never answers", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.hang_leases = true; });
  RunningServer server(0, fake.handler());
  WorkerConfig config = test_config(server.port());
  config.timeouts.read = dtraced::worker::kMaxClientTimeout;
  RunningWorker worker(config);

  REQUIRE(eventually([&] { return fake.counts().hung >= 1; }));
  REQUIRE(worker.stop() == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_rendered == 0);
}

TEST_CASE("the end of the grace period cancels submissions the collector never answers", "[worker][end_to_end]") {
  FakeCollector fake;
  fake.set_rules([](FakeRules& r) { r.hang_submits = true; });
  RunningServer server(0, fake.handler());
  WorkerConfig config = test_config(server.port());
  config.timeouts.read = dtraced::worker::kMaxClientTimeout;
  config.grace = 0s;
  RunningWorker worker(config);

  REQUIRE(eventually([&] { return fake.counts().hung >= 1; }));
  REQUIRE(worker.stop() == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_submitted == 0);
  CHECK(s.tiles_abandoned == s.tiles_rendered);
  CHECK(s.tiles_abandoned >= 1);
}

TEST_CASE("SIGTERM stops a worker that waits for an absent collector", "[worker][end_to_end]") {
  RunningWorker worker(test_config(unused_port()), RunOptions{.stop_on_signals = true, .notify_systemd = false});
  REQUIRE(eventually([&] { return worker.stats().started && worker.stats().lease_failures >= 1; }));
  REQUIRE(::kill(::getpid(), SIGTERM) == 0);
  REQUIRE(worker.wait() == std::optional<bool>(true));
  const WorkerStats s = worker.stats();
  check_stopped_cleanly(s);
  CHECK(s.tiles_rendered == 0);
}

TEST_CASE("an adaptive job's tiles carry their per-pixel sample counts", "[worker][end_to_end][adaptive]") {
  dtraced::scene::SceneDesc desc = load_tiny_scene();
  desc.render.samples = 16;
  desc.render.min_samples = 4;
  desc.render.error_target = 0.05;
  FakeCollector fake(desc);
  const std::uint16_t port = unused_port();
  RunningServer server(port, fake.handler());
  RunningWorker worker(test_config(port));
  REQUIRE(eventually([&] { return fake.all_stored(); }));
  REQUIRE(worker.stop() == std::optional<bool>(true));
  check_stopped_cleanly(worker.stats());
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
