// Tests for dtraced::image: file round trips (PFM bit-exact, PPM/PNG within half a code of the
// sRGB quantisation), readers on hand-made inputs (other colour types, byte orders, maxvals),
// every class of malformed file, the sRGB curves and the metrics on inputs with known answers.
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <limits>
#include <random>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "image/codec.h"
#include "image/image.h"
#include "image/image_io.h"
#include "image/metrics.h"
#include "util/file.h"

namespace {

namespace fs = std::filesystem;
using dtraced::image::ImageFormat;
using dtraced::image::ImageRGBf;
using dtraced::image::WriteOptions;

// A fresh directory under the system temp dir, removed with everything in it at scope exit.
class TempDir {
 public:
  TempDir() {
    std::random_device rd;
    for (;;) {
      const std::uint64_t r = (std::uint64_t{rd()} << 32) ^ rd();
      path_ = fs::temp_directory_path() / ("dtraced_test_image_" + std::to_string(r));
      if (fs::create_directory(path_)) break;  // false: name taken, try another
    }
  }
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  std::string file(const std::string& name) const { return (path_ / name).string(); }
  const fs::path& path() const { return path_; }

 private:
  fs::path path_;
};

void write_bytes(const std::string& path, std::string_view bytes) {
  REQUIRE(dtraced::util::write_file_atomic(path, bytes));
}

std::string read_bytes(const std::string& path) {
  auto bytes = dtraced::util::read_file_limited(path, 1 << 26);
  REQUIRE(bytes);
  return *bytes;
}

// The image API returns util::Result; the checks below read the value, or the error's text.
template <typename T>
std::optional<T> get(dtraced::util::Result<T> result, std::string& error) {
  if (result) return std::move(result).value();
  error = result.error().to_string();
  return std::nullopt;
}
bool get(const dtraced::util::Status& status, std::string& error) {
  if (!status) error = status.error().to_string();
  return status.ok();
}

template <std::size_t N>
std::string_view as_bytes(const unsigned char (&data)[N]) {
  return {reinterpret_cast<const char*>(data), N};
}

// Deterministic values in [lo, hi).
ImageRGBf random_image(std::uint32_t w, std::uint32_t h, float lo, float hi, std::uint32_t seed) {
  ImageRGBf img(w, h);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  for (float& v : img.rgb) v = dist(rng);
  return img;
}

std::string le_float(float v) {
  std::uint32_t bits = std::bit_cast<std::uint32_t>(v);
  std::string out(4, '\0');
  for (int i = 0; i < 4; ++i) out[i] = static_cast<char>((bits >> (8 * i)) & 0xff);
  return out;
}

std::string be_float(float v) {
  std::string le = le_float(v);
  return std::string(le.rbegin(), le.rend());
}

// Largest difference between two images after the sRGB curve, in units of `max_code` codes.
double max_code_error(const ImageRGBf& a, const ImageRGBf& b, double max_code) {
  double worst = 0.0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) {
    const double ea = dtraced::image::linear_to_srgb(std::clamp(a.rgb[i], 0.0f, 1.0f));
    const double eb = dtraced::image::linear_to_srgb(std::clamp(b.rgb[i], 0.0f, 1.0f));
    worst = std::max(worst, std::abs(ea - eb) * max_code);
  }
  return worst;
}

bool contains(const std::string& haystack, std::string_view needle) {
  return haystack.find(needle) != std::string::npos;
}

// Small PNGs assembled by hand (chunks, zlib stream and CRCs per the PNG spec) to reach reader
// paths our own writer never produces: 8-bit grey 3x2 {0,128,255 / 10,20,30} with an sRGB chunk;
// 2x1 palette {red, blue} with tRNS; 16-bit RGBA 1x1 (0x8000, 0xffff, 0, alpha 0x1234) tagged
// gAMA 1.0; and an IHDR claiming 100000x100000.
const unsigned char kGrey8Png[] = {
    0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44, 0x52, 0x00, 0x00,
    0x00, 0x03, 0x00, 0x00, 0x00, 0x02, 0x08, 0x00, 0x00, 0x00, 0x00, 0xb8, 0x1f, 0x39, 0xc6, 0x00, 0x00, 0x00,
    0x01, 0x73, 0x52, 0x47, 0x42, 0x00, 0xae, 0xce, 0x1c, 0xe9, 0x00, 0x00, 0x00, 0x10, 0x49, 0x44, 0x41, 0x54,
    0x78, 0x9c, 0x63, 0x60, 0x68, 0xf8, 0xcf, 0xc0, 0x25, 0x22, 0x07, 0x00, 0x08, 0x67, 0x01, 0xbc, 0x9c, 0x67,
    0x35, 0xa0, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82};

const unsigned char kPalettePng[] = {
    0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44, 0x52, 0x00,
    0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0x01, 0x08, 0x03, 0x00, 0x00, 0x00, 0xc3, 0xfc, 0x8f, 0xb8, 0x00,
    0x00, 0x00, 0x06, 0x50, 0x4c, 0x54, 0x45, 0xff, 0x00, 0x00, 0x00, 0x00, 0xff, 0x6c, 0xa1, 0xfd, 0x8e,
    0x00, 0x00, 0x00, 0x02, 0x74, 0x52, 0x4e, 0x53, 0x00, 0x80, 0x9b, 0x2b, 0x4e, 0x18, 0x00, 0x00, 0x00,
    0x0b, 0x49, 0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x60, 0x60, 0x04, 0x00, 0x00, 0x04, 0x00, 0x02, 0xbf,
    0x7a, 0x3f, 0x4a, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82};

const unsigned char kRgba16LinearPng[] = {
    0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d, 0x49, 0x48, 0x44, 0x52, 0x00, 0x00,
    0x00, 0x01, 0x00, 0x00, 0x00, 0x01, 0x10, 0x06, 0x00, 0x00, 0x00, 0x4f, 0x85, 0x18, 0xca, 0x00, 0x00, 0x00,
    0x04, 0x67, 0x41, 0x4d, 0x41, 0x00, 0x01, 0x86, 0xa0, 0x31, 0xe8, 0x96, 0x5f, 0x00, 0x00, 0x00, 0x11, 0x49,
    0x44, 0x41, 0x54, 0x78, 0x9c, 0x63, 0x68, 0x60, 0xf8, 0xff, 0x9f, 0x81, 0x41, 0xc8, 0x04, 0x00, 0x0f, 0x56,
    0x02, 0xc5, 0x7d, 0xd6, 0xb0, 0x0f, 0x00, 0x00, 0x00, 0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82};

const unsigned char kHugeHeaderPng[] = {0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0x00, 0x00, 0x00, 0x0d,
                                        0x49, 0x48, 0x44, 0x52, 0x00, 0x01, 0x86, 0xa0, 0x00, 0x01, 0x86, 0xa0,
                                        0x08, 0x02, 0x00, 0x00, 0x00, 0x27, 0x30, 0x9c, 0x9f, 0x00, 0x00, 0x00,
                                        0x00, 0x49, 0x45, 0x4e, 0x44, 0xae, 0x42, 0x60, 0x82};

}  // namespace

TEST_CASE("ImageRGBf stores interleaved rows from the top", "[image]") {
  ImageRGBf img(4, 3);
  CHECK(img.rgb.size() == 36);
  CHECK(img.is_consistent());
  img.pixel(1, 2)[2] = 5.0f;
  CHECK(img.rgb[(2 * 4 + 1) * 3 + 2] == 5.0f);
  const ImageRGBf& c = img;
  CHECK(c.pixel(1, 2)[2] == 5.0f);
  img.rgb.pop_back();
  CHECK_FALSE(img.is_consistent());
}

TEST_CASE("sRGB curves: known values and round trip", "[image]") {
  using dtraced::image::linear_to_srgb;
  using dtraced::image::srgb_to_linear;
  CHECK(linear_to_srgb(0.5f) == Approx(0.7353569830524495).epsilon(1e-6));
  CHECK(srgb_to_linear(0.5f) == Approx(0.21404114048223255).epsilon(1e-6));
  CHECK(linear_to_srgb(0.0f) == 0.0f);
  CHECK(linear_to_srgb(1.0f) == Approx(1.0).epsilon(1e-6));
  CHECK(srgb_to_linear(1.0f) == Approx(1.0).epsilon(1e-6));
  // Both sides of the knee: the linear segment and the power segment meet there.
  CHECK(linear_to_srgb(0.0031308f) == Approx(0.04045).epsilon(1e-4));
  CHECK(linear_to_srgb(0.001f) == Approx(0.01292).epsilon(1e-6));
  CHECK(srgb_to_linear(0.02f) == Approx(0.02 / 12.92).epsilon(1e-6));
  CHECK(std::isnan(linear_to_srgb(std::numeric_limits<float>::quiet_NaN())));
  for (int i = 0; i <= 1000; ++i) {
    const float v = static_cast<float>(i) / 1000.0f;
    CHECK(srgb_to_linear(linear_to_srgb(v)) == Approx(v).epsilon(1e-5).margin(1e-7));
  }
}

TEST_CASE("Quantisation rounds halves away from zero, as std::round does", "[image]") {
  using dtraced::image::detail::round_half_away;
  // The largest double below one half, halves, and the doubles either side of them.
  const double cases[] = {0.0,
                          0.49999999999999994,
                          0.5,
                          0.5000000000000001,
                          1.4999999999999998,
                          1.5,
                          2.5,
                          std::nextafter(2.5, 0.0),
                          254.5,
                          std::nextafter(254.5, 0.0),
                          65534.5,
                          std::nextafter(65534.5, 1e9),
                          65535.0,
                          1e-300,
                          4503599627370495.5};
  for (const double x : cases) {
    INFO("x " << fmt::format("{:.17g}", x));
    CHECK(round_half_away(x) == std::round(x));
  }
  // Every 8- and 16-bit code the writers store: quantize against the same sRGB value rounded by
  // std::round, over a sweep of displayed values that crosses every 8-bit code several times.
  std::size_t differ = 0;
  for (int i = 1; i < 1 << 16; ++i) {
    const float v = static_cast<float>(i) / 65536.0f;
    for (const std::uint32_t max : {255u, 65535u}) {
      const double want = std::round(dtraced::image::detail::srgb_encode(v) * max);
      if (dtraced::image::detail::quantize(v, max) != static_cast<std::uint32_t>(want)) ++differ;
    }
  }
  CHECK(differ == 0);
}

TEST_CASE("format_from_path reads the extension, any case", "[image]") {
  using dtraced::image::format_from_path;
  CHECK(format_from_path("out.png") == ImageFormat::kPng);
  CHECK(format_from_path("/tmp/x.d/OUT.PNG") == ImageFormat::kPng);
  CHECK(format_from_path("a.ppm") == ImageFormat::kPpm);
  CHECK(format_from_path("a.PpM") == ImageFormat::kPpm);
  CHECK(format_from_path("frame.0001.pfm") == ImageFormat::kPfm);
  CHECK(format_from_path("a.Pfm") == ImageFormat::kPfm);
  CHECK_FALSE(format_from_path("a.jpg"));
  CHECK_FALSE(format_from_path("noextension"));
  CHECK_FALSE(format_from_path("dir.png/file"));
  CHECK_FALSE(format_from_path(""));
}

TEST_CASE("PFM round trip is bit-exact, including odd sizes and special values", "[image][pfm]") {
  TempDir dir;
  for (auto [w, h] : {std::pair{7u, 3u}, std::pair{1u, 1u}, std::pair{3u, 7u}, std::pair{64u, 33u}}) {
    ImageRGBf img = random_image(w, h, -10.0f, 1000.0f, w * 100 + h);
    img.rgb[0] = -0.0f;
    img.rgb[1] = std::numeric_limits<float>::denorm_min();
    img.rgb[2] = std::numeric_limits<float>::infinity();
    if (img.rgb.size() > 3) img.rgb[3] = std::numeric_limits<float>::quiet_NaN();
    const std::string path = dir.file("rt.pfm");
    std::string error;
    REQUIRE(get(dtraced::image::write_image(path, img, {}), error));
    const auto back = get(dtraced::image::read_image(path), error);
    REQUIRE(back);
    CHECK(back->width == w);
    CHECK(back->height == h);
    REQUIRE(back->rgb.size() == img.rgb.size());
    CHECK(std::memcmp(back->rgb.data(), img.rgb.data(), img.rgb.size() * sizeof(float)) == 0);
  }
}

TEST_CASE("PFM files are little-endian with rows bottom to top", "[image][pfm]") {
  TempDir dir;
  ImageRGBf img(1, 2);
  img.pixel(0, 0)[0] = 1.0f;  // top
  img.pixel(0, 1)[0] = 2.0f;  // bottom
  const std::string path = dir.file("order.pfm");
  std::string error;
  REQUIRE(get(dtraced::image::write_image(path, img, {}), error));
  const std::string bytes = read_bytes(path);
  const std::string header = "PF\n1 2\n-1.0\n";
  REQUIRE(bytes.size() == header.size() + 24);
  CHECK(bytes.substr(0, header.size()) == header);
  CHECK(bytes.substr(header.size(), 4) == le_float(2.0f));  // first stored row is the bottom one
  CHECK(bytes.substr(header.size() + 12, 4) == le_float(1.0f));
}

TEST_CASE("PFM reader: big-endian, greyscale, scale", "[image][pfm]") {
  std::string error;
  SECTION("big-endian colour") {
    std::string bytes = "PF\n2 1\n1.0\n";
    for (float v : {1.5f, -2.0f, 3.0f, 4.0f, 5.0f, 6.25f}) bytes += be_float(v);
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPfm, bytes, "be.pfm"), error);
    REQUIRE(img);
    CHECK(img->rgb == std::vector<float>{1.5f, -2.0f, 3.0f, 4.0f, 5.0f, 6.25f});
  }
  SECTION("greyscale is replicated, bottom row first") {
    std::string bytes = "Pf\n1 2\n-1\n" + le_float(0.25f) + le_float(0.75f);
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPfm, bytes, "grey.pfm"), error);
    REQUIRE(img);
    CHECK(img->rgb == std::vector<float>{0.75f, 0.75f, 0.75f, 0.25f, 0.25f, 0.25f});
  }
  SECTION("a scale magnitude other than 1 multiplies") {
    std::string bytes = "PF 1 1 -2.5e0\n" + le_float(1.0f) + le_float(2.0f) + le_float(4.0f);
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPfm, bytes, "scaled.pfm"), error);
    REQUIRE(img);
    CHECK(img->rgb == std::vector<float>{2.5f, 5.0f, 10.0f});
  }
}

TEST_CASE("PPM round trip within half an 8-bit code", "[image][ppm]") {
  TempDir dir;
  const ImageRGBf img = random_image(13, 5, 0.0f, 1.0f, 7);
  const std::string path = dir.file("rt.ppm");
  std::string error;
  REQUIRE(get(dtraced::image::write_image(path, img, {}), error));
  CHECK(read_bytes(path).substr(0, 12) == "P6\n13 5\n255\n");
  const auto back = get(dtraced::image::read_image(path), error);
  REQUIRE(back);
  REQUIRE(back->width == 13);
  REQUIRE(back->height == 5);
  CHECK(max_code_error(img, *back, 255.0) <= 0.5 + 1e-3);
}

TEST_CASE("PPM reader: comments, maxval below 255 and 16-bit samples", "[image][ppm]") {
  using dtraced::image::srgb_to_linear;
  std::string error;
  SECTION("16-bit big-endian samples") {
    std::string bytes = "P6\n# made by hand\n1 1\n65535\n";
    bytes += std::string("\xff\xff\x80\x00\x00\x00", 6);
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPpm, bytes, "x.ppm"), error);
    REQUIRE(img);
    CHECK(img->rgb[0] == Approx(1.0f));
    CHECK(img->rgb[1] == Approx(srgb_to_linear(32768.0f / 65535.0f)).epsilon(1e-6));
    CHECK(img->rgb[2] == 0.0f);
  }
  SECTION("maxval 15") {
    std::string bytes = "P6 2 1 15\n";
    bytes += std::string("\x0f\x00\x05\x01\x02\x03", 6);
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPpm, bytes, "x.ppm"), error);
    REQUIRE(img);
    CHECK(img->rgb[0] == Approx(1.0f));
    CHECK(img->rgb[2] == Approx(srgb_to_linear(5.0f / 15.0f)).epsilon(1e-6));
  }
  SECTION("a sample above maxval is an error") {
    std::string bytes = "P6 1 1 15\n";
    bytes += std::string("\x10\x00\x00", 3);
    CHECK_FALSE(get(dtraced::image::decode_image(ImageFormat::kPpm, bytes, "x.ppm"), error));
    CHECK(contains(error, "exceeds the maxval 15"));
  }
}

TEST_CASE("PNG round trips", "[image][png]") {
  TempDir dir;
  // Include the darks, where the sRGB curve is steepest and quantisation errors show first.
  ImageRGBf img = random_image(17, 9, 0.0f, 1.0f, 11);
  for (std::size_t i = 0; i < 60; ++i) img.rgb[i] = static_cast<float>(i) * 1e-5f;
  std::string error;
  SECTION("8-bit within half a code") {
    const std::string path = dir.file("rt8.png");
    REQUIRE(get(dtraced::image::write_image(path, img, {.png_bit_depth = 8}), error));
    const std::string bytes = read_bytes(path);
    CHECK(static_cast<unsigned char>(bytes[24]) == 8);  // IHDR bit depth
    CHECK(contains(bytes, "sRGB"));
    const auto back = get(dtraced::image::read_image(path), error);
    REQUIRE(back);
    REQUIRE(back->width == 17);
    REQUIRE(back->height == 9);
    CHECK(max_code_error(img, *back, 255.0) <= 0.5 + 1e-3);
  }
  SECTION("16-bit within half a code") {
    const std::string path = dir.file("rt16.png");
    REQUIRE(get(dtraced::image::write_image(path, img, {.png_bit_depth = 16}), error));
    const std::string bytes = read_bytes(path);
    CHECK(static_cast<unsigned char>(bytes[24]) == 16);
    CHECK(contains(bytes, "sRGB"));
    const auto back = get(dtraced::image::read_image(path), error);
    REQUIRE(back);
    CHECK(max_code_error(img, *back, 65535.0) <= 0.5 + 0.05);
  }
  SECTION("out-of-range values clamp, NaN is black") {
    ImageRGBf odd(2, 1);
    odd.rgb = {-1.0f,
               5.0f,
               std::numeric_limits<float>::quiet_NaN(),
               std::numeric_limits<float>::infinity(),
               -std::numeric_limits<float>::infinity(),
               1.0f};
    const std::string path = dir.file("odd.png");
    REQUIRE(get(dtraced::image::write_image(path, odd, {}), error));
    const auto back = get(dtraced::image::read_image(path), error);
    REQUIRE(back);
    CHECK(back->rgb == std::vector<float>{0.0f, 1.0f, 0.0f, 1.0f, 0.0f, 1.0f});
  }
  SECTION("rows stay in order") {
    ImageRGBf two(1, 2);
    two.pixel(0, 0)[1] = 1.0f;
    const std::string path = dir.file("rows.png");
    REQUIRE(get(dtraced::image::write_image(path, two, {}), error));
    const auto back = get(dtraced::image::read_image(path), error);
    REQUIRE(back);
    CHECK(back->pixel(0, 0)[1] == 1.0f);
    CHECK(back->pixel(0, 1)[1] == 0.0f);
  }
}

TEST_CASE("PNG reader converts other colour types", "[image][png]") {
  using dtraced::image::srgb_to_linear;
  std::string error;
  SECTION("8-bit greyscale") {
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPng, as_bytes(kGrey8Png), "grey.png"), error);
    REQUIRE(img);
    REQUIRE(img->width == 3);
    REQUIRE(img->height == 2);
    CHECK(img->pixel(0, 0)[0] == 0.0f);
    CHECK(img->pixel(1, 0)[2] == Approx(srgb_to_linear(128.0f / 255.0f)).epsilon(1e-6));
    CHECK(img->pixel(2, 1)[1] == Approx(srgb_to_linear(30.0f / 255.0f)).epsilon(1e-6));
  }
  SECTION("palette with transparency: alpha is dropped") {
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPng, as_bytes(kPalettePng), "pal.png"), error);
    REQUIRE(img);
    CHECK(img->rgb == std::vector<float>{1.0f, 0.0f, 0.0f, 0.0f, 0.0f, 1.0f});
  }
  SECTION("16-bit RGBA tagged linear (gAMA 1.0)") {
    const auto img = get(dtraced::image::decode_image(ImageFormat::kPng, as_bytes(kRgba16LinearPng), "lin.png"), error);
    REQUIRE(img);
    CHECK(img->rgb[0] == Approx(32768.0 / 65535.0).epsilon(1e-6));
    CHECK(img->rgb[1] == 1.0f);
    CHECK(img->rgb[2] == 0.0f);
  }
}

TEST_CASE("Unknown extensions are errors naming the path and the choices", "[image][errors]") {
  TempDir dir;
  const std::string path = dir.file("out.jpg");
  std::string error;
  CHECK_FALSE(get(dtraced::image::write_image(path, ImageRGBf(2, 2), {}), error));
  CHECK(contains(error, path));
  CHECK(contains(error, ".png, .ppm, .pfm, .exr or .gif"));
  CHECK_FALSE(fs::exists(path));
  error.clear();
  CHECK_FALSE(get(dtraced::image::read_image(path), error));
  CHECK(contains(error, path));
  CHECK(contains(error, ".png, .ppm, .pfm, .exr or .gif"));
}

TEST_CASE("Malformed files give errors naming the file and the problem", "[image][errors]") {
  TempDir dir;
  std::string error;
  auto read_fails = [&](const std::string& name, std::string_view bytes, std::string_view expected) {
    const std::string path = dir.file(name);
    write_bytes(path, bytes);
    error.clear();
    const auto img = get(dtraced::image::read_image(path), error);
    CHECK_FALSE(img);
    INFO("error: " << error);
    CHECK(contains(error, path));
    CHECK(contains(error, expected));
  };

  SECTION("truncated PFM") {
    const std::string path = dir.file("full.pfm");
    REQUIRE(get(dtraced::image::write_image(path, random_image(7, 3, 0.0f, 1.0f, 3), {}), error));
    const std::string bytes = read_bytes(path);
    read_fails("cut.pfm", std::string_view(bytes).substr(0, bytes.size() - 5), "truncated");
    read_fails("header_only.pfm", "PF\n7 3\n-1.0\n", "truncated");
    read_fails("cut_header.pfm", "PF\n7 ", "truncated");
    read_fails("long.pfm", bytes + "x", "1 unexpected bytes");
  }
  SECTION("dimensions beyond the limit") {
    read_fails("huge.pfm", "PF\n100000 100000\n-1.0\n", "100000");
    read_fails("huge.pfm", "PF\n100000 100000\n-1.0\n", "16384");
    read_fails("huge.ppm", "P6\n100000 100000\n255\n", "16384");
    read_fails("digits.ppm", "P6\n1 99999999999999999999999999\n255\n", "too many digits");
    read_fails("zero.pfm", "PF\n0 4\n-1.0\n", "width 0");
    read_fails("huge.png", as_bytes(kHugeHeaderPng), "invalid PNG");
  }
  SECTION("wrong magic") {
    read_fails("magic.pfm", "P6\n1 1\n255\nabc", "not a PFM file");
    read_fails("magic.ppm", "PF\n1 1\n-1.0\n", "not a binary PPM file");
    read_fails("ascii.ppm", "P3\n1 1\n255\n0 0 0\n", "P3 is not supported");
    read_fails("magic.png", "P6\n1 1\n255\nabc", "not a PNG file");
    read_fails("empty.pfm", "", "not a PFM file");
  }
  SECTION("bad header fields") {
    read_fails("scale.pfm", "PF\n1 1\nabc\n", "scale 'abc'");
    read_fails("zeroscale.pfm", "PF\n1 1\n0\n", "scale '0'");
    read_fails("nosep.ppm", "P6\n1 1 255", "truncated after the maxval");
    read_fails("maxval.ppm", "P6\n1 1\n70000\n", "maxval 70000");
    read_fails("width.ppm", "P6\nx 1\n255\n", "width is not a decimal number");
  }
  SECTION("truncated and corrupt PNG") {
    const std::string path = dir.file("full.png");
    REQUIRE(get(dtraced::image::write_image(path, random_image(32, 32, 0.0f, 1.0f, 5), {}), error));
    const std::string bytes = read_bytes(path);
    read_fails("cut.png", std::string_view(bytes).substr(0, bytes.size() / 2), "truncated");
    read_fails("no_iend.png", std::string_view(bytes).substr(0, bytes.size() - 12), "truncated");
    std::string corrupt = bytes;
    corrupt[corrupt.size() - 20] ^= 0x55;  // inside the IDAT data: its CRC no longer matches
    read_fails("corrupt.png", corrupt, "invalid PNG");
  }
  SECTION("missing file") {
    const std::string path = dir.file("absent.png");
    CHECK_FALSE(get(dtraced::image::read_image(path), error));
    CHECK(contains(error, path));
  }
}

TEST_CASE("Writers reject what they cannot encode", "[image][errors]") {
  TempDir dir;
  std::string error;
  const std::string path = dir.file("bad.png");
  CHECK_FALSE(get(dtraced::image::write_image(path, ImageRGBf(2, 2), {.png_bit_depth = 12}), error));
  CHECK(contains(error, "bit depth 12"));
  CHECK_FALSE(get(dtraced::image::write_image(path, ImageRGBf(0, 3), {}), error));
  CHECK(contains(error, "empty"));
  ImageRGBf broken(2, 2);
  broken.rgb.resize(5);
  CHECK_FALSE(get(dtraced::image::write_image(dir.file("bad.pfm"), broken, {}), error));
  CHECK(contains(error, "inconsistent"));
  CHECK(fs::is_empty(dir.path()));  // nothing written, no temporary left behind
}

TEST_CASE("A successful write leaves only the target file", "[image]") {
  TempDir dir;
  std::string error;
  REQUIRE(get(dtraced::image::write_image(dir.file("a.png"), ImageRGBf(3, 3), {}), error));
  REQUIRE(get(dtraced::image::write_image(dir.file("a.png"), ImageRGBf(4, 4), {}), error));  // replaces
  std::vector<std::string> names;
  for (const auto& entry : fs::directory_iterator(dir.path())) names.push_back(entry.path().filename().string());
  CHECK(names == std::vector<std::string>{"a.png"});
  const auto back = get(dtraced::image::read_image(dir.file("a.png")), error);
  REQUIRE(back);
  CHECK(back->width == 4);
}

TEST_CASE("compare_images on known inputs", "[image][metrics]") {
  using dtraced::image::compare_images;
  std::string error;
  SECTION("identical images: zero error, infinite PSNR") {
    const ImageRGBf a = random_image(5, 4, 0.0f, 2.0f, 1);
    const auto d = get(compare_images(a, a), error);
    REQUIRE(d);
    CHECK(d->mse == 0.0);
    CHECK(d->rmse == 0.0);
    CHECK(d->max_abs == 0.0);
    CHECK(std::isinf(d->psnr_db));
    CHECK(d->psnr_db > 0.0);
    CHECK(d->nonfinite == 0);
  }
  SECTION("a constant difference of 0.1") {
    ImageRGBf a = random_image(6, 5, 0.2f, 0.8f, 2);
    ImageRGBf b = a;
    for (float& v : b.rgb) v += 0.1f;
    const auto d = get(compare_images(a, b), error);
    REQUIRE(d);
    CHECK(d->rmse == Approx(0.1).epsilon(1e-5));
    CHECK(d->mse == Approx(0.01).epsilon(1e-4));
    CHECK(d->max_abs == Approx(0.1).epsilon(1e-5));
    CHECK(std::isfinite(d->psnr_db));
  }
  SECTION("PSNR is display-referred") {
    ImageRGBf black(2, 1), mixed(2, 1);
    for (int c = 0; c < 3; ++c) mixed.pixel(1, 0)[c] = 4.0f;  // far above white, shows as 1
    const auto d = get(compare_images(black, mixed), error);
    REQUIRE(d);
    CHECK(d->max_abs == 4.0);
    CHECK(d->mse == Approx(8.0));                         // linear: half the values differ by 4
    CHECK(d->psnr_db == Approx(10.0 * std::log10(2.0)));  // display: half differ by 1
    ImageRGBf white = black;
    for (float& v : white.rgb) v = 1.0f;
    CHECK(get(compare_images(black, white), error)->psnr_db == Approx(0.0).margin(1e-9));
    ImageRGBf brighter = mixed;
    for (int c = 0; c < 3; ++c) brighter.pixel(1, 0)[c] = 9.0f;
    CHECK(std::isinf(get(compare_images(mixed, brighter), error)->psnr_db));  // both clip to white
  }
  SECTION("non-finite values are counted and excluded") {
    ImageRGBf a(2, 1), b(2, 1);
    a.rgb[0] = std::numeric_limits<float>::quiet_NaN();
    b.rgb[4] = std::numeric_limits<float>::infinity();
    b.rgb[5] = 0.5f;
    CHECK(dtraced::image::count_nonfinite(a) == 1);
    CHECK(dtraced::image::count_nonfinite(b) == 1);
    const auto d = get(compare_images(a, b), error);
    REQUIRE(d);
    CHECK(d->nonfinite == 2);
    CHECK(d->max_abs == 0.5);
    CHECK(d->mse == Approx(0.25 / 4.0));
  }
  SECTION("relative MSE is relative to the second image, with epsilon 0.01") {
    ImageRGBf render(2, 1), reference(2, 1);
    for (int c = 0; c < 3; ++c) {
      reference.pixel(0, 0)[c] = 1.0f;  // bright: an error of 0.5 weighs 0.25 / 1.01
      render.pixel(0, 0)[c] = 1.5f;
      render.pixel(1, 0)[c] = 0.5f;  // black reference: the same error weighs 0.25 / 0.01
    }
    const auto d = get(compare_images(render, reference), error);
    REQUIRE(d);
    CHECK(dtraced::image::kRelMseEpsilon == 0.01);
    CHECK(d->rel_mse == Approx((0.25 / 1.01 + 0.25 / 0.01) / 2.0).epsilon(1e-6));
    CHECK(d->mse == Approx(0.25));
    const auto swapped = get(compare_images(reference, render), error);
    REQUIRE(swapped);
    CHECK(swapped->rel_mse == Approx((0.25 / (2.25 + 0.01) + 0.25 / 0.26) / 2.0).epsilon(1e-6));
    CHECK(get(compare_images(reference, reference), error)->rel_mse == 0.0);
  }
  SECTION("size mismatch is an error") {
    CHECK_FALSE(get(compare_images(ImageRGBf(2, 3), ImageRGBf(3, 2)), error));
    CHECK(contains(error, "2x3"));
    CHECK(contains(error, "3x2"));
  }
}

TEST_CASE("One table names every image format", "[image][formats]") {
  using dtraced::image::ImageFormat;
  std::size_t n = 0;
  for (const auto& f : dtraced::image::image_formats()) {
    ++n;
    INFO(f.name);
    CHECK(&dtraced::image::format_info(f.format) == &f);
    CHECK(dtraced::image::format_from_name(f.name) == f.format);
    CHECK(dtraced::image::format_from_path(fmt::format("dir/x{}", f.extension)) == f.format);
    CHECK(f.extension.substr(1) == f.name);
    CHECK(f.extension.front() == '.');
    CHECK_FALSE(f.content_type.empty());
  }
  CHECK(n == 5);
  CHECK(dtraced::image::format_info(ImageFormat::kPfm).content_type == "image/x-portable-floatmap");
  CHECK(dtraced::image::format_info(ImageFormat::kPng).content_type == "image/png");
  CHECK_FALSE(dtraced::image::format_from_name("PNG"));
  CHECK_FALSE(dtraced::image::format_from_name("jpg"));
  CHECK_FALSE(dtraced::image::format_from_name(""));
  CHECK(dtraced::image::extension_list() == ".png, .ppm, .pfm, .exr or .gif");
  CHECK(dtraced::image::name_list() == "png, ppm, pfm, exr or gif");
}
