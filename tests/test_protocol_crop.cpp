// Tests for the crop of farm jobs in dtraced::protocol: a submission carries it and has it checked
// against the image its overrides make; stored settings keep it, a job without one keeps the
// settings text it always had, and a bad crop is refused with its member named.
#include <string>
#include <string_view>

#include <catch2/catch.hpp>

#include "decode_testing.h"
#include "protocol/messages.h"

namespace {

namespace protocol = dtraced::protocol;
namespace scene = dtraced::scene;

constexpr std::string_view kScene = R"({
  "camera": {"position": [0, 0, 5], "look_at": [0, 0, 0]},
  "render": {"width": 64, "height": 48, "samples": 2},
  "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1}],
  "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 3}]
})";

std::string submit_body(std::string_view extra) { return dtraced::testing::submit_body(kScene, extra); }

using dtraced::testing::first_error;

// Stored settings of a 64x48 image with `extra` keys.
std::string settings_text(std::string_view extra) {
  return R"({"width":64,"height":48,"samples":2,"max_depth":8,"background":[0,0,0],"seed":0,"frame":0)" +
         std::string(extra) + "}";
}

}  // namespace

TEST_CASE("a submission's crop round trips and is checked against the overridden image", "[protocol][crop]") {
  auto d = protocol::decode_job_submit(submit_body(R"("crop": {"x": 8, "y": 4, "width": 40, "height": 20})"));
  REQUIRE(d.ok());
  REQUIRE(d.value().overrides.crop);
  CHECK(*d.value().overrides.crop == scene::TileRect{8, 4, 40, 20});
  const std::string text = protocol::encode(d.value());
  INFO(text);
  CHECK(text.find(R"("crop":{"x":8,"y":4,"width":40,"height":20})") != std::string::npos);
  const auto back = protocol::decode_job_submit(text);
  REQUIRE(back.ok());
  CHECK(back.value() == d.value());

  // The whole image is a crop too; one pixel past it is not, at the width the overrides make.
  CHECK(protocol::decode_job_submit(submit_body(R"("crop": {"x": 0, "y": 0, "width": 64, "height": 48})")).ok());
  CHECK(
      first_error(protocol::decode_job_submit(submit_body(R"("crop": {"x": 1, "y": 0, "width": 64, "height": 48})"))) ==
      "/crop/width: crop columns [1, 65) extend past the image width 64");
  CHECK(first_error(protocol::decode_job_submit(
            submit_body(R"("width": 32, "crop": {"x": 8, "y": 4, "width": 40, "height": 20})"))) ==
        "/crop/width: crop columns [8, 48) extend past the image width 32");
  CHECK(protocol::decode_job_submit(
            submit_body(R"("width": 128, "height": 96, "crop": {"x": 70, "y": 50, "width": 40, "height": 40})"))
            .ok());
  CHECK(
      first_error(protocol::decode_job_submit(submit_body(R"("crop": {"x": 0, "y": 40, "width": 8, "height": 9})"))) ==
      "/crop/height: crop rows [40, 49) extend past the image height 48");
  // Empty, a missing or unknown member, not an object.
  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("crop": {"x": 0, "y": 0, "width": 0, "height": 9})")))
            .starts_with("/crop/width:"));
  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("crop": {"x": 0, "y": 0, "width": 4})")))
            .starts_with("/crop/height:"));
  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("crop": {"x": 0, "y": 0, "widht": 4, "height": 4})")))
            .starts_with("/crop"));
  CHECK(first_error(protocol::decode_job_submit(submit_body(R"("crop": [0, 0, 4, 4])"))).starts_with("/crop:"));
}

TEST_CASE("stored settings keep a crop, and a job without one keeps its text", "[protocol][crop]") {
  protocol::JobSettings whole;
  whole.render.width = 64;
  whole.render.height = 48;
  whole.render.samples = 2;
  const std::string whole_text = protocol::encode_settings(whole);
  // The exact text a job stored before crops existed has (its one-shot key hashes it).
  CHECK(whole_text == settings_text(""));
  const auto whole_back = protocol::decode_settings(whole_text);
  REQUIRE(whole_back.ok());
  CHECK_FALSE(whole_back.value().crop);
  CHECK(whole_back.value() == whole);

  protocol::JobSettings cropped = whole;
  cropped.crop = scene::TileRect{8, 4, 40, 20};
  const std::string cropped_text = protocol::encode_settings(cropped);
  CHECK(cropped_text == settings_text(R"(,"crop":{"x":8,"y":4,"width":40,"height":20})"));
  const auto back = protocol::decode_settings(cropped_text);
  REQUIRE(back.ok());
  CHECK(back.value() == cropped);

  CHECK(first_error(protocol::decode_settings(settings_text(R"(,"crop":{"x":60,"y":4,"width":8,"height":20})"))) ==
        "/crop/width: crop columns [60, 68) extend past the image width 64");
  CHECK(first_error(protocol::decode_settings(settings_text(R"(,"crop":{"x":0,"y":0,"width":8,"height":0})")))
            .starts_with("/crop/height:"));
  CHECK(first_error(protocol::decode_settings(settings_text(R"(,"crop":{"x":0,"y":0,"width":8})")))
            .starts_with("/crop/height:"));
}
