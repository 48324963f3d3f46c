// The collector's service driven through its request handler, without sockets: each request runs
// the loop until the answer and the work it started are done (Collector::handle_sync). Submit ->
// lease -> tiles -> image; outputs; duplicates and faulty duplicates; uploads in flight at once;
// refused payloads and bodies; unknown jobs; the token; cancel; priorities; the configuration.
// Restarts are in test_collector_restart.cpp, time and sockets in test_collector_clock.cpp, the
// pure checks in test_collector_checks.cpp.
#include <cstdint>
#include <filesystem>
#include <limits>
#include <set>
#include <string>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector_testing.h"
#include "util/file.h"
#include "util/sha256.h"

using namespace dtraced::testing;

// ---- configuration --------------------------------------------------------------------------------

TEST_CASE("collector configuration is validated, every problem naming its option", "[collector][config]") {
  TempDir dir;
  coll::CollectorConfig c = make_config(dir);
  CHECK(coll::check_collector_config(c).empty());
  const auto paths = [](const coll::CollectorConfig& config) {
    std::vector<std::string> out;
    for (const auto& e : coll::check_collector_config(config)) out.push_back(e.path);
    return out;
  };
  c.token = "";
  CHECK(coll::check_collector_config(c) ==
        dtraced::util::Errors{{"must not be empty (the collector never runs without authentication)", "token"}});
  c.token = "has space";
  CHECK(paths(c) == std::vector<std::string>{"token"});
  c = make_config(dir);
  c.listen_address = "localhost";
  CHECK(dtraced::util::to_string(coll::check_collector_config(c)) ==
        "listen_address: 'localhost' is not an IPv4 or IPv6 address");
  c = make_config(dir);
  c.exit_when_done = true;
  CHECK(paths(c) == std::vector<std::string>{"exit_when_done"});
  c.one_shot = one_shot("scene.json", "../x.png");
  CHECK(paths(c) == std::vector<std::string>{"output"});
  c.one_shot->output = "x.png";
  CHECK(coll::check_collector_config(c).empty());
  c.queue.max_copies = 0;
  CHECK(paths(c) == std::vector<std::string>{"queue.max_copies"});
  // Every problem at once, in the order of the options.
  c.state_dir = "";
  c.limits.read_timeout = 0ms;
  c.cpu_threads = 0;
  CHECK(paths(c) == std::vector<std::string>{"state_dir", "limits.read_timeout", "queue.max_copies", "cpu_threads"});
  CHECK(make_config(dir).effective_output_dir() == (dir.path() / "out").string());

  // A collector is made only from a usable configuration.
  auto refused = coll::Collector::create(c);
  REQUIRE_FALSE(refused);
  CHECK(refused.error().size() == 4);
  CHECK(coll::Collector::create(make_config(dir)).ok());
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
    job = h.submit(R"(, "png_bit_depth": 16, "background": [0.5, 0.25, 1])");
    for (const auto& l : h.lease_all()) {
      CHECK(l.settings.background == dtraced::scene::Color{0.5, 0.25, 1});
      h.put_ok(l);
    }
    REQUIRE(h.status(job).state == protocol::JobState::kDone);
    const auto written = dtraced::util::read_file_limited((dir.path() / "out" / "job-1.png").string(), 1 << 20);
    REQUIRE(written);
    CHECK(png_bit_depth(*written) == 16);
  }
  // After a restart the job's bit depth comes back from the store: the image is served at 16 bits.
  Harness again(dir);
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

  // Store all but the last a second later; the partial image shows them, black elsewhere.
  h.clock.advance(1s);
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
  auto written = dtraced::image::read_image((dir.path() / "out" / "job-1.png").string());
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
  const std::uint64_t job = h.submit(R"(, "output": "picture.pfm", "width": 16, "height": 8)");
  auto leases = h.lease_all();
  REQUIRE(leases.size() == 2);
  for (const auto& l : leases) h.put_ok(l);
  CHECK(h.status(job).output == "picture.pfm");
  auto img = dtraced::image::read_image((dir.path() / "out" / "picture.pfm").string());
  REQUIRE(img);
  CHECK(img->rgb == expected_image(job, 16, 8, 8, {0, 1}).rgb);
}

TEST_CASE("duplicates are answered already_done, and different pixels count as faulty", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
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
  // The store holds the pixels as pixels_to_blob lays them out (the upload's own bytes went there).
  {
    auto opened = dtraced::store::Store::open(h.config.state_dir, {.verify_integrity = false});
    REQUIRE(opened.ok());
    const auto stored = opened.value().get_tile(static_cast<std::int64_t>(job), leases[0].tile);
    REQUIRE(stored.ok());
    REQUIRE(stored.value());
    CHECK(stored.value()->pixels == coll::pixels_to_blob(fake_pixels(job, leases[0].tile, leases[0].rect)));
  }

  // Once the job is done its pixels are in the store only: duplicates are compared there.
  for (std::size_t i = 1; i < leases.size(); ++i) h.put_ok(leases[i]);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  CHECK(h.put_ok(leases[3]) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 1);
  CHECK(h.put_ok(leases[3], /*salt=*/1.0f) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 2);
  CHECK(stored_state(h.config).tiles[1].size() == kTiles);
}

namespace {
// The process's resident memory, from /proc (Linux); 0 where it cannot be read.
std::uint64_t resident_bytes() {
  const auto text = dtraced::util::read_file_limited("/proc/self/status", 1 << 20);
  if (!text.ok()) return 0;
  const std::string& s = text.value();
  const std::size_t at = s.find("VmRSS:");
  if (at == std::string::npos) return 0;
  return std::stoull(s.substr(at + 6)) * 1024;  // "VmRSS:   1234 kB"
}
}  // namespace

TEST_CASE("a large job's stored tiles stay in the store: no framebuffer in memory", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  // 16384 x 8192 pixels: a float framebuffer would be 1.5 GiB, filled at the first stored tile.
  const Response res =
      h.call(Verb::post, "/v1/jobs",
             fmt::format(R"({{"scene": {}, "tile_size": 32, "width": 16384, "height": 8192}})", kScene));
  REQUIRE(res.result() == Status::created);
  const std::uint64_t job = protocol::decode_job_created(res.body()).value().id;
  const auto first = h.lease();
  REQUIRE(first);
  const auto second = h.lease();
  REQUIRE(second);
  const std::uint64_t before = resident_bytes();
  REQUIRE(before > 0);
  REQUIRE(h.put_ok(*first) == protocol::SubmitResult::kStored);
  REQUIRE(h.put_ok(*second) == protocol::SubmitResult::kStored);
  const std::uint64_t after = resident_bytes();
  CHECK(after < before + (std::uint64_t{256} << 20));
  CHECK(h.status(job).tiles_done == 2);
  // The pixels are read back from the store: a duplicate is compared there.
  CHECK(h.put_ok(*first, /*salt=*/0.25f) == protocol::SubmitResult::kAlreadyDone);
  CHECK(metric(h, &coll::CollectorCounters::faulty_results) == 1);
}

TEST_CASE("two uploads of one tile in flight at once: one stored, one already_done", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
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
  auto again = must_create(h.config);
  require_ok(again->open());
  const Response lease = again->handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
  CHECK(std::holds_alternative<protocol::RetryAfter>(protocol::decode_lease_reply(lease.body()).value()));
  const Response status = again->handle_sync(make(Verb::get, fmt::format("/v1/jobs/{}", job)));
  CHECK(protocol::decode_job_status(status.body()).value().state == protocol::JobState::kCancelled);
  CHECK(protocol::decode_job_status(status.body()).value().tiles_done == 1);
}

TEST_CASE("higher priority first, then submission order", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t low = h.submit(R"(, "width": 8, "height": 8)");
  const std::uint64_t high = h.submit(R"(, "width": 8, "height": 8, "priority": 5)");
  const std::uint64_t low2 = h.submit(R"(, "width": 8, "height": 8)");
  auto leases = h.lease_all();
  REQUIRE(leases.size() == 3);
  CHECK(leases[0].job == high);
  CHECK(leases[1].job == low);
  CHECK(leases[2].job == low2);
}

TEST_CASE("an idle worker of a small farm asks again sooner than one of a large farm", "[collector][service]") {
  TempDir dir;
  Harness h(dir);
  // The retry hint a worker named `name` gets from a collector with no work.
  const auto hint = [&h](const std::string& name) {
    const Response res = h.call(Verb::post, "/v1/lease", fmt::format(R"({{"worker": "{}", "threads": 1}})", name));
    REQUIRE(res.result() == Status::ok);
    auto reply = protocol::decode_lease_reply(res.body());
    REQUIRE(reply.ok());
    const auto* retry = std::get_if<protocol::RetryAfter>(&reply.value());
    REQUIRE(retry != nullptr);
    return retry->ms;
  };
  // One worker: the shortest wait the queue allows (50 ms), not the longest (500 ms).
  CHECK(hint("only") == 50);
  // 40 workers known: 5 ms each, so that all of them together ask about 200 times a second.
  for (int i = 1; i < 39; ++i) hint(fmt::format("w{}", i));
  CHECK(hint("w39") == 200);
  // Past 100 workers the rule goes on growing: 151 workers wait 755 ms (the old 500 ms ceiling
  // is gone: the default is 5 s, --max-idle-wait-ms).
  for (int i = 40; i < 150; ++i) hint(fmt::format("w{}", i));
  CHECK(hint("w150") == 755);
}

TEST_CASE("the idle wait grows with the farm up to --max-idle-wait-ms", "[collector][service][limits]") {
  TempDir dir;
  // The retry hint of `name`, asking `h`'s collector, which has no work.
  const auto hint = [](Harness& h, const std::string& name) {
    const Response res = h.call(Verb::post, "/v1/lease", fmt::format(R"({{"worker": "{}", "threads": 1}})", name));
    REQUIRE(res.result() == Status::ok);
    auto reply = protocol::decode_lease_reply(res.body());
    REQUIRE(reply.ok());
    const auto* retry = std::get_if<protocol::RetryAfter>(&reply.value());
    REQUIRE(retry != nullptr);
    return retry->ms;
  };
  SECTION("the default ceiling, 5 s: reached at 1,000 known workers") {
    CHECK(coll::QueueConfig{}.max_retry_after == 5s);
    Harness h(dir);
    for (int i = 1; i < 999; ++i) hint(h, fmt::format("w{}", i));
    CHECK(hint(h, "w999") == 4995);
    CHECK(hint(h, "w1000") == 5000);
    for (int i = 1001; i < 1200; ++i) hint(h, fmt::format("w{}", i));
    CHECK(hint(h, "w1200") == 5000);
  }
  SECTION("a ceiling of 2 s: 300 workers wait 1.5 s, 500 and more 2 s") {
    coll::CollectorConfig c = make_config(dir);
    c.queue.max_retry_after = 2s;
    Harness h(std::move(c));
    for (int i = 1; i < 300; ++i) hint(h, fmt::format("w{}", i));
    CHECK(hint(h, "w300") == 1500);
    for (int i = 301; i < 600; ++i) hint(h, fmt::format("w{}", i));
    CHECK(hint(h, "w600") == 2000);
  }
  SECTION("the old ceiling, 500 ms, as a flag value") {
    coll::CollectorConfig c = make_config(dir);
    c.queue.max_retry_after = 500ms;
    Harness h(std::move(c));
    for (int i = 1; i < 200; ++i) hint(h, fmt::format("w{}", i));
    CHECK(hint(h, "w200") == 500);
  }
}

TEST_CASE("the configuration bounds the farm limits and names each one", "[collector][limits]") {
  TempDir dir;
  coll::CollectorConfig c = make_config(dir);
  const auto paths = [](const coll::CollectorConfig& config) {
    std::vector<std::string> out;
    for (const auto& e : coll::check_collector_config(config)) out.push_back(e.path);
    return out;
  };
  CHECK(c.workers.max_workers == coll::kDefaultMaxWorkers);
  CHECK(c.workers.max_workers >= 10'000);  // a 10,000-worker farm does not trip it
  c.workers.max_workers = coll::kMaxMaxWorkers;
  c.limits.max_idle_connections = 100'000;
  c.queue.max_retry_after = std::chrono::milliseconds(protocol::kMaxRetryAfterMs);
  CHECK(coll::check_collector_config(c).empty());
  c.workers.max_workers = coll::kMaxMaxWorkers + 1;
  CHECK(paths(c) == std::vector<std::string>{"workers.max_workers"});
  c.workers.max_workers = 0;
  CHECK(paths(c) == std::vector<std::string>{"workers.max_workers"});
  c = make_config(dir);
  c.limits.max_idle_connections = 0;
  CHECK(paths(c) == std::vector<std::string>{"limits.max_idle_connections"});
  c = make_config(dir);
  c.queue.max_retry_after = std::chrono::milliseconds(protocol::kMaxRetryAfterMs + 1);
  CHECK(paths(c) == std::vector<std::string>{"queue.max_retry_after"});
}
