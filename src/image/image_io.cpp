#include "image/image_io.h"

#include <png.h>

#include <algorithm>
#include <array>
#include <bit>
#include <cassert>
#include <charconv>
#include <cmath>
#include <csetjmp>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <vector>

#include <fmt/format.h>

#include "util/file.h"

namespace dtraced::image {
namespace {

// ---------------------------------------------------------------------------------------------
// Transfer functions and quantisation.

double srgb_encode(double v) { return v <= 0.0031308 ? 12.92 * v : 1.055 * std::pow(v, 1.0 / 2.4) - 0.055; }
double srgb_decode(double v) { return v <= 0.04045 ? v / 12.92 : std::pow((v + 0.055) / 1.055, 2.4); }

// linear -> clamp to [0, 1] -> sRGB -> nearest integer code in [0, max_code].
std::uint32_t quantize(float linear, std::uint32_t max_code) {
  // The negated test also sends NaN to black: it has no brightness, and the cast below would be UB.
  if (!(linear > 0.0f)) return 0;
  if (linear >= 1.0f) return max_code;
  const double code = std::round(srgb_encode(linear) * max_code);
  return static_cast<std::uint32_t>(std::clamp(code, 0.0, static_cast<double>(max_code)));
}

// How integer samples map back to light.
struct Transfer {
  bool srgb = true;
  double exponent = 1.0;  // used when !srgb: linear = (code / max) ^ exponent
};

// One float per possible code, so decoding costs a lookup instead of a pow() per sample. Built
// per call (at most 65536 entries), never cached globally.
std::vector<float> decode_table(std::uint32_t max_code, const Transfer& transfer) {
  std::vector<float> table(std::size_t{max_code} + 1);
  for (std::uint32_t i = 0; i <= max_code; ++i) {
    const double v = static_cast<double>(i) / max_code;
    table[i] = static_cast<float>(transfer.srgb ? srgb_decode(v) : std::pow(v, transfer.exponent));
  }
  return table;
}

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

std::string encode_ppm(const ImageRGBf& img) {
  std::string out = fmt::format("P6\n{} {}\n255\n", img.width, img.height);
  const std::size_t header = out.size();
  out.resize(header + img.rgb.size());
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    out[header + i] = static_cast<char>(quantize(img.rgb[i], 255));
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

// ---------------------------------------------------------------------------------------------
// PNG through libpng's classic API.
//
// libpng reports errors by longjmp. To keep that well-defined in C++, every libpng call happens
// inside one of the small guarded_png_* functions below, which call setjmp first and hold only
// trivially destructible locals; the callbacks libpng calls into do the same. C++ objects (the
// pixel buffers, the output string) are created by the callers before and used after. A longjmp
// therefore never skips a destructor.

struct PngIo {
  const unsigned char* data = nullptr;  // reading: the whole file
  std::size_t size = 0;
  std::size_t offset = 0;
  std::string* out = nullptr;  // writing: bytes are appended here
  char message[256] = {};      // libpng's error message, for the caller
};

void on_png_error(png_structp png, png_const_charp message) {
  auto* io = static_cast<PngIo*>(png_get_error_ptr(png));
  std::snprintf(io->message, sizeof io->message, "%s", message);
  png_longjmp(png, 1);
}

// Warnings (an odd ICC profile, a bad CRC in an ancillary chunk) do not fail the read, and libpng
// would otherwise print them to stderr behind the logger's back.
void on_png_warning(png_structp, png_const_charp) {}

void on_png_read(png_structp png, png_bytep dst, std::size_t n) {
  auto* io = static_cast<PngIo*>(png_get_io_ptr(png));
  if (n > io->size - io->offset) png_error(png, "unexpected end of data (file truncated)");
  std::memcpy(dst, io->data + io->offset, n);
  io->offset += n;
}

void on_png_write(png_structp png, png_bytep src, std::size_t n) {
  auto* io = static_cast<PngIo*>(png_get_io_ptr(png));
  bool ok = true;
  try {
    io->out->append(reinterpret_cast<const char*>(src), n);
  } catch (...) {
    ok = false;
  }
  // Outside the catch block, so the exception object is gone before we longjmp.
  if (!ok) png_error(png, "out of memory while encoding");
}

void on_png_flush(png_structp) {}

// Owns a libpng read (kWrite false) or write struct and its info struct.
template <bool kWrite>
class PngHandle {
 public:
  explicit PngHandle(PngIo* io)
      : png_(kWrite ? png_create_write_struct(PNG_LIBPNG_VER_STRING, io, on_png_error, on_png_warning)
                    : png_create_read_struct(PNG_LIBPNG_VER_STRING, io, on_png_error, on_png_warning)),
        info_(png_ ? png_create_info_struct(png_) : nullptr) {}
  ~PngHandle() {
    if (!png_) return;
    if constexpr (kWrite) {
      png_destroy_write_struct(&png_, info_ ? &info_ : nullptr);
    } else {
      png_destroy_read_struct(&png_, info_ ? &info_ : nullptr, nullptr);
    }
  }
  PngHandle(const PngHandle&) = delete;
  PngHandle& operator=(const PngHandle&) = delete;

  bool ok() const { return png_ && info_; }
  png_structp png() const { return png_; }
  png_infop info() const { return info_; }

 private:
  png_structp png_;
  png_infop info_;
};
using PngReader = PngHandle<false>;
using PngWriter = PngHandle<true>;

// What guarded_png_read_header learned, after libpng's transformations to 8- or 16-bit RGB.
struct PngHeader {
  png_uint_32 width = 0, height = 0;
  int bit_depth = 0;
  int channels = 0;
  std::size_t row_bytes = 0;
  bool has_srgb = false;
  bool has_gamma = false;
  png_fixed_point gamma = 0;  // file gamma times 100000
};

bool guarded_png_read_header(png_structp png, png_infop info, PngIo* io, PngHeader* header) {
  if (setjmp(png_jmpbuf(png))) return false;
  // libpng rejects larger IHDRs itself, before anything is allocated.
  png_set_user_limits(png, kMaxImageSide, kMaxImageSide);
  png_set_chunk_malloc_max(png, 8u << 20);  // bounds text and ICC chunks
  png_set_read_fn(png, io, on_png_read);
  png_read_info(png, info);
  header->has_srgb = png_get_valid(png, info, PNG_INFO_sRGB) != 0;
  header->has_gamma = png_get_gAMA_fixed(png, info, &header->gamma) != 0;
  // Palette to RGB, grey below 8 bits to 8, tRNS to alpha; then alpha dropped and grey widened,
  // so every file arrives as 3 samples of 8 or 16 bits. 16-bit samples stay big-endian.
  png_set_expand(png);
  png_set_strip_alpha(png);
  png_set_gray_to_rgb(png);
  png_set_interlace_handling(png);
  png_read_update_info(png, info);
  header->width = png_get_image_width(png, info);
  header->height = png_get_image_height(png, info);
  header->bit_depth = png_get_bit_depth(png, info);
  header->channels = png_get_channels(png, info);
  header->row_bytes = png_get_rowbytes(png, info);
  return true;
}

bool guarded_png_read_pixels(png_structp png, png_bytepp rows) {
  if (setjmp(png_jmpbuf(png))) return false;
  png_read_image(png, rows);
  png_read_end(png, nullptr);  // checks the remaining chunks through IEND: a cut file fails here
  return true;
}

bool guarded_png_write(png_structp png, png_infop info, PngIo* io, png_uint_32 width, png_uint_32 height, int bit_depth,
                       png_bytepp rows) {
  if (setjmp(png_jmpbuf(png))) return false;
  png_set_write_fn(png, io, on_png_write, on_png_flush);
  png_set_IHDR(png, info, width, height, bit_depth, PNG_COLOR_TYPE_RGB, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  // The sRGB chunk, plus gAMA and cHRM for readers that predate it (PNG spec, section 11.3.3.5).
  png_set_sRGB_gAMA_and_cHRM(png, info, PNG_sRGB_INTENT_PERCEPTUAL);
  png_write_info(png, info);
  png_write_image(png, rows);
  png_write_end(png, nullptr);
  return true;
}

std::optional<std::string> encode_png(const ImageRGBf& img, int bit_depth, std::string& problem) {
  const std::uint32_t max_code = bit_depth == 16 ? 65535 : 255;
  const std::size_t bytes_per_sample = bit_depth == 16 ? 2 : 1;
  const std::size_t row_bytes = std::size_t{img.width} * 3 * bytes_per_sample;
  std::vector<unsigned char> pixels(row_bytes * img.height);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    const std::uint32_t code = quantize(img.rgb[i], max_code);
    if (bytes_per_sample == 1) {
      pixels[i] = static_cast<unsigned char>(code);
    } else {  // PNG samples are big-endian
      pixels[2 * i] = static_cast<unsigned char>(code >> 8);
      pixels[2 * i + 1] = static_cast<unsigned char>(code & 0xff);
    }
  }
  std::vector<png_bytep> rows(img.height);
  for (std::uint32_t y = 0; y < img.height; ++y) rows[y] = pixels.data() + y * row_bytes;

  std::string out;
  PngIo io;
  io.out = &out;
  PngWriter writer(&io);
  if (!writer.ok()) {
    problem = "PNG: cannot allocate the libpng encoder";
    return std::nullopt;
  }
  if (!guarded_png_write(writer.png(), writer.info(), &io, img.width, img.height, bit_depth, rows.data())) {
    problem = fmt::format("PNG encoding failed: {}", io.message);
    return std::nullopt;
  }
  return out;
}

std::optional<ImageRGBf> decode_png(std::string_view bytes, std::string& problem) {
  constexpr std::size_t kSignatureSize = 8;
  if (bytes.size() < kSignatureSize ||
      png_sig_cmp(reinterpret_cast<png_const_bytep>(bytes.data()), 0, kSignatureSize) != 0) {
    problem = "not a PNG file: the 8-byte PNG signature is missing";
    return std::nullopt;
  }
  PngIo io;
  io.data = reinterpret_cast<const unsigned char*>(bytes.data());
  io.size = bytes.size();
  PngReader reader(&io);
  if (!reader.ok()) {
    problem = "PNG: cannot allocate the libpng decoder";
    return std::nullopt;
  }
  PngHeader header;
  if (!guarded_png_read_header(reader.png(), reader.info(), &io, &header)) {
    problem = fmt::format("invalid PNG: {}", io.message);
    return std::nullopt;
  }
  // libpng enforces the user limits; checking again keeps this function honest on its own.
  if (header.width == 0 || header.height == 0 || header.width > kMaxImageSide || header.height > kMaxImageSide) {
    problem =
        fmt::format("PNG size {}x{} is outside the supported range 1..{}", header.width, header.height, kMaxImageSide);
    return std::nullopt;
  }
  const std::size_t bytes_per_sample = header.bit_depth == 16 ? 2 : 1;
  if (header.channels != 3 || (header.bit_depth != 8 && header.bit_depth != 16) ||
      header.row_bytes != std::size_t{header.width} * 3 * bytes_per_sample) {
    problem = fmt::format("PNG: unexpected layout after conversion ({} channels of {} bits)", header.channels,
                          header.bit_depth);
    return std::nullopt;
  }

  std::vector<unsigned char> pixels(header.row_bytes * header.height);
  std::vector<png_bytep> rows(header.height);
  for (png_uint_32 y = 0; y < header.height; ++y) rows[y] = pixels.data() + y * header.row_bytes;
  if (!guarded_png_read_pixels(reader.png(), rows.data())) {
    problem = fmt::format("invalid PNG: {}", io.message);
    return std::nullopt;
  }

  Transfer transfer;  // sRGB unless the file says otherwise
  if (!header.has_srgb && header.has_gamma && header.gamma > 0) {
    // Writers that mean sRGB store gAMA 1/2.2 (45455) or near it (Adobe's 0.45); like libpng,
    // treat anything within 5% as sRGB. Anything else, notably 1.0 for linear data, is a power law.
    constexpr double kSrgbGamma = 45455.0;
    if (std::abs(header.gamma / kSrgbGamma - 1.0) > 0.05) {
      transfer.srgb = false;
      transfer.exponent = 100000.0 / header.gamma;
    }
  }
  const std::vector<float> table = decode_table(bytes_per_sample == 2 ? 65535 : 255, transfer);
  ImageRGBf img(header.width, header.height);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    const std::uint32_t code =
        bytes_per_sample == 1 ? pixels[i] : (std::uint32_t{pixels[2 * i]} << 8) | pixels[2 * i + 1];
    img.rgb[i] = table[code];
  }
  return img;
}

std::string_view format_name(ImageFormat format) { return format_info(format).label; }

constexpr std::array<FormatInfo, 3> kFormats = {{
    {ImageFormat::kPng, "png", ".png", "image/png", "PNG"},
    {ImageFormat::kPpm, "ppm", ".ppm", "image/x-portable-pixmap", "PPM"},
    {ImageFormat::kPfm, "pfm", ".pfm", "image/x-portable-floatmap", "PFM"},
}};

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

float linear_to_srgb(float linear) { return static_cast<float>(srgb_encode(linear)); }
float srgb_to_linear(float encoded) { return static_cast<float>(srgb_decode(encoded)); }

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
  switch (format) {
    case ImageFormat::kPpm:
      return encode_ppm(img);
    case ImageFormat::kPfm:
      return encode_pfm(img);
    case ImageFormat::kPng:
      break;
  }
  if (opts.png_bit_depth != 8 && opts.png_bit_depth != 16) {
    return util::Error(fmt::format("unsupported bit depth {} (8 or 16)", opts.png_bit_depth), "", "PNG");
  }
  std::optional<std::string> out = encode_png(img, opts.png_bit_depth, problem);
  if (!out) return util::Error(problem);
  return std::move(*out);
}

util::Result<ImageRGBf> decode_image(ImageFormat format, std::string_view bytes, std::string_view name) {
  std::string problem;
  std::optional<ImageRGBf> img;
  switch (format) {
    case ImageFormat::kPng:
      img = decode_png(bytes, problem);
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
