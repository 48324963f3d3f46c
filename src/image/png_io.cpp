// PNG through libpng's classic API (the PNG row of image_io.h).
#include <png.h>

#include <cmath>
#include <csetjmp>
#include <cstdio>
#include <cstring>
#include <vector>

#include <fmt/format.h>

#include "image/codec.h"

namespace dtraced::image::detail {
namespace {

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

}  // namespace

std::optional<std::string> encode_png(const ImageRGBf& img, int bit_depth, const DisplayTransform& display,
                                      std::string& problem) {
  const std::uint32_t max_code = bit_depth == 16 ? 65535 : 255;
  const std::size_t bytes_per_sample = bit_depth == 16 ? 2 : 1;
  const std::size_t row_bytes = std::size_t{img.width} * 3 * bytes_per_sample;
  std::vector<unsigned char> pixels(row_bytes * img.height);
  for (std::size_t i = 0; i < img.rgb.size(); ++i) {
    const std::uint32_t code = encode_sample(img.rgb[i], display, max_code);
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
    problem = "cannot allocate the libpng encoder";
    return std::nullopt;
  }
  if (!guarded_png_write(writer.png(), writer.info(), &io, img.width, img.height, bit_depth, rows.data())) {
    problem = fmt::format("encoding failed: {}", io.message);
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

}  // namespace dtraced::image::detail
