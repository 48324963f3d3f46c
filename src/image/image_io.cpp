#include "image/image_io.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <charconv>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <vector>

#include <fmt/format.h>

#include "image/codec.h"
#include "math/det_math.h"
#include "util/file.h"

namespace dtraced::image {
namespace detail {

// ---------------------------------------------------------------------------------------------
// Transfer functions and quantisation, shared by every 8- and 16-bit codec.

double srgb_encode(double v) { return v <= 0.0031308 ? 12.92 * v : 1.055 * math::det::pow_fast(v, 1.0 / 2.4) - 0.055; }
double srgb_decode(double v) { return v <= 0.04045 ? v / 12.92 : math::det::pow((v + 0.055) / 1.055, 2.4); }

std::uint32_t quantize(float display01, std::uint32_t max_code) {
  // The negated test also sends NaN to black: it has no brightness, and the cast below would be UB.
  if (!(display01 > 0.0f)) return 0;
  if (display01 >= 1.0f) return max_code;
  const double code = round_half_away(srgb_encode(display01) * max_code);
  return static_cast<std::uint32_t>(std::clamp(code, 0.0, static_cast<double>(max_code)));
}

double round_half_away(double x) {
  // std::round is a libm call on the baseline instruction set (2 % of a 1280x720 render's process
  // samples went to it in the PNG writer). The truncation is exact below 2^52, and so is
  // x - whole (whole <= x < 2 * whole once whole >= 1: Sterbenz), so the half test is exact;
  // truncating x + 0.5 instead would round 0.49999999999999994 up.
  const double whole = static_cast<double>(static_cast<std::int64_t>(x));
  return x - whole >= 0.5 ? whole + 1.0 : whole;
}

std::vector<float> decode_table(std::uint32_t max_code, const Transfer& transfer) {
  std::vector<float> table(std::size_t{max_code} + 1);
  for (std::uint32_t i = 0; i <= max_code; ++i) {
    const double v = static_cast<double>(i) / max_code;
    table[i] = static_cast<float>(transfer.srgb ? srgb_decode(v) : math::det::pow(v, transfer.exponent));
  }
  return table;
}

}  // namespace detail

namespace {

using detail::decode_table;
using detail::Transfer;

bool check_encodable(const ImageRGBf& img, std::string& problem) {
  if (!img.is_consistent()) {
    problem = fmt::format("inconsistent image: {}x{} with {} floats (expected {}, sides at most {})", img.width,
                          img.height, img.rgb.size(), std::size_t{img.width} * img.height * 3, kMaxImageSide);
    return false;
  }
  if (img.width == 0 || img.height == 0) {
    problem = fmt::format("cannot write an empty {}x{} image", img.width, img.height);
    return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------------
// The text headers of PPM and PFM. Every number is bounded in digits and value, and the whole
// header lies within the (already size-limited) file, so hostile input can neither overflow nor
// make us allocate.

bool is_space(char c) { return c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == '\v' || c == '\f'; }

class HeaderReader {
 public:
  HeaderReader(std::string_view bytes, bool allow_comments) : bytes_(bytes), allow_comments_(allow_comments) {}

  std::size_t pos() const { return pos_; }
  bool at_end() const { return pos_ >= bytes_.size(); }

  // Skips whitespace and, where the format allows them, '#' comments to the end of their line.
  // Returns false when nothing was skipped: tokens must be separated.
  bool skip_separator() {
    const std::size_t start = pos_;
    while (!at_end()) {
      const char c = bytes_[pos_];
      if (is_space(c)) {
        ++pos_;
      } else if (allow_comments_ && c == '#') {
        while (!at_end() && bytes_[pos_] != '\n' && bytes_[pos_] != '\r') ++pos_;
      } else {
        break;
      }
    }
    return pos_ != start;
  }

  // The single whitespace byte that ends both headers: more would eat into the binary data,
  // whose first bytes may well look like whitespace.
  bool skip_one_space() {
    if (at_end() || !is_space(bytes_[pos_])) return false;
    ++pos_;
    return true;
  }

  // A decimal integer of at most kMaxDigits digits; more is reported as too large, not wrapped.
  enum class Number { kOk, kMissing, kTooLarge };
  Number read_uint(std::uint64_t& value) {
    constexpr int kMaxDigits = 18;  // always fits in uint64
    value = 0;
    int digits = 0;
    while (!at_end() && bytes_[pos_] >= '0' && bytes_[pos_] <= '9') {
      if (++digits > kMaxDigits) return Number::kTooLarge;
      value = value * 10 + static_cast<std::uint64_t>(bytes_[pos_] - '0');
      ++pos_;
    }
    return digits == 0 ? Number::kMissing : Number::kOk;
  }

  // A run of non-space bytes (the PFM scale); nullopt when longer than max_len.
  std::optional<std::string_view> read_token(std::size_t max_len) {
    const std::size_t start = pos_;
    while (!at_end() && !is_space(bytes_[pos_])) {
      if (pos_ - start >= max_len) return std::nullopt;
      ++pos_;
    }
    return bytes_.substr(start, pos_ - start);
  }

 private:
  std::string_view bytes_;
  bool allow_comments_;
  std::size_t pos_ = 0;
};

// Separator, then a decimal number in [1, max], named `what` in errors.
bool read_header_number(HeaderReader& in, const char* what, std::uint64_t max, std::uint64_t& value,
                        std::string& problem) {
  if (!in.skip_separator()) {
    problem = in.at_end() ? fmt::format("header: truncated before the {}", what)
                          : fmt::format("header: expected whitespace before the {}", what);
    return false;
  }
  switch (in.read_uint(value)) {
    case HeaderReader::Number::kMissing:
      problem = in.at_end() ? fmt::format("header: truncated before the {}", what)
                            : fmt::format("header: the {} is not a decimal number", what);
      return false;
    case HeaderReader::Number::kTooLarge:
      problem = fmt::format("header: the {} has too many digits (limit {})", what, max);
      return false;
    case HeaderReader::Number::kOk:
      break;
  }
  if (value == 0 || value > max) {
    problem = fmt::format("header: {} {} is outside the supported range 1..{}", what, value, max);
    return false;
  }
  return true;
}

// Compares the bytes after the header with what the header promised, exactly.
bool check_payload_size(std::string_view format, std::uint64_t available, std::uint64_t expected, std::string_view what,
                        std::string& problem) {
  if (available < expected) {
    problem = fmt::format("truncated {}: the header promises {} ({} bytes of pixel data) but only {} bytes follow",
                          format, what, expected, available);
    return false;
  }
  if (available > expected) {
    problem = fmt::format("{} has {} unexpected bytes after the {} pixel data ({} bytes)", format, available - expected,
                          what, expected);
    return false;
  }
  return true;
}

// ---------------------------------------------------------------------------------------------
// PPM (P6).

std::string encode_ppm(const ImageRGBf& img, const DisplayTransform& display) {
  std::string out = fmt::format("P6\n{} {}\n255\n", img.width, img.height);
  const std::size_t header = out.size();
  out.resize(header + img.rgb.size());
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    out[header + i] = static_cast<char>(detail::encode_sample(img.rgb[i], display, 255));
  }
  return out;
}

std::optional<ImageRGBf> decode_ppm(std::string_view bytes, std::string& problem) {
  if (bytes.size() < 2 || bytes[0] != 'P' || bytes[1] != '6') {
    if (bytes.size() >= 2 && bytes[0] == 'P' && bytes[1] >= '1' && bytes[1] <= '5') {
      problem = fmt::format("netpbm format P{} is not supported; only binary colour PPM (P6) is", bytes[1]);
    } else {
      problem = "not a binary PPM file: it does not start with the magic 'P6'";
    }
    return std::nullopt;
  }
  HeaderReader in(bytes.substr(2), /* allow_comments = */ true);
  std::uint64_t width = 0, height = 0, maxval = 0;
  if (!read_header_number(in, "width", kMaxImageSide, width, problem) ||
      !read_header_number(in, "height", kMaxImageSide, height, problem) ||
      !read_header_number(in, "maxval", 65535, maxval, problem)) {
    return std::nullopt;
  }
  if (!in.skip_one_space()) {
    problem = in.at_end() ? "header: truncated after the maxval" : "header: expected one whitespace after the maxval";
    return std::nullopt;
  }
  const std::uint64_t bytes_per_sample = maxval < 256 ? 1 : 2;
  const std::uint64_t header_size = 2 + in.pos();
  const std::uint64_t expected = width * height * 3 * bytes_per_sample;
  if (!check_payload_size("PPM", bytes.size() - header_size, expected,
                          fmt::format("{}x{} pixels at maxval {}", width, height, maxval), problem)) {
    return std::nullopt;
  }

  // PPM has no colour-space tag; every tool that writes 8-bit PPMs today means sRGB, as we do.
  const std::vector<float> table = decode_table(static_cast<std::uint32_t>(maxval), Transfer{});
  ImageRGBf img(static_cast<std::uint32_t>(width), static_cast<std::uint32_t>(height));
  const auto* data = reinterpret_cast<const unsigned char*>(bytes.data() + header_size);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    const std::uint32_t code = bytes_per_sample == 1 ? data[i] : (std::uint32_t{data[2 * i]} << 8) | data[2 * i + 1];
    if (code > maxval) {
      const std::size_t pixel = i / 3;
      problem =
          fmt::format("sample {} at pixel ({}, {}) exceeds the maxval {}", code, pixel % width, pixel / width, maxval);
      return std::nullopt;
    }
    img.rgb[i] = table[code];
  }
  return img;
}

// ---------------------------------------------------------------------------------------------
// PFM.

constexpr std::uint32_t byteswap32(std::uint32_t v) {
  return (v >> 24) | ((v >> 8) & 0x0000ff00u) | ((v << 8) & 0x00ff0000u) | (v << 24);
}

std::string encode_pfm(const ImageRGBf& img) {
  // Little-endian, as most readers (pbrt, Mitsuba, OpenImageIO) write and expect.
  std::string out = fmt::format("PF\n{} {}\n-1.0\n", img.width, img.height);
  const std::size_t header = out.size();
  const std::size_t row_floats = std::size_t{img.width} * 3;
  out.resize(header + img.rgb.size() * 4);
  char* dst = out.data() + header;
  // PFM stores the bottom row first.
  for (std::uint32_t file_row = 0; file_row < img.height; ++file_row) {
    const float* src = img.rgb.data() + std::size_t{img.height - 1 - file_row} * row_floats;
    for (std::size_t i = 0; i < row_floats; ++i) {
      std::uint32_t bits = std::bit_cast<std::uint32_t>(src[i]);
      if constexpr (std::endian::native == std::endian::big) bits = byteswap32(bits);
      std::memcpy(dst, &bits, 4);
      dst += 4;
    }
  }
  return out;
}

std::optional<ImageRGBf> decode_pfm(std::string_view bytes, std::string& problem) {
  if (bytes.size() < 2 || bytes[0] != 'P' || (bytes[1] != 'F' && bytes[1] != 'f')) {
    problem = "not a PFM file: it does not start with the magic 'PF' (colour) or 'Pf' (greyscale)";
    return std::nullopt;
  }
  const std::uint64_t channels = bytes[1] == 'F' ? 3 : 1;
  HeaderReader in(bytes.substr(2), /* allow_comments = */ false);
  std::uint64_t width = 0, height = 0;
  if (!read_header_number(in, "width", kMaxImageSide, width, problem) ||
      !read_header_number(in, "height", kMaxImageSide, height, problem)) {
    return std::nullopt;
  }
  if (!in.skip_separator()) {
    problem = "header: expected whitespace before the scale";
    return std::nullopt;
  }
  constexpr std::size_t kMaxScaleChars = 64;  // "-1.000000" in practice; generous for exponents
  const std::optional<std::string_view> token = in.read_token(kMaxScaleChars);
  if (!token) {
    problem = fmt::format("header: the scale is longer than {} characters", kMaxScaleChars);
    return std::nullopt;
  }
  const std::string_view scale_text = *token;
  double scale = 0.0;
  const auto [end, ec] = std::from_chars(scale_text.data(), scale_text.data() + scale_text.size(), scale);
  if (scale_text.empty() || ec != std::errc() || end != scale_text.data() + scale_text.size() ||
      !std::isfinite(scale) || scale == 0.0) {
    problem = in.at_end() && scale_text.empty()
                  ? std::string("header: truncated before the scale")
                  : fmt::format("header: the scale '{}' is not a finite non-zero number", scale_text);
    return std::nullopt;
  }
  if (!in.skip_one_space()) {
    problem = "header: truncated after the scale";
    return std::nullopt;
  }
  const std::uint64_t header_size = 2 + in.pos();
  if (!check_payload_size("PFM", bytes.size() - header_size, width * height * channels * 4,
                          fmt::format("{}x{} {} pixels", width, height, channels == 3 ? "colour" : "greyscale"),
                          problem)) {
    return std::nullopt;
  }

  // The sign of the scale is the byte order; its magnitude, when not 1, scales the data.
  const bool file_little = scale < 0.0;
  const bool swap = file_little != (std::endian::native == std::endian::little);
  const float magnitude = static_cast<float>(std::abs(scale));
  ImageRGBf img(static_cast<std::uint32_t>(width), static_cast<std::uint32_t>(height));
  const char* src = bytes.data() + header_size;
  for (std::uint32_t file_row = 0; file_row < img.height; ++file_row) {
    float* dst = img.pixel(0, img.height - 1 - file_row);  // bottom row first
    for (std::uint32_t x = 0; x < img.width; ++x) {
      for (std::uint64_t c = 0; c < channels; ++c) {
        std::uint32_t bits = 0;
        std::memcpy(&bits, src, 4);
        src += 4;
        if (swap) bits = byteswap32(bits);
        float v = std::bit_cast<float>(bits);
        if (magnitude != 1.0f) v *= magnitude;
        dst[x * 3 + c] = v;
      }
      if (channels == 1) dst[x * 3 + 1] = dst[x * 3 + 2] = dst[x * 3];
    }
  }
  return img;
}

std::string_view format_name(ImageFormat format) { return format_info(format).label; }

constexpr std::array<FormatInfo, 5> kFormats = {{
    {ImageFormat::kPng, "png", ".png", "image/png", "PNG"},
    {ImageFormat::kPpm, "ppm", ".ppm", "image/x-portable-pixmap", "PPM"},
    {ImageFormat::kPfm, "pfm", ".pfm", "image/x-portable-floatmap", "PFM"},
    {ImageFormat::kExr, "exr", ".exr", "image/x-exr", "EXR"},
    {ImageFormat::kGif, "gif", ".gif", "image/gif", "GIF"},
}};
// Other spellings of an extension: the seed wrote its PPM files as .pnm.
constexpr std::array<std::pair<std::string_view, ImageFormat>, 1> kExtensionAliases = {{{".pnm", ImageFormat::kPpm}}};

// "a, b or c" from the formats' `field`.
std::string list_of(std::string_view FormatInfo::*field) {
  std::string out;
  for (std::size_t i = 0; i < kFormats.size(); ++i) {
    if (i > 0) out += i + 1 == kFormats.size() ? " or " : ", ";
    out += kFormats[i].*field;
  }
  return out;
}

}  // namespace

float linear_to_srgb(float linear) { return static_cast<float>(detail::srgb_encode(linear)); }
float srgb_to_linear(float encoded) { return static_cast<float>(detail::srgb_decode(encoded)); }

std::span<const FormatInfo> image_formats() { return kFormats; }

const FormatInfo& format_info(ImageFormat format) {
  for (const FormatInfo& f : kFormats) {
    if (f.format == format) return f;
  }
  assert(false && "every ImageFormat has a row in kFormats");
  return kFormats[0];
}

std::optional<ImageFormat> format_from_path(const std::string& path) {
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return static_cast<char>(c >= 'A' && c <= 'Z' ? c - 'A' + 'a' : c); });
  for (const FormatInfo& f : kFormats) {
    if (ext == f.extension) return f.format;
  }
  for (const auto& [alias, format] : kExtensionAliases) {
    if (ext == alias) return format;
  }
  return std::nullopt;
}

std::optional<ImageFormat> format_from_name(std::string_view name) {
  for (const FormatInfo& f : kFormats) {
    if (name == f.name) return f.format;
  }
  return std::nullopt;
}

std::string extension_list() { return list_of(&FormatInfo::extension); }
std::string name_list() { return list_of(&FormatInfo::name); }

util::Result<std::string> encode_image(ImageFormat format, const ImageRGBf& img, const WriteOptions& opts) {
  std::string problem;
  if (!check_encodable(img, problem)) return util::Error(problem, "", std::string(format_name(format)));
  std::optional<std::string> out;
  switch (format) {
    case ImageFormat::kPpm:
      return encode_ppm(img, opts.display);
    case ImageFormat::kPfm:
      return encode_pfm(img);
    case ImageFormat::kPng:
      if (opts.png_bit_depth != 8 && opts.png_bit_depth != 16) {
        return util::Error(fmt::format("unsupported bit depth {} (8 or 16)", opts.png_bit_depth), "", "PNG");
      }
      out = detail::encode_png(img, opts.png_bit_depth, opts.display, problem);
      break;
    case ImageFormat::kExr:
      out = detail::encode_exr(img, opts, problem);
      break;
    case ImageFormat::kGif:
      out = detail::encode_gif(img, opts.display, problem);
      break;
  }
  if (!out) return util::Error(problem, "", std::string(format_name(format)));
  return std::move(*out);
}

util::Result<ImageRGBf> decode_image(ImageFormat format, std::string_view bytes, std::string_view name) {
  std::string problem;
  std::optional<ImageRGBf> img;
  switch (format) {
    case ImageFormat::kPng:
      img = detail::decode_png(bytes, problem);
      break;
    case ImageFormat::kExr:
      img = detail::decode_exr(bytes, problem);
      break;
    case ImageFormat::kGif:
      problem = "reading GIF files is not supported (write them only)";
      break;
    case ImageFormat::kPpm:
      img = decode_ppm(bytes, problem);
      break;
    case ImageFormat::kPfm:
      img = decode_pfm(bytes, problem);
      break;
  }
  if (!img) return util::Error(problem, "", std::string(name));
  return std::move(*img);
}

util::Status write_image(const std::string& path, const ImageRGBf& img, const WriteOptions& opts) {
  const auto format = format_from_path(path);
  if (!format) {
    return util::Error(fmt::format("unknown image format (supported extensions: {})", extension_list()), "", path);
  }
  util::Result<std::string> bytes = encode_image(*format, img, opts);
  if (!bytes) return util::Error(bytes.error().to_string(), "", path);
  return util::write_file_atomic(path, *bytes);
}

util::Result<ImageRGBf> read_image(const std::string& path) {
  const auto format = format_from_path(path);
  if (!format) {
    return util::Error(fmt::format("unknown image format (supported extensions: {})", extension_list()), "", path);
  }
  util::Result<std::string> bytes = util::read_file_limited(path, kMaxImageFileBytes);
  if (!bytes) return bytes.error();
  return decode_image(*format, *bytes, path);
}

}  // namespace dtraced::image
