// Tests for dtraced::collector: the configuration, and the service driven through its request
// handler without sockets (Collector::handle_sync runs the loop until the answer and the work it
// started are done): submit -> lease -> tiles -> image; duplicates and
// faulty duplicates; refused payloads; unknown jobs; the token; cancel; priorities; restarts on
// the same state directory (after a clean destruction, and after a SIGKILL of a forked child that
// had acknowledged tiles), where stored tiles are never leased again; a corrupt database; the
// one-shot job; and one smoke test over a real socket with a graceful stop.
#include <signal.h>
#include <sqlite3.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <iterator>
#include <random>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/config.h"
#include "collector/jobs.h"
#include "collector/routes.h"
#include "collector/service.h"
#include "http/client.h"
#include "http/types.h"
#include "image/image_io.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "render/tile.h"
#include "store/store.h"
#include "util/file.h"
#include "util/sha256.h"

namespace {

namespace fs = std::filesystem;
namespace coll = dtraced::collector;
namespace protocol = dtraced::protocol;
namespace store = dtraced::store;
using dtraced::http::Request;
using dtraced::http::Response;
using dtraced::http::Status;
using dtraced::http::Verb;
using namespace std::chrono_literals;

constexpr std::string_view kToken = "s3cret-token";

// A small scene: 32x24 pixels in tiles of 8 is 4 x 3 = 12 tiles.
constexpr std::string_view kScene = R"({
  "camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 40},
  "render": {"width": 32, "height": 24, "samples": 1, "max_depth": 2, "seed": 7},
  "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"color": [0.8, 0.2, 0.2]}}],
  "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 50}]
})";
constexpr std::uint32_t kTiles = 12;

class TempDir {
 public:
  TempDir() {
    std::random_device rd;
    for (;;) {
      path_ =
          fs::temp_directory_path() / fmt::format("dtraced_test_collector_{:016x}", std::uint64_t{rd()} << 32 | rd());
      if (fs::create_directory(path_)) break;
    }
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const fs::path& path() const { return path_; }

 private:
  fs::path path_;
};

coll::CollectorConfig make_config(const TempDir& dir) {
  coll::CollectorConfig c;
  c.state_dir = (dir.path() / "state").string();
  c.output_dir = (dir.path() / "out").string();
  c.token = std::string(kToken);
  c.port = 0;
  return c;
}

coll::OneShotJob one_shot(std::string scene_path, std::string output) {
  coll::OneShotJob job;
  job.scene_path = std::move(scene_path);
  job.output = std::move(output);
  return job;
}

Request make(Verb method, std::string target, std::string body = {}, std::string_view token = kToken) {
  Request req = dtraced::http::make_request(method, target, std::move(body));
  if (!token.empty()) req.set(boost::beast::http::field::authorization, fmt::format("Bearer {}", token));
  return req;
}

std::string submit_body(std::string_view extra = "", std::string_view scene = kScene) {
  return fmt::format(R"({{"scene": {}, "tile_size": 8{}}})", scene, extra);
}

// Deterministic stand-in pixels: the collector cannot tell them from rendered ones.
std::vector<float> fake_pixels(std::uint64_t job, std::uint32_t tile, const dtraced::scene::TileRect& rect,
                               float salt = 0) {
  std::vector<float> rgb(std::size_t{rect.width} * rect.height * 3);
  for (std::size_t i = 0; i < rgb.size(); ++i) rgb[i] = static_cast<float>(job) + tile * 0.01f + i * 1e-5f + salt;
  return rgb;
}

std::string payload(std::uint64_t job, std::uint32_t tile, const dtraced::scene::TileRect& rect, float salt = 0) {
  return protocol::encode_tile_payload({job, tile, rect, fake_pixels(job, tile, rect, salt), {}});
}

struct Harness {
  explicit Harness(const TempDir& dir) : Harness(make_config(dir)) {}
  explicit Harness(coll::CollectorConfig c) : config(std::move(c)), collector(config) {}

  Response call(Verb method, std::string target, std::string body = {}, std::string_view token = kToken) {
    return collector.handle_sync(make(method, std::move(target), std::move(body), token));
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

  coll::CollectorConfig config;
  coll::Collector collector;
};

protocol::ErrorBody error_of(const Response& res) {
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

StoredState stored_state(const coll::CollectorConfig& config) {
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

dtraced::image::ImageRGBf expected_image(std::uint64_t job, std::uint32_t w, std::uint32_t h, std::uint32_t ts,
                                         const std::set<std::uint32_t>& tiles) {
  dtraced::image::ImageRGBf img(w, h);
  const auto rects = dtraced::scene::TileGrid(w, h, ts).all();
  for (std::uint32_t t : tiles) coll::copy_tile(img, rects[t], fake_pixels(job, t, rects[t]));
  return img;
}

dtraced::image::ImageRGBf fetch_pfm(Harness& h, std::uint64_t job) {
  const Response res = h.call(Verb::get, fmt::format("/v1/jobs/{}/image?format=pfm", job));
  REQUIRE(res.result() == Status::ok);
  std::string error;
  auto img = dtraced::image::decode_image(dtraced::image::ImageFormat::kPfm, res.body(), "pfm", error);
  INFO(error);
  REQUIRE(img);
  return *img;
}

std::uint64_t metric(const Harness& h, std::uint64_t coll::CollectorCounters::*field) {
  return h.collector.metrics().counters.*field;
}

}  // namespace

// ---- configuration --------------------------------------------------------------------------------

TEST_CASE("collector configuration is validated", "[collector][config]") {
  TempDir dir;
  coll::CollectorConfig c = make_config(dir);
  CHECK_FALSE(coll::check_collector_config(c));
  c.token = "";
  CHECK(coll::check_collector_config(c).value().find("token") == 0);
  c = make_config(dir);
  c.token = "has space";
  CHECK(coll::check_collector_config(c));
  c = make_config(dir);
  c.listen_address = "localhost";
  CHECK(coll::check_collector_config(c).value().find("listen_address") == 0);
  c = make_config(dir);
  c.exit_when_done = true;
  CHECK(coll::check_collector_config(c));
  c.one_shot = one_shot("scene.json", "../x.png");
  CHECK(coll::check_collector_config(c).value().find("output") == 0);
  c.one_shot->output = "x.png";
  CHECK_FALSE(coll::check_collector_config(c));
  c.queue.max_copies = 0;
  CHECK(coll::check_collector_config(c).value().find("queue") == 0);
  CHECK(make_config(dir).effective_output_dir() == (dir.path() / "out").string());
}

// ---- the service, through its handler --------------------------------------------------------------

TEST_CASE("a job's PNG bit depth and background overrides reach its image and survive a restart",
          "[collector][service]") {
  TempDir dir;
  // The PNG's bit depth is byte 24 of the file (the IHDR chunk's first data bytes are width and
  // height, 4 bytes each, after the 8-byte signature and the chunk's length and type).
  const auto png_bit_depth = [](const std::string& png) { return static_cast<int>(png.at(24)); };
  std::uint64_t job = 0;
  {
    Harness h(dir);
    REQUIRE_FALSE(h.collector.open());
    job = h.submit(R"(, "png_bit_depth": 16, "background": [0.5, 0.25, 1])");
    for (const auto& l : h.lease_all()) {
      CHECK(l.settings.background == dtraced::scene::Color{0.5, 0.25, 1});
      h.put_ok(l);
    }
    REQUIRE(h.status(job).state == protocol::JobState::kDone);
    std::string error;
    const auto written = dtraced::util::read_file_limited((dir.path() / "out" / "job-1.png").string(), 1 << 20, error);
    REQUIRE(written);
    CHECK(png_bit_depth(*written) == 16);
  }
  // After a restart the job's bit depth comes back from the store: the image is served at 16 bits.
  Harness again(dir);
  REQUIRE_FALSE(again.collector.open());
  const Response png = again.call(Verb::get, fmt::format("/v1/jobs/{}/image?format=png", job));
  REQUIRE(png.result() == Status::ok);
  CHECK(png_bit_depth(png.body()) == 16);
  // An 8-bit job's stored settings do not name a bit depth (its one-shot key is unchanged).
  const std::uint64_t plain = again.submit();
  const StoredState stored = stored_state(again.config);
  for (const auto& row : stored.jobs) {
    INFO(row.settings_json);
    CHECK((row.settings_json.find("png_bit_depth") != std::string::npos) == (row.id == std::int64_t(job)));
  }
  CHECK(plain == job + 1);
}

TEST_CASE("submit, lease every tile, store them, and the image is written", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());

  const Response health = h.call(Verb::get, "/healthz", "", "");
  CHECK(health.result() == Status::ok);
  CHECK(health.body() == R"({"ok":true})");
  const std::uint64_t job = h.submit();
  CHECK(job == 1);
  protocol::JobStatus s = h.status(job);
  CHECK(s.state == protocol::JobState::kQueued);
  CHECK(s.tiles_total == kTiles);
  CHECK(s.output == "job-1.png");
  CHECK(s.width == 32);
  CHECK(s.height == 24);
  CHECK_FALSE(s.eta_s);

  // The job and its scene are durable before the 201.
  StoredState stored = stored_state(h.config);
  REQUIRE(stored.jobs.size() == 1);
  CHECK(stored.jobs[0].digest == s.digest);

  // The scene by digest is exactly the text whose SHA-256 is the digest.
  const Response scene = h.call(Verb::get, "/v1/scenes/" + s.digest);
  REQUIRE(scene.result() == Status::ok);
  CHECK(dtraced::util::sha256_hex(scene.body()) == s.digest);

  std::vector<protocol::Lease> leases = h.lease_all();
  REQUIRE(leases.size() == kTiles);
  std::set<std::uint32_t> seen;
  const auto rects = dtraced::scene::TileGrid(32, 24, 8).all();
  for (const auto& l : leases) {
    CHECK(l.job == job);
    CHECK(l.digest == s.digest);
    CHECK(l.rect == rects[l.tile]);
    CHECK(l.settings.seed == 7);
    seen.insert(l.tile);
  }
  CHECK(seen.size() == kTiles);
  CHECK(h.status(job).state == protocol::JobState::kRendering);

  // Store all but the last; the partial image shows them, black elsewhere.
  for (std::size_t i = 0; i + 1 < leases.size(); ++i) CHECK(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);
  std::set<std::uint32_t> done;
  for (std::size_t i = 0; i + 1 < leases.size(); ++i) done.insert(leases[i].tile);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, done).rgb);
  const Response png = h.call(Verb::get, fmt::format("/v1/jobs/{}/image", job));
  REQUIRE(png.result() == Status::ok);
  CHECK(png.body().substr(1, 3) == "PNG");
  s = h.status(job);
  CHECK(s.tiles_done == kTiles - 1);
  CHECK(s.eta_s.has_value());
  CHECK_FALSE(fs::exists(dir.path() / "out" / "job-1.png"));

  CHECK(h.put_ok(leases.back()) == protocol::SubmitResult::kStored);
  s = h.status(job);
  CHECK(s.state == protocol::JobState::kDone);
  CHECK(s.tiles_done == kTiles);
  CHECK(s.eta_s == 0.0);
  REQUIRE(fs::exists(dir.path() / "out" / "job-1.png"));
  std::string error;
  auto written = dtraced::image::read_image((dir.path() / "out" / "job-1.png").string(), error);
  REQUIRE(written);
  CHECK(written->width == 32);
  // The final image, now from the store, is every tile's exact bits.
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, seen).rgb);
  // The scene is still served once the job is done (from the store now).
  CHECK(h.call(Verb::get, "/v1/scenes/" + s.digest).body() == scene.body());

  stored = stored_state(h.config);
  CHECK(stored.jobs[0].state == "done");
  CHECK(stored.tiles[1].size() == kTiles);
  CHECK_FALSE(h.lease());
  const coll::MetricsSnapshot m = h.collector.metrics();
  CHECK(m.counters.tiles_stored == kTiles);
  CHECK(m.counters.images_written == 1);
  CHECK(m.jobs_by_state[2] == 1);
  CHECK(m.epoch == 1);
  const Response metrics = h.call(Verb::get, "/metrics");
  CHECK(metrics.body().find("dtraced_tiles_stored_total 12\n") != std::string::npos);
  CHECK(metrics.body().find("dtraced_restored_tile_leases_total 0\n") != std::string::npos);
  CHECK(metrics.body().find("dtraced_jobs{state=\"done\"} 1\n") != std::string::npos);

  // The job list has it too.
  auto list = protocol::decode_job_list(h.call(Verb::get, "/v1/jobs").body());
  REQUIRE(list.ok());
  REQUIRE(list.value().jobs.size() == 1);
  CHECK(list.value().jobs[0].state == protocol::JobState::kDone);
}

TEST_CASE("a named output and a PPM output are written where asked", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit(R"(, "output": "picture.pfm", "width": 16, "height": 8)");
  auto leases = h.lease_all();
  REQUIRE(leases.size() == 2);
  for (const auto& l : leases) h.put_ok(l);
  CHECK(h.status(job).output == "picture.pfm");
  std::string error;
  auto img = dtraced::image::read_image((dir.path() / "out" / "picture.pfm").string(), error);
  REQUIRE(img);
  CHECK(img->rgb == expected_image(job, 16, 8, 8, {0, 1}).rgb);
}

TEST_CASE("duplicates are answered already_done; different pixels count as faulty", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  auto leases = h.lease_all();
  REQUIRE(h.put_ok(leases[0]) == protocol::SubmitResult::kStored);
  CHECK(h.put_ok(leases[0]) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 0);
  CHECK(h.put_ok(leases[0], /*salt=*/0.5f) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 1);
  CHECK(metric(h, &coll::CollectorCounters::tile_duplicates) == 2);
  // The first result stays.
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, {leases[0].tile}).rgb);

  // Once the job is done its pixels are in the store only: duplicates are compared there.
  for (std::size_t i = 1; i < leases.size(); ++i) h.put_ok(leases[i]);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  CHECK(h.put_ok(leases[3]) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 1);
  CHECK(h.put_ok(leases[3], /*salt=*/1.0f) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 2);
  CHECK(stored_state(h.config).tiles[1].size() == kTiles);
}

TEST_CASE("two uploads of one tile in flight at once: one stored, one already_done", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  const protocol::Lease l = *h.lease();
  std::vector<Response> answers;
  for (const float salt : {0.0f, 0.0f, 0.25f}) {
    boost::asio::co_spawn(h.collector.io_context(),
                          h.collector.handle(make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", job, l.tile),
                                                  payload(job, l.tile, l.rect, salt))),
                          [&answers](std::exception_ptr error, Response res) {
                            REQUIRE_FALSE(error);
                            answers.push_back(std::move(res));
                          });
  }
  h.collector.run_until_idle();
  REQUIRE(answers.size() == 3);
  std::multiset<protocol::SubmitResult> results;
  for (const auto& res : answers) {
    REQUIRE(res.result() == Status::ok);
    results.insert(protocol::decode_submit_result(res.body()).value());
  }
  CHECK(results.count(protocol::SubmitResult::kStored) == 1);
  CHECK(results.count(protocol::SubmitResult::kAlreadyDone) == 2);
  CHECK(h.status(job).tiles_done == 1);
  CHECK(stored_state(h.config).tiles[1].size() == 1);
  // The third upload had other pixels: if it lost it is counted faulty; if it won, the two others are.
  const auto faulty = metric(h, &coll::CollectorCounters::faulty_results);
  CHECK((faulty == 1 || faulty == 2));
}

TEST_CASE("once the store is closed, writes get 503 with Retry-After", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  const protocol::Lease l = *h.lease();
  h.collector.stop();
  CHECK(h.collector.run() == 0);
  Response res = h.put(job, l.tile, payload(job, l.tile, l.rect));
  CHECK(res.result() == Status::service_unavailable);
  CHECK(res[boost::beast::http::field::retry_after] == "1");
  res = h.call(Verb::post, "/v1/jobs", submit_body());
  CHECK(res.result() == Status::service_unavailable);
  // Reads from memory still work.
  CHECK(h.status(job).state == protocol::JobState::kRendering);
}

TEST_CASE("malformed tiles are refused with 400 and change nothing", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  const protocol::Lease l = *h.lease();
  const std::string good = payload(job, l.tile, l.rect);
  const StoredState before = stored_state(h.config);

  const auto refused = [&](std::string body, std::string_view field, std::string_view words, std::uint32_t tile) {
    const Response res = h.put(job, tile, std::move(body));
    CHECK(res.result() == Status::bad_request);
    const protocol::ErrorBody e = error_of(res);
    CHECK(e.field == field);
    CHECK_THAT(e.error, Catch::Matchers::Contains(std::string(words)));
  };
  SECTION("truncated") { refused(good.substr(0, good.size() - 1), "", "payload", l.tile); }
  SECTION("bad checksum") {
    std::string bad = good;
    bad[100] ^= 1;
    refused(bad, "", "payload", l.tile);
  }
  SECTION("bad magic") {
    std::string bad = good;
    bad[0] = 'X';
    refused(bad, "", "payload", l.tile);
  }
  SECTION("not the job's rectangle") {
    dtraced::scene::TileRect r = l.rect;
    r.x0 = r.x0 == 0 ? 8 : 0;
    refused(payload(job, l.tile, r), "/rect", "rectangle", l.tile);
  }
  SECTION("smaller rectangle at the right place") {
    dtraced::scene::TileRect r = l.rect;
    r.width = 4;
    refused(payload(job, l.tile, r), "/rect", "rectangle", l.tile);
  }
  SECTION("URL and payload disagree on the tile") { refused(good, "/tile", "URL", (l.tile + 1) % kTiles); }
  SECTION("URL and payload disagree on the job") {
    const Response res = h.put(job + 1, l.tile, good);
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).field == "/job");
  }
  SECTION("tile out of the job's range") { refused(payload(job, kTiles, l.rect), "/tile", "no tile", kTiles); }
  SECTION("non-finite pixel") {
    std::vector<float> rgb = fake_pixels(job, l.tile, l.rect);
    rgb[5] = std::numeric_limits<float>::quiet_NaN();
    refused(protocol::encode_tile_payload({job, l.tile, l.rect, rgb, {}}), "/pixels", "non-finite", l.tile);
  }
  SECTION("body over the tile limit") {
    const Response res = h.put(job, l.tile, std::string(protocol::kMaxTilePayloadBytes + 1, 'x'));
    CHECK(res.result() == Status::payload_too_large);
  }
  CHECK(stored_state(h.config) == before);
  CHECK(h.status(job).tiles_done == 0);
  CHECK(metric(h, &coll::CollectorCounters::tiles_stored) == 0);
  // The good one still goes in.
  CHECK(h.put_ok(l) == protocol::SubmitResult::kStored);
}

TEST_CASE("unknown jobs: 410 for tiles, 404 for status, image and cancel", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const dtraced::scene::TileRect rect{0, 0, 8, 8};
  const Response gone = h.put(42, 0, payload(42, 0, rect));
  CHECK(gone.result() == Status::gone);
  CHECK(protocol::decode_submit_result(gone.body()).value() == protocol::SubmitResult::kJobGone);
  CHECK(h.call(Verb::get, "/v1/jobs/42").result() == Status::not_found);
  CHECK(h.call(Verb::get, "/v1/jobs/42/image").result() == Status::not_found);
  CHECK(h.call(Verb::post, "/v1/jobs/42/cancel").result() == Status::not_found);
  CHECK(h.call(Verb::get, "/v1/scenes/" + std::string(64, '0')).result() == Status::not_found);
  CHECK(h.call(Verb::get, "/v1/nothing").result() == Status::not_found);
  CHECK(stored_state(h.config).jobs.empty());
}

TEST_CASE("bad control bodies get a 4xx that names the field and change nothing", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  Response res = h.call(Verb::post, "/v1/jobs", "{not json");
  CHECK(res.result() == Status::bad_request);
  res = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "tile_size": "big")"));
  CHECK(res.result() == Status::bad_request);
  res = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "colour": 1)"));
  CHECK(res.result() == Status::bad_request);
  CHECK(error_of(res).field == "/colour");
  std::string bad_scene(kScene);
  bad_scene.replace(bad_scene.find(R"("radius": 1)"), 11, R"("radius": -1)");
  res = h.call(Verb::post, "/v1/jobs", submit_body("", bad_scene));
  CHECK(res.result() == Status::bad_request);
  CHECK(error_of(res).field == "/scene/scene_objects/0/radius");
  res = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "output": "../../etc/passwd.png")"));
  CHECK(res.result() == Status::bad_request);
  CHECK(error_of(res).field == "/output");
  res = h.call(Verb::post, "/v1/lease", R"({"worker": 5})");
  CHECK(res.result() == Status::bad_request);
  CHECK(error_of(res).field == "/worker");
  res = h.call(Verb::post, "/v1/lease", std::string(protocol::kMaxMessageBytes + 1, ' '));
  CHECK(res.result() == Status::payload_too_large);
  res = h.call(Verb::delete_, "/v1/jobs");
  CHECK(res.result() == Status::method_not_allowed);
  CHECK(res[boost::beast::http::field::allow] == "GET, POST");
  CHECK(stored_state(h.config).jobs.empty());
  CHECK_FALSE(h.lease());
}

TEST_CASE("a missing or wrong token gets 401 everywhere and changes nothing", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  const protocol::Lease l = *h.lease();
  REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  const protocol::Lease l2 = *h.lease();
  const StoredState before = stored_state(h.config);
  const auto leases_before = h.collector.metrics().queue.leases;

  for (const std::string_view token : {std::string_view(), std::string_view("wrong"), kToken.substr(0, 5)}) {
    INFO("token: '" << token << "'");
    const std::vector<std::pair<Verb, std::string>> requests = {
        {Verb::get, "/metrics"},
        {Verb::get, "/v1/jobs"},
        {Verb::get, fmt::format("/v1/jobs/{}", job)},
        {Verb::get, fmt::format("/v1/jobs/{}/image", job)},
        {Verb::post, fmt::format("/v1/jobs/{}/cancel", job)},
        {Verb::get, "/v1/scenes/" + l.digest},
        {Verb::get, "/v1/nowhere"},
    };
    for (const auto& [verb, target] : requests) {
      const Response res = h.call(verb, target, "", token);
      CHECK(res.result() == Status::unauthorized);
      CHECK(res[boost::beast::http::field::www_authenticate] == "Bearer");
    }
    CHECK(h.call(Verb::post, "/v1/jobs", submit_body(), token).result() == Status::unauthorized);
    CHECK(h.call(Verb::post, "/v1/lease", R"({"worker": "x", "threads": 1})", token).result() == Status::unauthorized);
    CHECK(h.put(job, l2.tile, payload(job, l2.tile, l2.rect), token).result() == Status::unauthorized);
  }
  CHECK(stored_state(h.config) == before);
  CHECK(h.collector.metrics().queue.leases == leases_before);
  CHECK(h.status(job).state == protocol::JobState::kRendering);
  CHECK(h.status(job).tiles_done == 1);
  CHECK(metric(h, &coll::CollectorCounters::auth_failures) == 30);
}

TEST_CASE("cancel stops leases, refuses tiles with job_gone, and is durable", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t job = h.submit();
  const protocol::Lease a = *h.lease();
  const protocol::Lease b = *h.lease();
  REQUIRE(h.put_ok(a) == protocol::SubmitResult::kStored);

  Response res = h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job));
  REQUIRE(res.result() == Status::ok);
  CHECK(protocol::decode_job_status(res.body()).value().state == protocol::JobState::kCancelled);
  CHECK(stored_state(h.config).jobs[0].state == "cancelled");
  CHECK_FALSE(h.lease());
  res = h.put(job, b.tile, payload(job, b.tile, b.rect));
  CHECK(res.result() == Status::gone);
  CHECK(stored_state(h.config).tiles[1].size() == 1);
  // Again: still cancelled, still 200.
  CHECK(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job)).result() == Status::ok);
  // The partial image is still there to look at.
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, {a.tile}).rgb);

  // A finished job cannot be cancelled.
  const std::uint64_t other = h.submit();
  for (const auto& l : h.lease_all()) h.put_ok(l);
  REQUIRE(h.status(other).state == protocol::JobState::kDone);
  res = h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", other));
  CHECK(res.result() == Status::conflict);

  // After a restart the cancelled job stays cancelled and is not leased.
  h.collector.stop();
  h.collector.run();
  coll::Collector again(h.config);
  REQUIRE_FALSE(again.open());
  const Response lease = again.handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
  CHECK(std::holds_alternative<protocol::RetryAfter>(protocol::decode_lease_reply(lease.body()).value()));
  const Response status = again.handle_sync(make(Verb::get, fmt::format("/v1/jobs/{}", job)));
  CHECK(protocol::decode_job_status(status.body()).value().state == protocol::JobState::kCancelled);
  CHECK(protocol::decode_job_status(status.body()).value().tiles_done == 1);
}

TEST_CASE("higher priority first, then submission order", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  REQUIRE_FALSE(h.collector.open());
  const std::uint64_t low = h.submit(R"(, "width": 8, "height": 8)");
  const std::uint64_t high = h.submit(R"(, "width": 8, "height": 8, "priority": 5)");
  const std::uint64_t low2 = h.submit(R"(, "width": 8, "height": 8)");
  auto leases = h.lease_all();
  REQUIRE(leases.size() == 3);
  CHECK(leases[0].job == high);
  CHECK(leases[1].job == low);
  CHECK(leases[2].job == low2);
}

TEST_CASE("a restart resumes the job with its stored tiles, which are never leased again", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::set<std::uint32_t> first;
  std::uint64_t job = 0;
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    job = h.submit();
    auto leases = h.lease_all();
    for (std::size_t i = 0; i < 5; ++i) {
      REQUIRE(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);
      first.insert(leases[i].tile);
    }
    // Destroyed without stop(): the writer drains in the destructor.
  }
  Harness h(config);
  REQUIRE_FALSE(h.collector.open());
  coll::MetricsSnapshot m = h.collector.metrics();
  CHECK(m.epoch == 2);
  CHECK(m.restored_tiles == 5);
  protocol::JobStatus s = h.status(job);
  CHECK(s.state == protocol::JobState::kRendering);
  CHECK(s.tiles_done == 5);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, first).rgb);

  auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - 5);
  for (const auto& l : leases) CHECK_FALSE(first.contains(l.tile));
  // A worker whose acknowledgement was lost retries a stored tile: already done, counted.
  const auto rects = dtraced::scene::TileGrid(32, 24, 8).all();
  const std::uint32_t restored = *first.begin();
  CHECK(h.put(job, restored, payload(job, restored, rects[restored])).result() == Status::ok);
  for (const auto& l : leases) REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  m = h.collector.metrics();
  CHECK(m.counters.restored_tile_leases == 0);
  CHECK(m.counters.restored_tile_submissions == 1);
  CHECK(m.counters.tiles_stored == kTiles - 5);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  std::set<std::uint32_t> all;
  for (std::uint32_t t = 0; t < kTiles; ++t) all.insert(t);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all).rgb);

  // Every tile records the start that acknowledged it.
  auto opened = store::Store::open(config.state_dir, {.verify_integrity = false});
  REQUIRE(opened.ok());
  auto tiles = opened.value().get_all_tiles(static_cast<std::int64_t>(job));
  REQUIRE(tiles.ok());
  for (const auto& t : tiles.value()) {
    CHECK(t.worker == fmt::format("epoch={} worker=unknown", first.contains(t.tile) ? 1 : 2));
  }
}

TEST_CASE("after a SIGKILL, acknowledged tiles are restored and not leased again", "[collector][service][crash]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  constexpr std::size_t kAcked = 7;
  int pipe_fds[2];
  REQUIRE(::pipe(pipe_fds) == 0);
  const pid_t child = ::fork();
  REQUIRE(child >= 0);
  if (child == 0) {
    // The child: no Catch2 here; any failure ends it with a nonzero status before it reports.
    ::close(pipe_fds[0]);
    coll::Collector c(config);
    if (c.open()) ::_exit(2);
    const Response created = c.handle_sync(make(Verb::post, "/v1/jobs", submit_body()));
    if (created.result() != Status::created) ::_exit(3);
    std::string acked;
    for (std::size_t i = 0; i < kAcked; ++i) {
      const Response res = c.handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
      const auto reply = protocol::decode_lease_reply(res.body());
      if (!reply.ok() || !std::holds_alternative<protocol::Lease>(reply.value())) ::_exit(5);
      const protocol::Lease l = std::get<protocol::Lease>(reply.value());
      const Response put = c.handle_sync(
          make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l.job, l.tile), payload(l.job, l.tile, l.rect)));
      if (put.result() != Status::ok) ::_exit(4);
      acked += fmt::format("{} ", l.tile);
    }
    // One more leased but never submitted: it must come back after the crash.
    c.handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
    acked += "\n";
    if (::write(pipe_fds[1], acked.data(), acked.size()) != static_cast<ssize_t>(acked.size())) ::_exit(5);
    for (;;) ::pause();  // killed here, with the writer thread and the loop still alive
  }
  ::close(pipe_fds[1]);
  std::string report;
  char buf[256];
  for (;;) {
    const ssize_t n = ::read(pipe_fds[0], buf, sizeof buf);
    if (n <= 0) break;
    report.append(buf, static_cast<std::size_t>(n));
    if (report.find('\n') != std::string::npos) break;
  }
  ::close(pipe_fds[0]);
  ::kill(child, SIGKILL);
  int wstatus = 0;
  ::waitpid(child, &wstatus, 0);
  REQUIRE(report.find('\n') != std::string::npos);
  std::set<std::uint32_t> acked;
  {
    std::istringstream in(report);
    std::uint32_t t = 0;
    while (in >> t) acked.insert(t);
  }
  REQUIRE(acked.size() == kAcked);

  Harness h(config);
  REQUIRE_FALSE(h.collector.open());
  CHECK(h.collector.metrics().restored_tiles == kAcked);
  CHECK(h.collector.metrics().epoch == 2);
  auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - kAcked);
  for (const auto& l : leases) CHECK_FALSE(acked.contains(l.tile));
  for (const auto& l : leases) h.put_ok(l);
  CHECK(h.collector.metrics().counters.restored_tile_leases == 0);
  CHECK(h.status(1).state == protocol::JobState::kDone);
  std::set<std::uint32_t> all;
  for (std::uint32_t t = 0; t < kTiles; ++t) all.insert(t);
  std::string error;
  auto img = dtraced::image::read_image((dir.path() / "out" / "job-1.png").string(), error);
  REQUIRE(img);
}

TEST_CASE("a job whose tiles were all stored but whose image was not written gets it written at start",
          "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    const std::uint64_t job = h.submit();
    for (const auto& l : h.lease_all()) h.put_ok(l);
    REQUIRE(h.status(job).state == protocol::JobState::kDone);
  }
  // Simulate a crash between the last commit and the image: the job back to rendering, no file.
  {
    auto opened = store::Store::open(config.state_dir);
    REQUIRE(opened.ok());
    REQUIRE(opened.value().set_job_state(1, store::kJobRendering, 0).ok());
  }
  fs::remove(dir.path() / "out" / "job-1.png");
  Harness h(config);
  REQUIRE_FALSE(h.collector.open());
  h.collector.run_until_idle();
  CHECK(fs::exists(dir.path() / "out" / "job-1.png"));
  CHECK(h.status(1).state == protocol::JobState::kDone);
  CHECK(stored_state(config).jobs[0].state == "done");
  CHECK(h.collector.metrics().queue.leases == 0);
}

TEST_CASE("a corrupt database stops start-up with a message and is left untouched", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  fs::create_directories(config.state_dir);
  const std::string db = (fs::path(config.state_dir) / store::kDatabaseFileName).string();
  std::string garbage(8192, '\0');
  for (std::size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<char>(i * 7 + 3);
  {
    std::ofstream out(db, std::ios::binary);
    out << garbage;
  }
  coll::Collector c(config);
  const auto error = c.open();
  REQUIRE(error);
  CHECK_THAT(*error, Catch::Matchers::Contains("dtraced.db"));
  std::string read_error;
  CHECK(dtraced::util::read_file_limited(db, 1 << 20, read_error).value() == garbage);
  // The start counter was not advanced either.
  CHECK_FALSE(fs::exists(fs::path(config.state_dir) / coll::kEpochFileName));
  CHECK(c.handle_sync(make(Verb::get, "/v1/jobs")).result() == Status::service_unavailable);
}

TEST_CASE("a broken start counter stops start-up", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  fs::create_directories(config.state_dir);
  {
    std::ofstream out(fs::path(config.state_dir) / coll::kEpochFileName);
    out << "twelve\n";
  }
  coll::Collector c(config);
  const auto error = c.open();
  REQUIRE(error);
  CHECK_THAT(*error, Catch::Matchers::Contains("collector.epoch"));
}

TEST_CASE("the one-shot job is enqueued once and resumed after a restart", "[collector][service][one-shot]") {
  TempDir dir;
  const std::string scene_path = (dir.path() / "scene.json").string();
  {
    std::ofstream out(scene_path);
    out << kScene;
  }
  coll::CollectorConfig config = make_config(dir);
  config.one_shot = one_shot(scene_path, "shot.png");
  config.one_shot->overrides.width = 16;
  config.one_shot->overrides.samples = 2;
  config.one_shot->overrides.tile_size = 8;
  config.exit_when_done = true;

  std::set<std::uint32_t> first;
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    protocol::JobStatus s = h.status(1);
    CHECK(s.output == "shot.png");
    CHECK(s.width == 16);
    CHECK(s.height == 24);
    CHECK(s.samples == 2);
    CHECK(s.tiles_total == 6);
    const protocol::Lease l = *h.lease();
    h.put_ok(l);
    first.insert(l.tile);
  }
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    CHECK(stored_state(config).jobs.size() == 1);  // resumed, not copied
    CHECK(h.status(1).tiles_done == 1);
    auto leases = h.lease_all();
    CHECK(leases.size() == 5);
    for (const auto& l : leases) CHECK_FALSE(first.contains(l.tile));
    for (const auto& l : leases) h.put_ok(l);
    // The image is written and the collector stops itself.
    CHECK(fs::exists(dir.path() / "out" / "shot.png"));
    CHECK(h.collector.run() == 0);
  }
  {
    // Once more with the same arguments: nothing to do, exit 0 at once.
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    REQUIRE_FALSE(h.collector.listen());
    CHECK(h.collector.port() == 0);  // never listened
    CHECK(h.collector.run() == 0);
    CHECK(stored_state(config).jobs.size() == 1);
  }
  {
    // A different output is a different job.
    config.one_shot->output = "other.png";
    config.exit_when_done = false;
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    CHECK(stored_state(config).jobs.size() == 2);
  }
}

TEST_CASE("a one-shot job takes adaptive sampling's settings, checked like a submission",
          "[collector][service][one-shot][adaptive]") {
  TempDir dir;
  const std::string scene_path = (dir.path() / "scene.json").string();
  {
    std::ofstream out(scene_path);
    out << kScene;
  }
  coll::CollectorConfig config = make_config(dir);
  config.one_shot = one_shot(scene_path, "shot.png");
  config.one_shot->overrides.samples = 16;
  config.one_shot->overrides.error_target = 0.1;
  config.one_shot->overrides.min_samples = 4;
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    const protocol::Lease l = *h.lease();
    CHECK(l.settings.samples == 16);
    CHECK(l.settings.error_target == 0.1);
    CHECK(l.settings.min_samples == 4);
  }
  // Out of range: start-up stops and names the field.
  TempDir dir2;
  config = make_config(dir2);
  config.one_shot = one_shot(scene_path, "shot.png");
  config.one_shot->overrides.error_target = 2.0;
  coll::Collector c(config);
  const auto error = c.open();
  REQUIRE(error);
  CHECK_THAT(*error, Catch::Matchers::Contains("error_target"));
}

TEST_CASE("a one-shot job with a bad scene stops start-up", "[collector][service][one-shot]") {
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.one_shot = one_shot((dir.path() / "missing.json").string(), "x.png");
  coll::Collector c(config);
  const auto error = c.open();
  REQUIRE(error);
  CHECK_THAT(*error, Catch::Matchers::Contains("missing.json"));
}

TEST_CASE("over a real socket: listen, serve, and stop gracefully", "[collector][service][socket]") {
  TempDir dir;
  coll::Collector c(make_config(dir));
  REQUIRE_FALSE(c.open());
  REQUIRE_FALSE(c.listen());
  REQUIRE(c.port() != 0);
  auto code = std::async(std::launch::async, [&c] { return c.run(); });
  std::string error;
  const auto url = dtraced::http::parse_base_url(fmt::format("http://127.0.0.1:{}", c.port()), error);
  REQUIRE(url);
  const dtraced::http::ClientTimeouts timeouts{5s, 5s, 5s};
  auto res = dtraced::http::request_sync(*url, dtraced::http::make_request(Verb::get, "/healthz"), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::ok);
  res = dtraced::http::request_sync(*url, make(Verb::post, "/v1/jobs", submit_body()), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::created);
  res = dtraced::http::request_sync(*url, make(Verb::get, "/v1/jobs", "", ""), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::unauthorized);
  c.stop();
  REQUIRE(code.wait_for(20s) == std::future_status::ready);
  CHECK(code.get() == 0);
  // The job survived the stop.
  CHECK(stored_state(make_config(dir)).jobs.size() == 1);
}

// ---- adaptive sampling: per-pixel sample counts ----------------------------------------------------

namespace {

// Counts a worker of an adaptive job (samples 16, min_samples 4) could send: checkpoints 4 and 8,
// or all 16.
std::vector<std::uint32_t> fake_counts(std::uint32_t tile, const dtraced::scene::TileRect& rect) {
  std::vector<std::uint32_t> spp(std::size_t{rect.width} * rect.height);
  for (std::size_t i = 0; i < spp.size(); ++i) spp[i] = std::uint32_t{4} << ((tile + i) % 3);
  return spp;
}

std::string adaptive_payload(const protocol::Lease& l, std::vector<std::uint32_t> spp) {
  return protocol::encode_tile_payload({l.job, l.tile, l.rect, fake_pixels(l.job, l.tile, l.rect), std::move(spp)});
}

constexpr std::string_view kAdaptive = R"(, "samples": 16, "error_target": 0.1, "min_samples": 4)";

}  // namespace

TEST_CASE("an adaptive job: counts checked, stored with the pixels, and their mean survives restarts",
          "[collector][service][adaptive]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::uint64_t job = 0, uniform = 0;
  std::uint64_t sum = 0, pixels = 0;
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    job = h.submit(kAdaptive);
    CHECK_FALSE(h.status(job).mean_spp.has_value());  // nothing stored yet
    auto leases = h.lease_all();
    REQUIRE(leases.size() == kTiles);
    for (const auto& l : leases) {
      CHECK(l.settings.error_target == 0.1);
      CHECK(l.settings.min_samples == 4);
      CHECK(l.settings.samples == 16);
    }
    const protocol::Lease& l = leases[0];
    const auto refused = [&](std::string body, std::string_view fragment) {
      const Response res = h.put(l.job, l.tile, std::move(body));
      CHECK(res.result() == Status::bad_request);
      const protocol::ErrorBody e = error_of(res);
      CHECK(e.field == "/spp");
      CHECK(e.error.find(fragment) != std::string::npos);
    };
    refused(payload(l.job, l.tile, l.rect), "no sample counts");
    std::vector<std::uint32_t> bad = fake_counts(l.tile, l.rect);
    bad[3] = 17;
    refused(adaptive_payload(l, bad), "took 17 samples");
    bad[3] = 0;
    refused(adaptive_payload(l, bad), "took 0 samples");
    CHECK(h.status(job).tiles_done == 0);

    for (std::size_t i = 0; i < 5; ++i) {
      const auto counts = fake_counts(leases[i].tile, leases[i].rect);
      const Response res = h.put(leases[i].job, leases[i].tile, adaptive_payload(leases[i], counts));
      REQUIRE(res.result() == Status::ok);
      for (const std::uint32_t n : counts) sum += n;
      pixels += counts.size();
    }
    const protocol::JobStatus s = h.status(job);
    REQUIRE(s.mean_spp.has_value());
    CHECK(*s.mean_spp == double(sum) / double(pixels));
    CHECK(*s.mean_spp > 4.0);
    CHECK(*s.mean_spp < 16.0);

    // A uniform job takes no counts, and its mean is its samples once a tile is stored.
    uniform = h.submit();
    auto more = h.lease_all();
    REQUIRE_FALSE(more.empty());
    const Response res = h.put(more[0].job, more[0].tile, adaptive_payload(more[0], fake_counts(0, more[0].rect)));
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).error.find("uniformly") != std::string::npos);
    CHECK_FALSE(h.status(uniform).mean_spp.has_value());
    REQUIRE(h.put_ok(more[0]) == protocol::SubmitResult::kStored);
    CHECK(h.status(uniform).mean_spp == 1.0);
  }
  {
    // Restarted while rendering: the stored counts are read back with the pixels.
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
    for (const auto& l : h.lease_all()) {
      if (l.job != job) continue;
      const auto counts = fake_counts(l.tile, l.rect);
      REQUIRE(h.put(l.job, l.tile, adaptive_payload(l, counts)).result() == Status::ok);
      for (const std::uint32_t n : counts) sum += n;
      pixels += counts.size();
    }
    CHECK(h.status(job).state == protocol::JobState::kDone);
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
  }
  // The blobs are the floats followed by the counts.
  {
    auto opened = store::Store::open(config.state_dir, {.verify_integrity = false});
    REQUIRE(opened.ok());
    auto tile = opened.value().get_tile(static_cast<std::int64_t>(job), 0);
    REQUIRE(tile.ok());
    REQUIRE(tile.value());
    CHECK(tile.value()->pixels.size() == 8 * 8 * 16);
  }
  // Restarted once done: the mean is read back from the store after start-up (on the pool; the
  // first request runs the loop until that is done).
  {
    Harness h(config);
    REQUIRE_FALSE(h.collector.open());
    CHECK(pixels == 32 * 24);
    CHECK(h.status(job).state == protocol::JobState::kDone);
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
    CHECK(h.status(uniform).mean_spp == 1.0);
  }
  // A finished job's stored tile damaged behind the collector's back (cut short): start-up still
  // succeeds, the job stays done and its mean is unknown rather than wrong.
  {
    sqlite3* db = nullptr;
    const std::string path = (fs::path(config.state_dir) / store::kDatabaseFileName).string();
    REQUIRE(sqlite3_open(path.c_str(), &db) == SQLITE_OK);
    const std::string sql =
        fmt::format("UPDATE tiles SET pixels = substr(pixels, 1, 100) WHERE job = {} AND tile = 1", job);
    CHECK(sqlite3_exec(db, sql.c_str(), nullptr, nullptr, nullptr) == SQLITE_OK);
    CHECK(sqlite3_changes(db) == 1);
    sqlite3_close(db);
  }
  Harness h(config);
  REQUIRE_FALSE(h.collector.open());
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK_FALSE(h.status(job).mean_spp.has_value());
  CHECK(h.status(uniform).mean_spp == 1.0);
}
