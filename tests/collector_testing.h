// What the collector's service tests share: a small scene and its submissions, fake tile pixels
// (deterministic, so the collector cannot tell them from rendered ones), and a Harness that makes
// a collector on a ManualClock, opens it, and talks to it through its request handler. By default the
// harness answers each request by running the loop until it is idle (Collector::handle_sync);
// after start_loop() the loop runs on a thread of its own, for tests in which the collector
// sleeps on its clock (a loop run until idle would wait for that sleep forever).
#pragma once

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/use_future.hpp>
#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/config.h"
#include "collector/jobs.h"
#include "collector/service.h"
#include "http/types.h"
#include "image/image_io.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "protocol/worker_messages.h"
#include "scene/tiling.h"
#include "store/store.h"
#include "temp_dir.h"
#include "util/clock.h"
#include "util/result.h"

namespace dtraced::testing {

namespace coll = dtraced::collector;
namespace fs = std::filesystem;
namespace protocol = dtraced::protocol;
namespace store = dtraced::store;
using http::Request;
using http::Response;
using http::Status;
using http::Verb;
using namespace std::chrono_literals;

inline constexpr std::string_view kToken = "s3cret-token";
// The longest a test waits for something that happens on another thread before it fails.
inline constexpr auto kBound = 20s;

// A small scene: 32x24 pixels in tiles of 8 is 4 x 3 = 12 tiles.
inline constexpr std::string_view kScene = R"({
  "camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 40},
  "render": {"width": 32, "height": 24, "samples": 1, "max_depth": 2, "seed": 7},
  "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"color": [0.8, 0.2, 0.2]}}],
  "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 50}]
})";
inline constexpr std::uint32_t kTiles = 12;

inline void require_ok(const util::Status& status) {
  if (!status) FAIL(status.error().to_string());
}

inline coll::CollectorConfig make_config(const TempDir& dir) {
  coll::CollectorConfig c;
  c.state_dir = (dir.path() / "state").string();
  c.output_dir = (dir.path() / "out").string();
  c.token = std::string(kToken);
  c.port = 0;
  return c;
}

inline std::unique_ptr<coll::Collector> must_create(coll::CollectorConfig config,
                                                    const util::Clock& clock = util::real_clock()) {
  auto created = coll::Collector::create(std::move(config), clock);
  if (!created) FAIL(util::to_string(created.error()));
  return std::move(created).value();
}

// Writes `text` to `path`.
inline void write_text(const std::filesystem::path& path, std::string_view text) {
  std::FILE* f = std::fopen(path.c_str(), "wb");
  REQUIRE(f != nullptr);
  REQUIRE(std::fwrite(text.data(), 1, text.size(), f) == text.size());
  std::fclose(f);
}

// Why start-up with `config` fails (it must).
inline std::string open_error(const coll::CollectorConfig& config) {
  auto collector = must_create(config);
  const util::Status opened = collector->open();
  REQUIRE_FALSE(opened);
  return opened.error().to_string();
}

inline coll::OneShotJob one_shot(std::string scene_path, std::string output) {
  coll::OneShotJob job;
  job.scene_path = std::move(scene_path);
  job.output = std::move(output);
  return job;
}

// A configuration whose one-shot job renders kScene (written to the directory) to `output`.
inline coll::CollectorConfig one_shot_config(const TempDir& dir, std::string output = "shot.png") {
  const fs::path scene_path = dir.path() / "scene.json";
  write_text(scene_path, kScene);
  coll::CollectorConfig config = make_config(dir);
  config.one_shot = one_shot(scene_path.string(), std::move(output));
  return config;
}

inline Request make(Verb method, std::string target, std::string body = {}, std::string_view token = kToken) {
  Request req = http::make_request(method, target, std::move(body));
  if (!token.empty()) req.set(boost::beast::http::field::authorization, fmt::format("Bearer {}", token));
  // As every worker does: a lease needs this build's pixel version (tests of the refusal remove it).
  if (target == "/v1/lease") req.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
  return req;
}

inline std::string submit_body(std::string_view extra = "", std::string_view scene = kScene) {
  return fmt::format(R"({{"scene": {}, "tile_size": 8{}}})", scene, extra);
}

// Deterministic stand-in pixels: the collector cannot tell them from rendered ones.
inline std::vector<float> fake_pixels(std::uint64_t job, std::uint32_t tile, const scene::TileRect& rect,
                                      float salt = 0) {
  std::vector<float> rgb(std::size_t{rect.width} * rect.height * 3);
  for (std::size_t i = 0; i < rgb.size(); ++i) rgb[i] = static_cast<float>(job) + tile * 0.01f + i * 1e-5f + salt;
  return rgb;
}

inline std::string payload(std::uint64_t job, std::uint32_t tile, const scene::TileRect& rect, float salt = 0) {
  return protocol::encode_tile_payload({job, tile, rect, fake_pixels(job, tile, rect, salt), {}});
}

struct Harness {
  explicit Harness(const TempDir& dir) : Harness(make_config(dir)) {}
  // Creates and opens the collector.
  explicit Harness(coll::CollectorConfig c) : config(std::move(c)), owned(must_create(config, clock)) {
    require_ok(collector.open());
  }
  ~Harness() {
    if (loop.valid()) {
      collector.stop();
      work.reset();
      loop.wait();
    }
  }
  Harness(const Harness&) = delete;
  Harness& operator=(const Harness&) = delete;

  Response call(Verb method, std::string target, std::string body = {}, std::string_view token = kToken) {
    Request req = make(method, std::move(target), std::move(body), token);
    if (!loop.valid()) return collector.handle_sync(std::move(req));
    auto answer =
        boost::asio::co_spawn(collector.io_context(), collector.handle(std::move(req)), boost::asio::use_future);
    REQUIRE(answer.wait_for(kBound) == std::future_status::ready);
    Response res = answer.get();
    res.prepare_payload();
    return res;
  }

  // Runs the loop on a thread of its own from now on; requests go to it.
  void start_loop() {
    work.emplace(collector.io_context().get_executor());
    loop = std::async(std::launch::async, [this] { return collector.run(); });
  }
  // Stops the collector (after start_loop) and returns run()'s exit code.
  int stop_loop() {
    collector.stop();
    work.reset();
    REQUIRE(loop.wait_for(kBound) == std::future_status::ready);
    return loop.get();
  }
  // The collector's metrics, read on its loop.
  coll::MetricsSnapshot metrics() {
    if (!loop.valid()) return collector.metrics();
    auto read = std::make_shared<std::promise<coll::MetricsSnapshot>>();
    boost::asio::post(collector.io_context(), [this, read] { read->set_value(collector.metrics()); });
    auto snapshot = read->get_future();
    REQUIRE(snapshot.wait_for(kBound) == std::future_status::ready);
    return snapshot.get();
  }

  std::uint64_t submit(std::string_view extra = "") {
    const Response res = call(Verb::post, "/v1/jobs", submit_body(extra));
    REQUIRE(res.result() == Status::created);
    auto created = protocol::decode_job_created(res.body());
    REQUIRE(created.ok());
    return created.value().id;
  }

  // nullopt for "retry after".
  std::optional<protocol::Lease> lease() {
    const Response res = call(Verb::post, "/v1/lease", R"({"worker": "test", "threads": 1})");
    REQUIRE(res.result() == Status::ok);
    auto reply = protocol::decode_lease_reply(res.body());
    REQUIRE(reply.ok());
    if (auto* l = std::get_if<protocol::Lease>(&reply.value())) return *l;
    return std::nullopt;
  }

  std::vector<protocol::Lease> lease_all() {
    std::vector<protocol::Lease> out;
    while (auto l = lease()) out.push_back(*l);
    return out;
  }

  Response put(std::uint64_t job, std::uint32_t tile, std::string body, std::string_view token = kToken) {
    return call(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, tile), std::move(body), token);
  }

  protocol::SubmitResult put_ok(const protocol::Lease& l, float salt = 0) {
    const Response res = put(l.job, l.tile, payload(l.job, l.tile, l.rect, salt));
    REQUIRE(res.result() == Status::ok);
    auto result = protocol::decode_submit_result(res.body());
    REQUIRE(result.ok());
    return result.value();
  }

  protocol::JobStatus status(std::uint64_t job) {
    const Response res = call(Verb::get, fmt::format("/v1/jobs/{}", job));
    REQUIRE(res.result() == Status::ok);
    auto s = protocol::decode_job_status(res.body());
    REQUIRE(s.ok());
    return s.value();
  }

  util::ManualClock clock;  // declared first: the collector reads it until it is destroyed
  coll::CollectorConfig config;
  std::unique_ptr<coll::Collector> owned;
  coll::Collector& collector = *owned;
  std::optional<boost::asio::executor_work_guard<boost::asio::io_context::executor_type>> work;
  std::future<int> loop;  // after start_loop(): run()'s exit code
};

inline protocol::ErrorBody error_of(const Response& res) {
  auto e = protocol::decode_error_body(res.body());
  REQUIRE(e.ok());
  return e.value();
}

// What the database holds, read through a connection of its own.
struct StoredState {
  std::vector<store::StoredJob> jobs;
  std::map<std::int64_t, std::vector<std::uint32_t>> tiles;
  bool operator==(const StoredState&) const = default;
};

inline StoredState stored_state(const coll::CollectorConfig& config) {
  auto opened = store::Store::open(config.state_dir, {.verify_integrity = false});
  REQUIRE(opened.ok());
  StoredState state;
  auto jobs = opened.value().list_jobs();
  REQUIRE(jobs.ok());
  state.jobs = jobs.value();
  for (const auto& j : state.jobs) {
    auto tiles = opened.value().stored_tiles(j.id);
    REQUIRE(tiles.ok());
    state.tiles[j.id] = tiles.value();
  }
  return state;
}

inline image::ImageRGBf expected_image(std::uint64_t job, std::uint32_t w, std::uint32_t h, std::uint32_t ts,
                                       const std::set<std::uint32_t>& tiles) {
  image::ImageRGBf img(w, h);
  const auto rects = scene::TileGrid(w, h, ts).all();
  for (std::uint32_t t : tiles) coll::copy_tile(img, rects[t], fake_pixels(job, t, rects[t]));
  return img;
}

inline std::set<std::uint32_t> all_tiles() {
  std::set<std::uint32_t> all;
  for (std::uint32_t t = 0; t < kTiles; ++t) all.insert(t);
  return all;
}

inline image::ImageRGBf fetch_pfm(Harness& h, std::uint64_t job) {
  const Response res = h.call(Verb::get, fmt::format("/v1/jobs/{}/image?format=pfm", job));
  REQUIRE(res.result() == Status::ok);
  auto img = image::decode_image(image::ImageFormat::kPfm, res.body(), "pfm");
  if (!img) INFO(img.error().to_string());
  REQUIRE(img);
  return *img;
}

inline std::uint64_t metric(Harness& h, std::uint64_t coll::CollectorCounters::*field) {
  return h.metrics().counters.*field;
}

}  // namespace dtraced::testing
