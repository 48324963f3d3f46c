// Tests for the GIF encoder (image/gif_io.h), read back with giflib's own decoder (DGifSlurp):
// frame count, delays, the NETSCAPE2.0 loop, every pixel against the display-encoded input (the
// PPM writer's bytes for the same display transform), the median cut's error and dithering.
#include <gif_lib.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "image/gif_io.h"
#include "image/image_io.h"
#include "util/file.h"

namespace {

using dtraced::image::DisplayTransform;
using dtraced::image::GifEncoder;
using dtraced::image::GifOptions;
using dtraced::image::ImageFormat;
using dtraced::image::ImageRGBf;

struct DecodedGif {
  std::string version;
  int width = 0, height = 0;
  std::vector<std::vector<std::uint8_t>> frames;  // 8-bit RGB per frame
  std::vector<int> delays;                        // centiseconds
  int loop_count = -1;                            // -1: no NETSCAPE2.0 extension
};

struct MemoryReader {
  const std::vector<std::uint8_t>* bytes;
  std::size_t pos = 0;
};

int read_memory(GifFileType* gif, GifByteType* out, int n) {
  auto* r = static_cast<MemoryReader*>(gif->UserData);
  const std::size_t take = std::min<std::size_t>(std::size_t(n), r->bytes->size() - r->pos);
  std::memcpy(out, r->bytes->data() + r->pos, take);
  r->pos += take;
  return int(take);
}

// The loop count of a NETSCAPE2.0 application extension among `blocks`, or -1.
int loop_count(const ExtensionBlock* blocks, int count) {
  for (int i = 0; i + 1 < count; ++i) {
    const ExtensionBlock& app = blocks[i];
    const ExtensionBlock& data = blocks[i + 1];
    if (app.Function == APPLICATION_EXT_FUNC_CODE && app.ByteCount == 11 &&
        std::memcmp(app.Bytes, "NETSCAPE2.0", 11) == 0 && data.Function == CONTINUE_EXT_FUNC_CODE &&
        data.ByteCount == 3 && data.Bytes[0] == 1) {
      return data.Bytes[1] | (data.Bytes[2] << 8);
    }
  }
  return -1;
}

DecodedGif decode(const std::vector<std::uint8_t>& bytes) {
  DecodedGif out;
  REQUIRE(bytes.size() > 6);
  out.version.assign(bytes.begin(), bytes.begin() + 6);
  MemoryReader reader{&bytes};
  int error = 0;
  GifFileType* gif = DGifOpen(&reader, read_memory, &error);
  REQUIRE(gif != nullptr);
  const int slurped = DGifSlurp(gif);
  INFO(GifErrorString(gif->Error));
  REQUIRE(slurped == GIF_OK);
  out.width = gif->SWidth;
  out.height = gif->SHeight;
  for (int i = 0; i < gif->ImageCount; ++i) {
    const SavedImage& image = gif->SavedImages[i];
    REQUIRE(image.ImageDesc.Left == 0);
    REQUIRE(image.ImageDesc.Top == 0);
    REQUIRE(image.ImageDesc.Width == gif->SWidth);
    REQUIRE(image.ImageDesc.Height == gif->SHeight);
    const ColorMapObject* map = image.ImageDesc.ColorMap ? image.ImageDesc.ColorMap : gif->SColorMap;
    REQUIRE(map != nullptr);
    std::vector<std::uint8_t> rgb;
    for (int p = 0; p < gif->SWidth * gif->SHeight; ++p) {
      const int index = image.RasterBits[p];
      REQUIRE(index < map->ColorCount);
      rgb.push_back(map->Colors[index].Red);
      rgb.push_back(map->Colors[index].Green);
      rgb.push_back(map->Colors[index].Blue);
    }
    out.frames.push_back(std::move(rgb));
    GraphicsControlBlock gcb;
    REQUIRE(DGifSavedExtensionToGCB(gif, i, &gcb) == GIF_OK);
    out.delays.push_back(gcb.DelayTime);
    if (out.loop_count < 0) out.loop_count = loop_count(image.ExtensionBlocks, image.ExtensionBlockCount);
  }
  DGifCloseFile(gif, &error);
  return out;
}

// What the 8-bit writers make of `img`: the PPM encoder's samples for the same display transform.
std::vector<std::uint8_t> display_codes(const ImageRGBf& img, const DisplayTransform& display) {
  dtraced::image::WriteOptions opts;
  opts.display = display;
  const auto ppm = dtraced::image::encode_image(ImageFormat::kPpm, img, opts);
  REQUIRE(ppm);
  const std::size_t n = img.rgb.size();
  return std::vector<std::uint8_t>(ppm->end() - std::ptrdiff_t(n), ppm->end());
}

// A linear image whose 8-bit sRGB codes are code(x, y, channel).
template <typename F>
ImageRGBf image_of_codes(std::uint32_t w, std::uint32_t h, F code) {
  ImageRGBf img(w, h);
  for (std::uint32_t y = 0; y < h; ++y) {
    for (std::uint32_t x = 0; x < w; ++x) {
      for (int c = 0; c < 3; ++c) img.pixel(x, y)[c] = dtraced::image::srgb_to_linear(float(code(x, y, c)) / 255.0f);
    }
  }
  return img;
}

std::vector<std::uint8_t> encode(const std::vector<ImageRGBf>& frames, const GifOptions& options) {
  auto encoder = GifEncoder::create(frames.at(0).width, frames.at(0).height, options);
  REQUIRE(encoder);
  for (const ImageRGBf& f : frames) {
    const auto added = encoder->add_frame(f);
    INFO((added ? "" : added.error().to_string()));
    REQUIRE(added);
  }
  CHECK(encoder->frame_count() == frames.size());
  auto bytes = encoder->finish();
  REQUIRE(bytes);
  return std::move(bytes).value();
}

int max_difference(const std::vector<std::uint8_t>& a, const std::vector<std::uint8_t>& b) {
  REQUIRE(a.size() == b.size());
  int worst = 0;
  for (std::size_t i = 0; i < a.size(); ++i) worst = std::max(worst, std::abs(int(a[i]) - int(b[i])));
  return worst;
}

}  // namespace

TEST_CASE("An animated GIF reads back with its frames, delays and an endless loop", "[image][gif]") {
  std::vector<ImageRGBf> frames;
  for (int k = 0; k < 3; ++k) {  // a few colours per frame: the palette holds them exactly
    frames.push_back(image_of_codes(16, 8, [k](std::uint32_t x, std::uint32_t y, int c) {
      if (x == std::uint32_t(k) * 5) return 255;
      return (c == k ? 200 : 30) + int(y % 3) * 10;
    }));
  }
  frames[1].pixel(3, 3)[0] = std::numeric_limits<float>::quiet_NaN();  // encoded as black, like PNG
  frames[2].pixel(4, 4)[1] = 50.0f;                                    // clipped, like PNG

  for (const DisplayTransform& display :
       {DisplayTransform{}, DisplayTransform{-1.5, dtraced::image::ToneCurve::kReinhard}}) {
    GifOptions options;
    options.fps = 10;
    options.display = display;
    const DecodedGif gif = decode(encode(frames, options));
    CHECK(gif.version == "GIF89a");
    CHECK(gif.width == 16);
    CHECK(gif.height == 8);
    REQUIRE(gif.frames.size() == 3);
    CHECK(gif.delays == std::vector<int>{10, 10, 10});
    CHECK(gif.loop_count == 0);  // 0 = forever
    for (std::size_t k = 0; k < 3; ++k) {
      INFO("frame " << k);
      CHECK(gif.frames[k] == display_codes(frames[k], display));
    }
  }
}

TEST_CASE("Frame delays come from fps in centiseconds, rounded, at least 2", "[image][gif]") {
  using dtraced::image::gif_delay_centiseconds;
  CHECK(gif_delay_centiseconds(24) == 4);
  CHECK(gif_delay_centiseconds(25) == 4);
  CHECK(gif_delay_centiseconds(30) == 3);
  CHECK(gif_delay_centiseconds(10) == 10);
  CHECK(gif_delay_centiseconds(60) == 2);
  CHECK(gif_delay_centiseconds(1000) == 2);
  CHECK(gif_delay_centiseconds(0.5) == 200);
  CHECK(gif_delay_centiseconds(0.001) == 65535);

  const ImageRGBf frame(4, 4);
  GifOptions options;
  options.fps = 24;
  CHECK(decode(encode({frame, frame}, options)).delays == std::vector<int>{4, 4});
  options.fps = 100;
  CHECK(decode(encode({frame}, options)).delays == std::vector<int>{2});
}

TEST_CASE("A frame of more than 256 colours stays within the median cut's error", "[image][gif]") {
  // 4096 distinct colours on a regular grid: 256 boxes of 4x4 colours, 4 codes apart, so no
  // pixel should land more than 6 codes from its colour (half a box's extent of 12).
  const ImageRGBf img = image_of_codes(64, 64, [](std::uint32_t x, std::uint32_t y, int c) {
    return c == 0 ? int(x) * 4 : c == 1 ? int(y) * 4 : 128;
  });
  const std::vector<std::uint8_t> want = display_codes(img, {});
  const DecodedGif gif = decode(encode({img}, {}));
  REQUIRE(gif.frames.size() == 1);
  const int worst = max_difference(gif.frames[0], want);
  CHECK(worst > 0);  // really quantised
  CHECK(worst <= 6);
}

TEST_CASE("Dithering keeps the local average of a frame closer to its colours", "[image][gif]") {
  // Random colours fill most of the frame, so the median cut spreads most of its 256 entries over
  // the whole cube; a dark grey ramp (8 rows) below them then falls between entries. Without
  // dithering it turns into bands (about 1.2 codes of error per 8x8 block mean here);
  // Floyd-Steinberg mixes neighbours so that the block means follow the ramp (about 0.4). The
  // input and the encoder are deterministic, so these figures are too.
  std::mt19937 rng(7);
  std::uniform_int_distribution<int> code(0, 255);
  std::vector<int> noise(128 * 120 * 3);
  for (int& v : noise) v = code(rng);
  const ImageRGBf img = image_of_codes(128, 128, [&](std::uint32_t x, std::uint32_t y, int c) {
    return y < 120 ? noise[(y * 128 + x) * 3 + std::uint32_t(c)] : 40 + int(x) / 2;
  });
  const std::vector<std::uint8_t> want = display_codes(img, {});
  GifOptions plain, dithered;
  dithered.dither = true;
  const DecodedGif a = decode(encode({img}, plain));
  const DecodedGif b = decode(encode({img}, dithered));
  REQUIRE(a.frames.size() == 1);
  REQUIRE(b.frames.size() == 1);
  CHECK(a.frames[0] != b.frames[0]);
  auto ramp_block_error = [&](const std::vector<std::uint8_t>& got) {
    double total = 0;
    for (int by = 120; by < 128; by += 8) {
      for (int bx = 0; bx < 128; bx += 8) {
        for (int c = 0; c < 3; ++c) {
          double diff = 0;
          for (int y = by; y < by + 8; ++y) {
            for (int x = bx; x < bx + 8; ++x) {
              const std::size_t i = (std::size_t(y) * 128 + std::size_t(x)) * 3 + std::size_t(c);
              diff += double(got[i]) - double(want[i]);
            }
          }
          total += std::abs(diff / 64);
        }
      }
    }
    return total / (16 * 3);  // per block and channel, in codes
  };
  const double plain_error = ramp_block_error(a.frames[0]);
  const double dithered_error = ramp_block_error(b.frames[0]);
  INFO("mean block error on the ramp without dithering " << plain_error << ", with " << dithered_error);
  CHECK(plain_error > 1.0);
  CHECK(dithered_error < 0.5 * plain_error);
}

TEST_CASE("A single image written to .gif is a one-frame GIF", "[image][gif]") {
  const ImageRGBf img = image_of_codes(
      5, 3, [](std::uint32_t x, std::uint32_t y, int c) { return int(x * 50 + y * 7 + std::uint32_t(c) * 3); });
  const auto bytes = dtraced::image::encode_image(ImageFormat::kGif, img, {});
  REQUIRE(bytes);
  const DecodedGif gif = decode(std::vector<std::uint8_t>(bytes->begin(), bytes->end()));
  REQUIRE(gif.frames.size() == 1);
  CHECK(gif.frames[0] == display_codes(img, {}));
  const auto read = dtraced::image::decode_image(ImageFormat::kGif, *bytes, "x.gif");
  REQUIRE_FALSE(read);
  CHECK(read.error().to_string() == "x.gif: reading GIF files is not supported (write them only)");
}

TEST_CASE("The GIF encoder refuses bad sizes, rates, frames and calls out of order", "[image][gif]") {
  CHECK_FALSE(GifEncoder::create(0, 4, {}));
  CHECK_FALSE(GifEncoder::create(4, dtraced::image::kMaxImageSide + 1, {}));
  for (double fps : {0.0, -1.0, 1001.0, std::numeric_limits<double>::quiet_NaN()}) {
    GifOptions options;
    options.fps = fps;
    const auto encoder = GifEncoder::create(4, 4, options);
    REQUIRE_FALSE(encoder);
    CHECK(encoder.error().message.find("fps") != std::string::npos);
  }
  auto encoder = GifEncoder::create(4, 4, {});
  REQUIRE(encoder);
  const auto wrong = encoder->add_frame(ImageRGBf(4, 5));
  REQUIRE_FALSE(wrong);
  CHECK(wrong.error().message.find("every frame must be 4x4") != std::string::npos);
  ImageRGBf broken(4, 4);
  broken.rgb.pop_back();
  CHECK_FALSE(encoder->add_frame(broken));

  auto empty = GifEncoder::create(4, 4, {});
  REQUIRE(empty);
  const auto none = empty->finish();
  REQUIRE_FALSE(none);
  CHECK(none.error().message.find("no frames") != std::string::npos);

  REQUIRE(encoder->add_frame(ImageRGBf(4, 4)));
  REQUIRE(encoder->finish());
  CHECK_FALSE(encoder->add_frame(ImageRGBf(4, 4)));
  CHECK_FALSE(encoder->finish());
}
