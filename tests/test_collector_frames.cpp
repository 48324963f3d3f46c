// A farm job of several frames, through the collector's handler: one queue across the frames
// (lowest frames first, each lease the frame's number and its tile's rectangle), each frame's
// image written as soon as it and the frames before it are complete, the frame progress in the
// status, any frame fetched (partial while it renders), and a restart that resumes every
// unfinished frame, writes the complete ones, and never leases a stored tile again.
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/queue.h"
#include "collector/routes.h"
#include "collector_testing.h"
#include "image/gif_io.h"
#include "image/image_io.h"
#include "util/file.h"

namespace {

using namespace dtraced::testing;
namespace image = dtraced::image;
namespace scene = dtraced::scene;

// Frames 4, 6 and 8 of kScene in tiles of 8: 3 x 12 tiles.
constexpr std::string_view kFrames = R"(, "frames": {"first": 4, "last": 8, "step": 2}, "output": "seq-%04d.pfm")";
constexpr std::uint32_t kFrameCount = 3;

fs::path out_file(const TempDir& dir, std::uint32_t frame) {
  return dir.path() / "out" / fmt::format("seq-{:04d}.pfm", frame);
}

// The image frame `frame_index` of job `job` must hold: the fake pixels of its tiles.
image::ImageRGBf expected_image_of(std::uint64_t job, std::uint32_t frame_index, const std::set<std::uint32_t>& tiles) {
  image::ImageRGBf img(32, 24);
  const auto rects = scene::TileGrid(32, 24, 8).all();
  for (std::uint32_t t : tiles) {
    const std::uint32_t index = frame_index * kTiles + t;
    coll::copy_tile(img, rects[t], fake_pixels(job, index, rects[t]));
  }
  return img;
}
// Its pixels, to compare.
std::vector<float> expected_frame(std::uint64_t job, std::uint32_t frame_index, const std::set<std::uint32_t>& tiles) {
  return expected_image_of(job, frame_index, tiles).rgb;
}

std::vector<float> read_pfm(const fs::path& path) {
  auto img = image::read_image(path.string());
  if (!img) INFO(img.error().to_string());
  REQUIRE(img);
  return img->rgb;
}

std::vector<float> fetch_frame(Harness& h, std::uint64_t job, std::uint32_t frame) {
  const Response res = h.call(Verb::get, fmt::format("/v1/jobs/{}/image?format=pfm&frame={}", job, frame));
  REQUIRE(res.result() == Status::ok);
  auto img = image::decode_image(image::ImageFormat::kPfm, res.body(), "pfm");
  REQUIRE(img);
  return img->rgb;
}

}  // namespace

TEST_CASE("the queue hands out a frame range's tiles lowest frame first", "[collector][frames]") {
  coll::WorkQueue q;
  const coll::TimePoint t0{};
  // Three frames of four tiles, the first tile of frame 1 already stored.
  const std::vector<coll::TileIndex> stored = {4};
  REQUIRE(q.add_job(1, 0, 12, stored));
  std::vector<coll::TileIndex> order;
  for (int i = 0; i < 11; ++i) {
    const coll::LeaseResult r = q.lease(t0);
    REQUIRE(r.grant);
    order.push_back(r.grant->tile);
  }
  CHECK(order == std::vector<coll::TileIndex>{0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11});
  CHECK_FALSE(q.lease(t0).grant);
}

TEST_CASE("a job of several frames leases each frame's tiles and writes each frame in order", "[collector][frames]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit(kFrames);
  protocol::JobStatus s = h.status(job);
  CHECK(s.tiles_total == kFrameCount * kTiles);
  REQUIRE(s.frames);
  CHECK(*s.frames == protocol::FrameProgress{kFrameCount, 0, 4, 0, kTiles});

  const std::vector<protocol::Lease> leases = h.lease_all();
  REQUIRE(leases.size() == kFrameCount * kTiles);
  const auto rects = scene::TileGrid(32, 24, 8).all();
  for (std::uint32_t i = 0; i < leases.size(); ++i) {
    INFO(i);
    CHECK(leases[i].tile == i);
    CHECK(leases[i].settings.frame == 4 + 2 * (i / kTiles));
    CHECK_FALSE(leases[i].settings.frames);
    CHECK(leases[i].rect == rects[i % kTiles]);
    CHECK(leases[i].digest == leases[0].digest);  // one scene for every frame
  }

  // Frame 6 complete and frame 4 all but one tile: nothing is written, frames go in order.
  for (std::uint32_t i = 0; i + 1 < kTiles; ++i) h.put_ok(leases[i]);
  for (std::uint32_t i = kTiles; i < 2 * kTiles; ++i) h.put_ok(leases[i]);
  CHECK_FALSE(fs::exists(out_file(dir, 4)));
  CHECK_FALSE(fs::exists(out_file(dir, 6)));
  s = h.status(job);
  CHECK(*s.frames == protocol::FrameProgress{kFrameCount, 0, 4, kTiles - 1, kTiles});
  // A partial frame while it renders; a frame the job does not render is 404.
  std::set<std::uint32_t> most = all_tiles();
  most.erase(kTiles - 1);
  CHECK(fetch_frame(h, job, 4) == expected_frame(job, 0, most));
  CHECK(h.call(Verb::get, fmt::format("/v1/jobs/{}/image?frame=5", job)).result() == Status::not_found);

  // Frame 4's last tile: frames 4 and 6 are written, and the job renders frame 8.
  h.put_ok(leases[kTiles - 1]);
  CHECK(read_pfm(out_file(dir, 4)) == expected_frame(job, 0, all_tiles()));
  CHECK(read_pfm(out_file(dir, 6)) == expected_frame(job, 1, all_tiles()));
  s = h.status(job);
  CHECK(s.state == protocol::JobState::kRendering);
  CHECK(*s.frames == protocol::FrameProgress{kFrameCount, 2, 8, 0, kTiles});
  // A written frame comes from the store.
  CHECK(fetch_frame(h, job, 6) == expected_frame(job, 1, all_tiles()));

  for (std::uint32_t i = 2 * kTiles; i < leases.size(); ++i) h.put_ok(leases[i]);
  s = h.status(job);
  CHECK(s.state == protocol::JobState::kDone);
  CHECK(*s.frames == protocol::FrameProgress{kFrameCount, kFrameCount, 8, kTiles, kTiles});
  CHECK(read_pfm(out_file(dir, 8)) == expected_frame(job, 2, all_tiles()));
  CHECK(fetch_frame(h, job, 8) == expected_frame(job, 2, all_tiles()));
  CHECK(fetch_frame(h, job, 4) == expected_frame(job, 0, all_tiles()));
}

TEST_CASE("a restart resumes a sequence: complete frames written, stored tiles never leased", "[collector][frames]") {
  TempDir dir;
  std::uint64_t job = 0;
  std::vector<protocol::Lease> leases;
  {
    Harness h(dir);
    job = h.submit(kFrames);
    leases = h.lease_all();
    REQUIRE(leases.size() == kFrameCount * kTiles);
    // Frame 6 complete, frame 4 missing one tile, two tiles of frame 8.
    for (std::uint32_t i = 0; i + 1 < kTiles; ++i) h.put_ok(leases[i]);
    for (std::uint32_t i = kTiles; i < 2 * kTiles + 2; ++i) h.put_ok(leases[i]);
    CHECK_FALSE(fs::exists(out_file(dir, 4)));
  }
  Harness again(dir);
  const std::vector<protocol::Lease> left = again.lease_all();
  std::vector<std::uint32_t> tiles;
  for (const auto& l : left) tiles.push_back(l.tile);
  std::vector<std::uint32_t> expected = {kTiles - 1};
  for (std::uint32_t i = 2 * kTiles + 2; i < kFrameCount * kTiles; ++i) expected.push_back(i);
  CHECK(tiles == expected);
  CHECK(left.front().settings.frame == 4);
  CHECK(left.back().settings.frame == 8);
  for (const auto& l : left) again.put_ok(l);
  CHECK(again.status(job).state == protocol::JobState::kDone);
  for (std::uint32_t k = 0; k < kFrameCount; ++k) {
    CHECK(read_pfm(out_file(dir, 4 + 2 * k)) == expected_frame(job, k, all_tiles()));
  }
}

TEST_CASE("frames complete before a restart are written at start-up", "[collector][frames]") {
  TempDir dir;
  std::uint64_t job = 0;
  {
    Harness h(dir);
    job = h.submit(kFrames);
    const auto leases = h.lease_all();
    for (std::uint32_t i = 0; i < 2 * kTiles; ++i) h.put_ok(leases[i]);
    REQUIRE(fs::exists(out_file(dir, 6)));
  }
  // As if killed after the tiles were stored and before the files were written.
  fs::remove(out_file(dir, 4));
  fs::remove(out_file(dir, 6));
  Harness again(dir);
  again.call(Verb::get, "/healthz");  // runs the loop until the writes are done
  CHECK(read_pfm(out_file(dir, 4)) == expected_frame(job, 0, all_tiles()));
  CHECK(read_pfm(out_file(dir, 6)) == expected_frame(job, 1, all_tiles()));
  CHECK(again.status(job).frames->frames_done == 2);
}

TEST_CASE("a sequence needs a frame number in its output name", "[collector][frames]") {
  TempDir dir;
  Harness h(dir);
  const Response res =
      h.call(Verb::post, "/v1/jobs", submit_body(R"(, "frames": {"first": 0, "last": 1}, "output": "one.png")"));
  CHECK(res.result() == Status::bad_request);
  CHECK(error_of(res).field == "/output");
  // Without an output name the default is a sequence pattern.
  const std::uint64_t job = h.submit(R"(, "frames": {"first": 0, "last": 1})");
  CHECK(h.status(job).output == fmt::format("job-{}-%04d.png", job));
}

// tests/data/state_v2.db: made by the release before frame ranges (schema version 2), with job 1
// done (32x24 in tiles of 16: 4 tiles) and job 2 rendering (64x48, frame 3: 4 of 12 tiles stored).
TEST_CASE("a state directory of the release before frame ranges opens, its jobs read as single frames",
          "[collector][frames][store]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  fs::create_directories(config.state_dir);
  fs::copy_file(fs::path(DTRACED_SOURCE_DIR) / "tests" / "data" / "state_v2.db",
                fs::path(config.state_dir) / "dtraced.db");
  Harness h(config);
  const protocol::JobStatus done = h.status(1);
  CHECK(done.state == protocol::JobState::kDone);
  CHECK(done.output == "done.pfm");
  CHECK(done.tiles_total == 4);
  CHECK_FALSE(done.frames);
  const protocol::JobStatus half = h.status(2);
  CHECK(half.state == protocol::JobState::kRendering);
  CHECK(half.tiles_done == 4);
  CHECK(half.tiles_total == 12);
  CHECK_FALSE(half.frames);
  // The 8 tiles not stored, of frame 3, and never a stored one.
  const auto left = h.lease_all();
  REQUIRE(left.size() == 8);
  for (const auto& l : left) {
    CHECK(l.job == 2);
    CHECK(l.settings.frame == 3);
    CHECK_FALSE(l.settings.frames);
  }
  for (const auto& l : left) h.put_ok(l);
  CHECK(h.status(2).state == protocol::JobState::kDone);
  CHECK(fs::exists(dir.path() / "out" / "half.pfm"));
  // The database keeps its schema: nothing about frames needed a new one.
  const StoredState stored = stored_state(config);
  REQUIRE(stored.jobs.size() == 2);
  CHECK(stored.jobs[1].settings_json.find("frames") == std::string::npos);
}

TEST_CASE("a sequence with a .gif output writes one GIF of every frame when the last completes",
          "[collector][frames][gif]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job =
      h.submit(R"(, "frames": {"first": 4, "last": 8, "step": 2}, "output": "seq.gif", "fps": 10, "tone": "reinhard")");
  const auto leases = h.lease_all();
  REQUIRE(leases.size() == kFrameCount * kTiles);
  for (std::uint32_t i = 0; i + 1 < leases.size(); ++i) h.put_ok(leases[i]);
  // Two frames complete, no file yet (and none per frame).
  CHECK(h.status(job).frames->frames_done == 2);
  CHECK_FALSE(fs::exists(dir.path() / "out" / "seq.gif"));
  CHECK(fs::is_empty(dir.path() / "out"));
  h.put_ok(leases.back());
  CHECK(h.status(job).state == protocol::JobState::kDone);

  // The same bytes as an encoder fed the three frames with the job's fps and tone curve.
  image::GifOptions options;
  options.fps = 10;
  options.display.tone = image::ToneCurve::kReinhard;
  auto encoder = image::GifEncoder::create(32, 24, options);
  REQUIRE(encoder);
  for (std::uint32_t k = 0; k < kFrameCount; ++k)
    require_ok(encoder->add_frame(expected_image_of(job, k, all_tiles())));
  auto expected = encoder->finish();
  REQUIRE(expected);
  const auto written = dtraced::util::read_file_limited((dir.path() / "out" / "seq.gif").string(), 1 << 20);
  REQUIRE(written);
  CHECK(*written == std::string(expected->begin(), expected->end()));
}

TEST_CASE("with an image budget smaller than one frame, every frame is still written, served and put in a GIF",
          "[collector][frames][memory]") {
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.image_memory_bytes = 1;  // a 32x24 frame is 9,216 bytes: each is assembled alone
  Harness h(config);
  const std::uint64_t pfms = h.submit(kFrames);
  const std::uint64_t gif =
      h.submit(R"(, "frames": {"first": 4, "last": 8, "step": 2}, "output": "seq.gif", "fps": 10, "tone": "reinhard")");
  for (const auto& l : h.lease_all()) h.put_ok(l);
  REQUIRE(h.status(pfms).state == protocol::JobState::kDone);
  REQUIRE(h.status(gif).state == protocol::JobState::kDone);
  std::set<std::uint32_t> all;
  for (std::uint32_t t = 0; t < kTiles; ++t) all.insert(t);
  for (std::uint32_t k = 0; k < kFrameCount; ++k) {
    INFO("frame " << k);
    CHECK(read_pfm(out_file(dir, 4 + 2 * k)) == expected_frame(pfms, k, all));
    CHECK(fetch_frame(h, pfms, 4 + 2 * k) == expected_frame(pfms, k, all));
  }
  image::GifOptions options;
  options.fps = 10;
  options.display.tone = image::ToneCurve::kReinhard;
  auto encoder = image::GifEncoder::create(32, 24, options);
  REQUIRE(encoder);
  for (std::uint32_t k = 0; k < kFrameCount; ++k) require_ok(encoder->add_frame(expected_image_of(gif, k, all)));
  auto expected = encoder->finish();
  REQUIRE(expected);
  const auto written = dtraced::util::read_file_limited((dir.path() / "out" / "seq.gif").string(), 1 << 20);
  REQUIRE(written);
  CHECK(*written == std::string(expected->begin(), expected->end()));
}

TEST_CASE("the image route takes a frame number, once, in decimal", "[collector][frames][routes]") {
  const auto route = coll::match_route(Verb::get, "/v1/jobs/7/image?format=pfm&frame=12");
  REQUIRE(route.ok());
  CHECK(route.value().image_frame == 12u);
  CHECK(route.value().image_format == image::ImageFormat::kPfm);
  CHECK_FALSE(coll::match_route(Verb::get, "/v1/jobs/7/image").value().image_frame);
  for (const char* bad : {"frame=", "frame=-1", "frame=012", "frame=1x", "frame=4294967296", "frame=1&frame=2"}) {
    INFO(bad);
    const auto refused = coll::match_route(Verb::get, fmt::format("/v1/jobs/7/image?{}", bad));
    REQUIRE_FALSE(refused.ok());
    CHECK(refused.error().status == Status::bad_request);
    CHECK(refused.error().error.path == "/frame");
  }
}
