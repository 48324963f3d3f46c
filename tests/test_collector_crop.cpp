// A cropped farm job through the collector's handler: only the tiles that overlap the crop are
// queued, leased, accepted and counted (for every frame of a range, with their indices in the
// full grid); the partial image, each frame's file and a sequence's GIF are the crop's pixels;
// a restart rebuilds the same queue.
#include <cstdint>
#include <set>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/jobs.h"
#include "collector_testing.h"
#include "image/gif_io.h"
#include "image/image_io.h"
#include "util/file.h"

namespace {

using namespace dtraced::testing;
namespace image = dtraced::image;
namespace scene = dtraced::scene;

// kScene is 32x24 in tiles of 8 (4 x 3 tiles). Columns [10, 22) and rows [4, 12) touch tile
// columns 1-2 and rows 0-1: tiles 1, 2, 5 and 6 of each frame.
constexpr std::string_view kCrop = R"(, "crop": {"x": 10, "y": 4, "width": 12, "height": 8})";
constexpr scene::TileRect kCropRect{10, 4, 12, 8};
const std::vector<std::uint32_t> kCropTiles = {1, 2, 5, 6};
// Frames 4, 6 and 8.
constexpr std::string_view kFrames = R"(, "frames": {"first": 4, "last": 8, "step": 2})";
constexpr std::uint32_t kFrameCount = 3;

// The tile indices of the crop over `frames` frames: frame k's are k x kTiles + kCropTiles.
std::vector<std::uint32_t> crop_indices(std::uint32_t frames) {
  std::vector<std::uint32_t> out;
  for (std::uint32_t k = 0; k < frames; ++k) {
    for (const std::uint32_t t : kCropTiles) out.push_back(k * kTiles + t);
  }
  return out;
}

// The crop of the image that frame `frame_index` of `job` shows once `tiles` (in-frame indices)
// are stored.
image::ImageRGBf expected_crop(std::uint64_t job, std::uint32_t frame_index, const std::set<std::uint32_t>& tiles) {
  image::ImageRGBf full(32, 24);
  const auto rects = scene::TileGrid(32, 24, 8).all();
  for (const std::uint32_t t : tiles) {
    coll::copy_tile(full, rects[t], fake_pixels(job, frame_index * kTiles + t, rects[t]));
  }
  // Cut by hand from the whole frame: an oracle apart from the reader's windowed copy.
  image::ImageRGBf cut(kCropRect.width, kCropRect.height);
  for (std::uint32_t y = 0; y < cut.height; ++y) {
    for (std::uint32_t x = 0; x < cut.width; ++x) {
      for (int c = 0; c < 3; ++c) cut.pixel(x, y)[c] = full.pixel(kCropRect.x0 + x, kCropRect.y0 + y)[c];
    }
  }
  return cut;
}

std::set<std::uint32_t> crop_tiles() { return {kCropTiles.begin(), kCropTiles.end()}; }

image::ImageRGBf read_image_file(const fs::path& path) {
  auto img = image::read_image(path.string());
  if (!img) INFO(img.error().to_string());
  REQUIRE(img);
  return *img;
}

std::vector<std::uint32_t> tiles_of(const std::vector<protocol::Lease>& leases) {
  std::vector<std::uint32_t> out;
  for (const auto& l : leases) out.push_back(l.tile);
  return out;
}

}  // namespace

TEST_CASE("the queue never leases nor counts a skipped tile", "[collector][crop]") {
  coll::WorkQueue q;
  const coll::TimePoint t0{};
  const std::vector<coll::TileIndex> stored = {1};
  const std::vector<coll::TileIndex> skipped = {0, 3};
  REQUIRE(q.add_job(1, 0, 5, stored, skipped));
  CHECK(q.progress(1, t0)->tiles_total == 3);
  CHECK(q.progress(1, t0)->tiles_done == 1);
  CHECK(q.tile_status(1, 0) == coll::TileStatus::kNoSuchTile);
  CHECK(q.complete(1, 3, t0) == coll::CompleteResult::kJobGone);
  std::vector<coll::TileIndex> order;
  while (const auto grant = q.lease(t0).grant) order.push_back(grant->tile);
  CHECK(order == std::vector<coll::TileIndex>{2, 4});
  CHECK(q.complete(1, 2, t0) == coll::CompleteResult::kStored);
  CHECK(q.complete(1, 4, t0) == coll::CompleteResult::kStored);
  CHECK(q.is_done(1));
  // A tile both stored and skipped, and a job with every tile skipped, are refused.
  CHECK_FALSE(q.add_job(2, 0, 2, std::vector<coll::TileIndex>{0}, std::vector<coll::TileIndex>{0}));
  CHECK_FALSE(q.add_job(3, 0, 2, {}, std::vector<coll::TileIndex>{0, 1}));
}

TEST_CASE("a cropped job leases, counts and writes only the crop's tiles", "[collector][crop]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit(std::string(kCrop) + R"(, "output": "crop.pfm")");
  protocol::JobStatus s = h.status(job);
  CHECK(s.tiles_total == kCropTiles.size());
  CHECK(s.tiles_done == 0);

  const std::vector<protocol::Lease> leases = h.lease_all();
  CHECK(tiles_of(leases) == kCropTiles);
  const auto rects = scene::TileGrid(32, 24, 8).all();
  for (const auto& l : leases) CHECK(l.rect == rects[l.tile]);

  // A tile outside the crop is refused, and not stored.
  const Response outside = h.put(job, 0, payload(job, 0, rects[0]));
  CHECK(outside.result() == Status::bad_request);
  CHECK(error_of(outside).field == "/tile");

  h.put_ok(leases[0]);
  s = h.status(job);
  CHECK(s.tiles_done == 1);
  // The partial image is the crop's size.
  const image::ImageRGBf partial = fetch_pfm(h, job);
  CHECK(partial.width == kCropRect.width);
  CHECK(partial.height == kCropRect.height);
  CHECK(partial.rgb == expected_crop(job, 0, {kCropTiles[0]}).rgb);

  for (std::size_t i = 1; i < leases.size(); ++i) h.put_ok(leases[i]);
  s = h.status(job);
  CHECK(s.state == protocol::JobState::kDone);
  CHECK(s.tiles_done == kCropTiles.size());
  const image::ImageRGBf written = read_image_file(dir.path() / "out" / "crop.pfm");
  CHECK(written.width == kCropRect.width);
  CHECK(written.height == kCropRect.height);
  CHECK(written.rgb == expected_crop(job, 0, crop_tiles()).rgb);
  CHECK(fetch_pfm(h, job).rgb == written.rgb);  // from the store once done
  CHECK(stored_state(h.config).tiles.at(static_cast<std::int64_t>(job)) == kCropTiles);
}

TEST_CASE("a cropped frame range: each frame is the crop, a restart rebuilds the same queue", "[collector][crop]") {
  TempDir dir;
  std::uint64_t job = 0;
  const std::vector<std::uint32_t> all = crop_indices(kFrameCount);
  {
    Harness h(dir);
    job = h.submit(std::string(kCrop) + std::string(kFrames) + R"(, "output": "crop-%04d.pfm")");
    const protocol::JobStatus s = h.status(job);
    CHECK(s.tiles_total == all.size());
    REQUIRE(s.frames);
    CHECK(*s.frames == protocol::FrameProgress{kFrameCount, 0, 4, 0, 4});
    const std::vector<protocol::Lease> leases = h.lease_all();
    REQUIRE(tiles_of(leases) == all);
    // Frame 4 complete, one tile of frame 6.
    for (std::size_t i = 0; i < 5; ++i) h.put_ok(leases[i]);
    CHECK(h.status(job).frames->frames_done == 1);
    CHECK(*h.status(job).frames == protocol::FrameProgress{kFrameCount, 1, 6, 1, 4});
  }
  Harness again(dir);
  protocol::JobStatus s = again.status(job);
  CHECK(s.tiles_done == 5);
  CHECK(s.tiles_total == all.size());
  const std::vector<protocol::Lease> left = again.lease_all();
  CHECK(tiles_of(left) == std::vector<std::uint32_t>(all.begin() + 5, all.end()));
  for (const auto& l : left) again.put_ok(l);
  s = again.status(job);
  CHECK(s.state == protocol::JobState::kDone);
  for (std::uint32_t k = 0; k < kFrameCount; ++k) {
    INFO(k);
    const image::ImageRGBf frame = read_image_file(dir.path() / "out" / fmt::format("crop-{:04d}.pfm", 4 + 2 * k));
    CHECK(frame.width == kCropRect.width);
    CHECK(frame.rgb == expected_crop(job, k, crop_tiles()).rgb);
  }
}

TEST_CASE("a cropped sequence's GIF holds the crop of every frame", "[collector][crop][gif]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job =
      h.submit(std::string(kCrop) + std::string(kFrames) + R"(, "output": "crop.gif", "fps": 10)");
  for (const auto& l : h.lease_all()) h.put_ok(l);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  image::GifOptions options;
  options.fps = 10;
  auto encoder = image::GifEncoder::create(kCropRect.width, kCropRect.height, options);
  REQUIRE(encoder);
  for (std::uint32_t k = 0; k < kFrameCount; ++k) require_ok(encoder->add_frame(expected_crop(job, k, crop_tiles())));
  auto expected = encoder->finish();
  REQUIRE(expected);
  const auto written = dtraced::util::read_file_limited((dir.path() / "out" / "crop.gif").string(), 1 << 20);
  REQUIRE(written);
  CHECK(*written == std::string(expected->begin(), expected->end()));
}

TEST_CASE("a crop outside the image is refused at its member", "[collector][crop]") {
  TempDir dir;
  Harness h(dir);
  const Response res = h.call(Verb::post, "/v1/jobs",
                              submit_body(R"(, "width": 16, "crop": {"x": 10, "y": 4, "width": 12, "height": 8})"));
  CHECK(res.result() == Status::bad_request);
  const protocol::ErrorBody e = error_of(res);
  CHECK(e.field == "/crop/width");
  CHECK(e.error == "crop columns [10, 22) extend past the image width 16");
}

TEST_CASE("a one-shot job keeps its key without a crop and gets another with one", "[collector][crop]") {
  protocol::JobSettings settings;
  const std::string whole = coll::one_shot_client_key(std::string(64, 'a'), settings, 8, "x.png");
  settings.crop = kCropRect;
  CHECK(coll::one_shot_client_key(std::string(64, 'a'), settings, 8, "x.png") != whole);
}
