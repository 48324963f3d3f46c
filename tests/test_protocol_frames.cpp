// Tests for the frame ranges of farm jobs in dtraced::protocol: a submission carries its range,
// frame rate and display settings; stored settings and leases keep them; a sequence's status
// carries its frame progress and an older collector's status (without it) still reads.
#include <cstdint>
#include <string>
#include <string_view>

#include <catch2/catch.hpp>

#include "protocol/messages.h"
#include "scene/load.h"

namespace {

namespace protocol = dtraced::protocol;
namespace scene = dtraced::scene;

constexpr std::string_view kScene = R"({
  "camera": {"position": [0, 0, 5], "look_at": [0, 0, 0]},
  "render": {"width": 64, "height": 48, "samples": 2, "frame": 3},
  "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1}],
  "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 3}]
})";

std::string body(std::string_view extra) {
  std::string b = "{\"scene\": " + std::string(kScene);
  if (!extra.empty()) b += ", " + std::string(extra);
  return b + "}";
}

protocol::JobSubmit submit_of(std::string_view extra) {
  auto d = protocol::decode_job_submit(body(extra));
  if (!d.ok()) INFO(dtraced::util::to_string(d.error()));
  REQUIRE(d.ok());
  return std::move(d).value();
}

std::string first_error(std::string_view extra) {
  auto d = protocol::decode_job_submit(body(extra));
  REQUIRE_FALSE(d.ok());
  return d.error().front().path + ": " + d.error().front().message;
}

}  // namespace

TEST_CASE("a submission's frame range, fps, exposure and tone round trip", "[protocol][frames]") {
  protocol::JobSubmit m = submit_of("");
  m.overrides.frames = scene::FrameRange{2, 11, 3};
  m.overrides.fps = 12.5;
  m.overrides.exposure = -1.25;
  m.overrides.tone = dtraced::image::ToneCurve::kFilmic;
  const std::string text = protocol::encode(m);
  INFO(text);
  CHECK(text.find("\"frames\":{\"first\":2,\"last\":11,\"step\":3}") != std::string::npos);
  const auto back = protocol::decode_job_submit(text);
  REQUIRE(back.ok());
  CHECK(back.value() == m);
  const scene::RenderSettings s = protocol::effective_settings(back.value());
  REQUIRE(s.frames);
  CHECK(protocol::frame_count(s) == 4);
  CHECK(protocol::frame_number(s, 3) == 11);
  CHECK(s.fps == 12.5);
  CHECK(s.display.exposure == -1.25);
  CHECK(s.display.tone == dtraced::image::ToneCurve::kFilmic);
}

TEST_CASE("the effective range is the override, else the scene's, else the single frame", "[protocol][frames]") {
  const scene::RenderSettings single = protocol::effective_settings(submit_of(""));
  CHECK_FALSE(single.frames);
  CHECK(protocol::frame_count(single) == 1);
  CHECK(protocol::frame_number(single, 0) == 3);

  protocol::JobSubmit m = submit_of(R"("frames": {"first": 1, "last": 4})");
  CHECK(protocol::frame_count(protocol::effective_settings(m)) == 4);
  // The scene's own range, unless the submission names one frame or another range.
  m.scene.render.frames = scene::FrameRange{10, 19, 1};
  m.overrides.frames.reset();
  CHECK(protocol::frame_count(protocol::effective_settings(m)) == 10);
  m.overrides.frame = 7;
  const scene::RenderSettings one = protocol::effective_settings(m);
  CHECK_FALSE(one.frames);
  CHECK(one.frame == 7);
  // A range of one frame is stored as that frame, so the settings text is a single frame's.
  m.overrides.frame.reset();
  m.overrides.frames = scene::FrameRange{5, 5, 1};
  const scene::RenderSettings five = protocol::effective_settings(m);
  CHECK_FALSE(five.frames);
  CHECK(five.frame == 5);
}

TEST_CASE("a bad frame range is refused at its key", "[protocol][frames]") {
  CHECK(first_error(R"("frames": {"first": 4, "last": 2})") == "/frames/last: must be >= first (4) (got 2)");
  CHECK(first_error(R"("frames": {"first": 0, "last": 2, "step": 0})").starts_with("/frames/step:"));
  CHECK(first_error(R"("frames": {"first": 0, "last": 2, "stpe": 1})").starts_with("/frames/stpe:"));
  CHECK(first_error(R"("frames": [0, 2])").starts_with("/frames:"));
  CHECK(first_error(R"("frames": {"first": 0, "last": 100000})").starts_with("/frames: 100001 frames"));
  CHECK(first_error(R"("fps": 0)").starts_with("/fps:"));
  CHECK(first_error(R"("tone": "filmc")").starts_with("/tone:"));
  CHECK(first_error(R"("exposure": 33)").starts_with("/exposure:"));
}

TEST_CASE("the tile limit counts every frame of a job", "[protocol][frames]") {
  // 64x48 in tiles of 1 is 3072 tiles a frame: 85 frames fit under 2^18 tiles, 86 do not.
  CHECK(protocol::decode_job_submit(body(R"("tile_size": 1, "frames": {"first": 0, "last": 84})")).ok());
  CHECK(first_error(R"("tile_size": 1, "frames": {"first": 0, "last": 85})") ==
        "/tile_size: a 64x48 image in tiles of 1 is 3072 tiles x 86 frames, more than the limit of 262144");
  // Without a tile size the range is what to change.
  CHECK(first_error(R"("width": 16384, "height": 16384, "frames": {"first": 0, "last": 1})")
            .starts_with("/frames: a 16384x16384 image"));
}

TEST_CASE("stored settings keep a sequence's range and a single frame keeps its text", "[protocol][frames]") {
  protocol::JobSettings single;
  const std::string single_text = protocol::encode_settings(single);
  CHECK(single_text.find("frames") == std::string::npos);
  CHECK(single_text.find("fps") == std::string::npos);

  protocol::JobSettings seq;
  seq.render.frames = scene::FrameRange{0, 47, 2};
  seq.render.fps = 30;
  seq.render.display.tone = dtraced::image::ToneCurve::kReinhard;
  seq.render.display.exposure = 0.5;
  const auto back = protocol::decode_settings(protocol::encode_settings(seq));
  REQUIRE(back.ok());
  CHECK(back.value() == seq);
}

TEST_CASE("a lease carries its frame's fps and display settings", "[protocol][frames]") {
  protocol::Lease lease;
  lease.job = 3;
  lease.digest = std::string(64, 'b');
  lease.tile = 17;
  lease.rect = {0, 0, 8, 8};
  lease.settings.width = 8;
  lease.settings.height = 8;
  lease.settings.frame = 6;
  lease.settings.fps = 25;
  lease.settings.display.tone = dtraced::image::ToneCurve::kFilmic;
  const auto back = protocol::decode_lease_reply(protocol::encode(protocol::LeaseReply{lease}));
  REQUIRE(back.ok());
  CHECK(std::get<protocol::Lease>(back.value()) == lease);
}

TEST_CASE("a sequence's status carries its frame progress, and a status without it reads", "[protocol][frames]") {
  protocol::JobStatus s;
  s.id = 9;
  s.output = "snow-%04d.png";
  s.width = s.height = s.samples = 1;
  s.tiles_total = 40;
  s.tiles_done = 25;
  s.digest = std::string(64, 'c');
  const std::string plain = protocol::encode(s);
  CHECK(plain.find("frames_total") == std::string::npos);
  auto read = protocol::decode_job_status(plain);
  REQUIRE(read.ok());
  CHECK_FALSE(read.value().frames);

  s.frames = protocol::FrameProgress{4, 2, 12, 5, 10};
  read = protocol::decode_job_status(protocol::encode(s));
  REQUIRE(read.ok());
  CHECK(read.value() == s);

  std::string bad = protocol::encode(s);
  bad.replace(bad.find("\"frames_done\":2"), 15, "\"frames_done\":5");
  const auto refused = protocol::decode_job_status(bad);
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error().front().path == "/frames_done");
}
