// dtraced::image file formats: PNG, binary PPM (P6), PFM, OpenEXR and GIF.
//
// Owns: the mapping between ImageRGBf (linear float RGB) and the on-disk encodings, the one table
// of formats (name, extension, content type), and the sRGB transfer functions used for the 8- and
// 16-bit ones.
//
//   PNG  written as 8- or 16-bit RGB, sRGB-encoded at both depths (so every viewer shows the same
//        picture), with an sRGB chunk plus the gAMA/cHRM fallbacks the PNG spec recommends.
//        Read: any bit depth and colour type (palette, grey, alpha) converted to RGB; alpha is
//        dropped, not composited. Samples are decoded as sRGB unless the file carries a gAMA
//        chunk (and no sRGB chunk) with a gamma more than 5% away from 1/2.2 (libpng's own
//        threshold), in which case that power law is inverted; this reads back the linear
//        16-bit files libpng's simplified API writes.
//        ICC profiles are ignored.
//   PPM  written as P6 with maxval 255, sRGB-encoded. Read: P6 with maxval 1..65535 (two bytes
//        big-endian per sample above 255), '#' comments in the header, sRGB-decoded. A file
//        must hold exactly one image: trailing bytes are an error. ".pnm" (the seed's spelling)
//        names the same format.
//   PFM  written as "PF" (colour), linear float32, little-endian (scale -1), rows bottom to top
//        as the format specifies, so floats round-trip bit for bit. Read: "PF" and greyscale
//        "Pf" (replicated to RGB), either endianness by the sign of the scale; a scale whose
//        magnitude is not 1 multiplies the data, as pbrt does.
//   EXR  (exr_io.cpp) written as linear R, G, B, half by default or float (WriteOptions), ZIP
//        compressed, with an optional "spp" float channel; read: R, G, B of any pixel type.
//   GIF  (gif_io.h) one frame here; an animation goes through GifEncoder. Not read.
//
// Encoding to 8/16 bits: linear -> display transform (display.h; identity: clamp to [0, 1], NaN
// becomes 0) -> sRGB curve -> round to nearest code. PFM and EXR ignore the display transform.
// Readers bound everything by kMaxImageSide, check the file size against the header exactly, and
// name the file and the problem in every error.
//
// Thread safety: every function is stateless and may be called from any thread. libpng is used
// with per-call state only; its error longjmp never crosses a C++ frame with live destructors.
// OpenEXR is used with per-call streams and no global thread pool.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>

#include "image/display.h"
#include "image/image.h"
#include "util/result.h"

namespace dtraced::image {

enum class ImageFormat { kPng, kPpm, kPfm, kExr, kGif };

// Everything the program says about an image format, in one table: every reader, writer,
// HTTP content type, `?format=` value, file-name check and message takes it from here.
struct FormatInfo {
  ImageFormat format;
  std::string_view name;          // "png": the value of `?format=`, lower case
  std::string_view extension;     // ".png"
  std::string_view content_type;  // "image/png"
  std::string_view label;         // "PNG", for messages
};

// Every format, in the order messages list them (PNG, PPM, PFM, EXR, GIF).
std::span<const FormatInfo> image_formats();
const FormatInfo& format_info(ImageFormat format);

// The format named by the path's extension (.png, .ppm or .pnm, .pfm, .exr, .gif, any letter
// case); nullopt for anything else, including no extension.
std::optional<ImageFormat> format_from_path(const std::string& path);
// The format of a `?format=` value ("png", "ppm", "pfm", "exr", "gif": exactly, lower case).
std::optional<ImageFormat> format_from_name(std::string_view name);
// ".png, .ppm, .pfm, .exr or .gif" and "png, ppm, pfm, exr or gif", for messages and help texts.
std::string extension_list();
std::string name_list();

struct WriteOptions {
  int png_bit_depth = 8;  // 8 or 16; PPM and GIF are always 8-bit and PFM always float
  // How PNG, PPM and GIF show the linear pixels; PFM and EXR stay linear.
  DisplayTransform display{};
  // EXR: float32 channels instead of half (which holds 11 significant bits, up to 65504).
  bool exr_float = false;
  // EXR: when not empty, width * height values (row 0 at the top) written as the float channel
  // "spp", the samples each pixel took. Ignored by the other formats. The span must outlive the call.
  std::span<const float> sample_counts{};
};

// Largest file read_image accepts: a 16384^2 colour PFM plus room for headers. Every valid
// image within kMaxImageSide fits; PNG's worst case (stored RGBA16) is smaller.
inline constexpr std::uint64_t kMaxImageFileBytes =
    std::uint64_t{kMaxImageSide} * kMaxImageSide * 3 * sizeof(float) + (std::uint64_t{1} << 20);

// Failures are util::Error{problem, "", file}: to_string() reads "FILE: problem" ("PNG: ..." for
// an image encoded in memory).

// Encodes `img` in `format` to bytes in memory: pure, no I/O, so a server can answer with a PNG
// without touching the disk. Fails for an inconsistent or empty image or an unsupported bit
// depth.
util::Result<std::string> encode_image(ImageFormat format, const ImageRGBf& img, const WriteOptions& opts);

// Decodes `bytes` as `format`. `name` (usually the path) is the error's file.
util::Result<ImageRGBf> decode_image(ImageFormat format, std::string_view bytes, std::string_view name);

// Writes `img` to `path` in the format its extension names, atomically (encoded in memory, then
// util::write_file_atomic): a concurrent reader sees the old file or the new one, never a torn one.
// An unknown extension is an error naming the path and the supported extensions.
util::Status write_image(const std::string& path, const ImageRGBf& img, const WriteOptions& opts = {});

// Reads the image at `path` in the format its extension names (the content must match: a PPM
// named .pfm is an error, not a guess). At most kMaxImageFileBytes are read.
util::Result<ImageRGBf> read_image(const std::string& path);

// The standard piecewise sRGB curves (IEC 61966-2-1), evaluated in double. Inputs outside [0, 1]
// follow the same formulas (linear segment below the knee, power segment above 1); NaN stays NaN.
float linear_to_srgb(float linear);
float srgb_to_linear(float encoded);

}  // namespace dtraced::image
