// Tests for the display transform (image/display.h) against closed forms, its use by the 8-bit
// writers, the format table's new rows and aliases, and sequence patterns (image/sequence.h).
#include <cmath>
#include <limits>
#include <string>

#include <catch2/catch.hpp>

#include "image/display.h"
#include "image/image_io.h"
#include "image/sequence.h"

namespace {

using dtraced::image::display_value;
using dtraced::image::DisplayTransform;
using dtraced::image::ImageFormat;
using dtraced::image::ToneCurve;

constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();

DisplayTransform transform(double exposure, ToneCurve tone) {
  DisplayTransform d;
  d.exposure = exposure;
  d.tone = tone;
  return d;
}

std::string error_of(const dtraced::util::Status& status) { return status ? "" : status.error().to_string(); }

}  // namespace

TEST_CASE("The identity display transform is the clip every 8-bit output always did", "[image][display]") {
  const DisplayTransform identity;
  CHECK(display_value(identity, 0.25f) == 0.25f);
  CHECK(display_value(identity, 0.999f) == 0.999f);
  CHECK(display_value(identity, 1.0f) == 1.0f);
  CHECK(display_value(identity, 7.5f) == 1.0f);
  CHECK(display_value(identity, kInf) == 1.0f);
  CHECK(display_value(identity, -0.5f) == 0.0f);
  CHECK(display_value(identity, -kInf) == 0.0f);
  CHECK(display_value(identity, kNaN) == 0.0f);
}

TEST_CASE("Each stop of exposure doubles the value before the curve", "[image][display]") {
  for (double stops : {-3.0, -1.0, 0.5, 1.0, 2.0}) {
    for (float x : {0.01f, 0.1f, 0.2f, 0.7f}) {
      INFO("stops " << stops << " x " << x);
      const double exposed = x * std::exp2(stops);
      CHECK(display_value(transform(stops, ToneCurve::kClamp), x) == Approx(std::min(exposed, 1.0)).epsilon(1e-6));
      CHECK(display_value(transform(stops, ToneCurve::kReinhard), x) == Approx(exposed / (1 + exposed)).epsilon(1e-6));
    }
  }
  // One more stop is exactly twice the linear value (below the clip).
  CHECK(display_value(transform(1, ToneCurve::kClamp), 0.125f) == 0.25f);
  CHECK(display_value(transform(-2, ToneCurve::kClamp), 0.5f) == 0.125f);
}

TEST_CASE("Reinhard is x / (1 + x), reaching 1 only at infinity", "[image][display]") {
  const DisplayTransform reinhard = transform(0, ToneCurve::kReinhard);
  for (float x : {0.0f, 0.5f, 1.0f, 3.0f, 100.0f, 1e6f}) {
    INFO(x);
    CHECK(display_value(reinhard, x) == Approx(double(x) / (1.0 + x)).epsilon(1e-6));
  }
  CHECK(display_value(reinhard, 1.0f) == 0.5f);
  CHECK(display_value(reinhard, 1e6f) < 1.0f);
  CHECK(display_value(reinhard, kInf) == 1.0f);
  CHECK(display_value(reinhard, kNaN) == 0.0f);
  CHECK(display_value(reinhard, -2.0f) == 0.0f);
}

TEST_CASE("The filmic curve is monotone, within [0, 1], and follows Narkowicz's fit", "[image][display]") {
  const DisplayTransform filmic = transform(0, ToneCurve::kFilmic);
  float previous = display_value(filmic, 0.0f);
  CHECK(previous == 0.0f);
  for (int i = 1; i <= 200000; ++i) {
    const float x = float(i) * 1e-4f;  // up to 20, past the point (~7.2) where the fit reaches 1
    const float y = display_value(filmic, x);
    REQUIRE(y >= previous);
    REQUIRE(y <= 1.0f);
    previous = y;
  }
  CHECK(previous == 1.0f);
  CHECK(display_value(filmic, 1.0f) == Approx(2.54 / 3.16).epsilon(1e-6));
  CHECK(display_value(filmic, 0.18f) == Approx(0.18 * (2.51 * 0.18 + 0.03) / (0.18 * (2.43 * 0.18 + 0.59) + 0.14)));
  CHECK(display_value(filmic, kInf) == 1.0f);
  CHECK(display_value(filmic, kNaN) == 0.0f);
  CHECK(display_value(filmic, -1.0f) == 0.0f);
}

TEST_CASE("PNG, PPM and GIF writers apply the display transform and PFM ignores it", "[image][display]") {
  dtraced::image::ImageRGBf img(1, 1);
  img.rgb = {0.25f, 2.0f, kNaN};
  dtraced::image::WriteOptions plain, brighter;
  brighter.display = transform(1, ToneCurve::kClamp);
  const auto ppm = dtraced::image::encode_image(ImageFormat::kPpm, img, plain);
  const auto ppm_bright = dtraced::image::encode_image(ImageFormat::kPpm, img, brighter);
  REQUIRE(ppm);
  REQUIRE(ppm_bright);
  const auto code = [](const std::string& bytes, int c) {
    return int(static_cast<unsigned char>(bytes[bytes.size() - 3 + c]));
  };
  // sRGB codes of 0.25 and 0.5: round(255 * (1.055 x^(1/2.4) - 0.055)).
  CHECK(code(*ppm, 0) == 137);
  CHECK(code(*ppm_bright, 0) == 188);
  CHECK(code(*ppm_bright, 1) == 255);
  CHECK(code(*ppm_bright, 2) == 0);
  const auto png = dtraced::image::encode_image(ImageFormat::kPng, img, plain);
  const auto png_bright = dtraced::image::encode_image(ImageFormat::kPng, img, brighter);
  REQUIRE(png);
  REQUIRE(png_bright);
  CHECK(*png != *png_bright);
  const auto back = dtraced::image::decode_image(ImageFormat::kPng, *png_bright, "bright.png");
  REQUIRE(back);
  CHECK(back->rgb[0] == Approx(dtraced::image::srgb_to_linear(188 / 255.0f)));
  const auto pfm = dtraced::image::encode_image(ImageFormat::kPfm, img, plain);
  const auto pfm_bright = dtraced::image::encode_image(ImageFormat::kPfm, img, brighter);
  REQUIRE(pfm);
  REQUIRE(pfm_bright);
  CHECK(*pfm == *pfm_bright);
}

TEST_CASE("The format table knows EXR and GIF, and .pnm reads as PPM", "[image][formats]") {
  using dtraced::image::format_from_path;
  CHECK(format_from_path("a.pnm") == ImageFormat::kPpm);
  CHECK(format_from_path("dir/A.PNM") == ImageFormat::kPpm);
  CHECK(format_from_path("a.exr") == ImageFormat::kExr);
  CHECK(format_from_path("a.GIF") == ImageFormat::kGif);
  CHECK_FALSE(dtraced::image::format_from_name("pnm"));  // one name per format for ?format=
  CHECK(dtraced::image::format_from_name("exr") == ImageFormat::kExr);
  CHECK(dtraced::image::format_info(ImageFormat::kExr).content_type == "image/x-exr");
  CHECK(dtraced::image::format_info(ImageFormat::kGif).content_type == "image/gif");
}

TEST_CASE("Sequence patterns split a path around %d or %0Nd", "[image][sequence]") {
  using dtraced::image::frame_path;
  using dtraced::image::parse_sequence_pattern;
  auto snow = parse_sequence_pattern("out/snow-%04d.png");
  REQUIRE(snow);
  CHECK(snow->has_number);
  CHECK(snow->prefix == "out/snow-");
  CHECK(snow->suffix == ".png");
  CHECK(snow->width == 4);
  CHECK(frame_path(*snow, 7) == "out/snow-0007.png");
  CHECK(frame_path(*snow, 12345) == "out/snow-12345.png");

  auto plain = parse_sequence_pattern("%d.exr");
  REQUIRE(plain);
  CHECK(plain->width == 0);
  CHECK(frame_path(*plain, 0) == "0.exr");
  CHECK(frame_path(*plain, 42) == "42.exr");

  auto nine = parse_sequence_pattern("f%09d");
  REQUIRE(nine);
  CHECK(frame_path(*nine, 3) == "f000000003");

  auto none = parse_sequence_pattern("still.png");
  REQUIRE(none);
  CHECK_FALSE(none->has_number);
  CHECK(frame_path(*none, 5) == "still.png");
}

TEST_CASE("A doubled %% in a sequence pattern is a literal percent sign", "[image][sequence]") {
  using dtraced::image::frame_path;
  using dtraced::image::parse_sequence_pattern;
  auto p = parse_sequence_pattern("100%%/f-%03d%%.png");
  REQUIRE(p);
  CHECK(frame_path(*p, 5) == "100%/f-005%.png");
  auto literal = parse_sequence_pattern("a%%d.png");  // "%%" then "d": no frame number
  REQUIRE(literal);
  CHECK_FALSE(literal->has_number);
  CHECK(frame_path(*literal, 9) == "a%d.png");
}

TEST_CASE("Malformed sequence patterns are errors naming the path and the position", "[image][sequence]") {
  for (const char* bad : {"a%d-%02d.png", "a%5d.png", "a%x.png", "a%010d.png", "a%0d.png", "a%00d.png", "a%.png",
                          "out%", "a%04.png", "a%-4d.png"}) {
    INFO(bad);
    const auto p = dtraced::image::parse_sequence_pattern(bad);
    REQUIRE_FALSE(p);
    CHECK(p.error().file == bad);
    CHECK(p.error().message.find("position") != std::string::npos);
  }
  const auto two = dtraced::image::parse_sequence_pattern("a%d-%02d.png");
  REQUIRE_FALSE(two);
  CHECK(two.error().message.find("second frame number at position 5") != std::string::npos);
  CHECK_FALSE(dtraced::image::parse_sequence_pattern(""));
}

TEST_CASE("A sequence path that would write two frames to one file is refused, except a GIF", "[image][sequence]") {
  using dtraced::image::check_sequence_path;
  CHECK(error_of(check_sequence_path("out.png", 1)).empty());
  CHECK(error_of(check_sequence_path("out-%04d.png", 24)).empty());
  CHECK(error_of(check_sequence_path("out-%d.exr", 100000)).empty());
  CHECK(error_of(check_sequence_path("snow.gif", 48)).empty());
  CHECK(error_of(check_sequence_path("100%%.png", 1)).empty());

  const std::string one_file = error_of(check_sequence_path("out.png", 2));
  CHECK(one_file.find("out.png: 2 frames would all be written to this one file") == 0);
  CHECK(one_file.find("%04d") != std::string::npos);
  CHECK_FALSE(error_of(check_sequence_path("100%%.pnm", 3)).empty());

  const std::string unknown = error_of(check_sequence_path("out-%04d.jpg", 2));
  CHECK(unknown.find("out-%04d.jpg: unknown image format") == 0);
  const std::string bad = error_of(check_sequence_path("out-%4d.png", 2));
  CHECK(bad.find("out-%4d.png: ") == 0);
}
