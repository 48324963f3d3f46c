// dtraced::image internals: what the per-format codecs (image_io.cpp for PPM and PFM, png_io.cpp,
// exr_io.cpp, gif_io.cpp) share. Included only by src/image/*.cpp; other modules use image_io.h.
//
// Owns: the 8/16-bit quantisation (display transform, sRGB curve, rounding), the decoding tables,
// and one entry point per codec. A codec reports failure as nullopt plus `problem`, a sentence
// without the file name, which image_io.cpp turns into a located util::Error.
//
// Thread safety: pure functions; per-call state only.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "image/display.h"
#include "image/image.h"
#include "image/image_io.h"

namespace dtraced::image::detail {

double srgb_encode(double v);
double srgb_decode(double v);

// A displayed value (display.h: [0, 1], NaN already 0) -> sRGB -> nearest code in [0, max_code].
// Values outside [0, 1] and NaN are clipped here too, so a caller can never produce a bad code.
std::uint32_t quantize(float display01, std::uint32_t max_code);
// std::round for 0 <= x < 2^52 (halves away from zero), without the libm call.
double round_half_away(double x);

// linear -> display transform -> sRGB -> code: what every 8- and 16-bit writer stores.
inline std::uint32_t encode_sample(float linear, const DisplayTransform& display, std::uint32_t max_code) {
  return quantize(display_value(display, linear), max_code);
}

// How integer samples map back to light.
struct Transfer {
  bool srgb = true;
  double exponent = 1.0;  // used when !srgb: linear = (code / max) ^ exponent
};

// One float per possible code, so decoding costs a lookup instead of a pow() per sample. Built
// per call (at most 65536 entries), never cached globally.
std::vector<float> decode_table(std::uint32_t max_code, const Transfer& transfer);

// Codecs. `img` is consistent and not empty (image_io.cpp checks it first).
std::optional<std::string> encode_png(const ImageRGBf& img, int bit_depth, const DisplayTransform& display,
                                      std::string& problem);
std::optional<ImageRGBf> decode_png(std::string_view bytes, std::string& problem);
std::optional<std::string> encode_exr(const ImageRGBf& img, const WriteOptions& opts, std::string& problem);
std::optional<ImageRGBf> decode_exr(std::string_view bytes, std::string& problem);
// A one-frame GIF (gif_io.cpp).
std::optional<std::string> encode_gif(const ImageRGBf& img, const DisplayTransform& display, std::string& problem);

}  // namespace dtraced::image::detail
