// OpenEXR through the C++ API (the EXR row of image_io.h), entirely in memory: the streams below
// stand in for files, so a server can answer with an EXR without touching the disk.
//
// OpenEXR reports errors by exceptions; they are caught here and become `problem`. Files are read
// with numThreads 0 (no global thread pool), and a hostile header's data window and tile size are
// checked by a small scan of the header before OpenEXR allocates anything from them.
#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfIO.h>
#include <ImfInputFile.h>
#include <ImfOutputFile.h>
#include <half.h>

#include <cstring>
#include <exception>
#include <string>
#include <vector>

#include <fmt/format.h>

#include "image/codec.h"

namespace dtraced::image::detail {
namespace {

// Writes into a string; OpenEXR seeks back to fill in the offset table, so writes may overwrite.
class MemoryOStream : public Imf::OStream {
 public:
  explicit MemoryOStream(std::string& out) : Imf::OStream("EXR (in memory)"), out_(out) {}
  void write(const char c[], int n) override {
    if (n <= 0) return;
    if (pos_ + std::size_t(n) > out_.size()) out_.resize(pos_ + std::size_t(n));
    std::memcpy(out_.data() + pos_, c, std::size_t(n));
    pos_ += std::size_t(n);
  }
  std::uint64_t tellp() override { return pos_; }
  void seekp(std::uint64_t pos) override { pos_ = pos; }

 private:
  std::string& out_;
  std::size_t pos_ = 0;
};

// Reads from bytes already in memory (and already bounded by kMaxImageFileBytes).
class MemoryIStream : public Imf::IStream {
 public:
  explicit MemoryIStream(std::string_view bytes) : Imf::IStream("EXR"), bytes_(bytes) {}
  bool read(char c[], int n) override {
    if (n < 0 || pos_ > bytes_.size() || std::size_t(n) > bytes_.size() - pos_) {
      throw std::runtime_error("unexpected end of data (file truncated)");
    }
    std::memcpy(c, bytes_.data() + pos_, std::size_t(n));
    pos_ += std::size_t(n);
    return pos_ < bytes_.size();
  }
  std::uint64_t tellg() override { return pos_; }
  void seekg(std::uint64_t pos) override { pos_ = pos; }
  void clear() override {}

 private:
  std::string_view bytes_;
  std::uint64_t pos_ = 0;
};

std::int32_t read_le32(const char* p) {
  std::uint32_t v = 0;
  for (int i = 3; i >= 0; --i) v = (v << 8) | static_cast<unsigned char>(p[i]);
  return static_cast<std::int32_t>(v);
}

// What check_header reads from the first header before OpenEXR sees the file.
struct HeaderScan {
  std::int64_t x0 = 0, y0 = 0, x1 = -1, y1 = -1;  // dataWindow
  bool has_window = false;
  std::uint32_t tile_x = 0, tile_y = 0;  // tiles (tiledesc), 0 when the file has scanlines
};

// Bounds what OpenEXR would allocate from a header alone: it sizes its chunk offset tables from the
// data window and the tile size, so a small hostile file could ask for gigabytes. Walks the first
// header's attribute list (name\0 type\0 size value) for dataWindow and tiles; refuses deep and
// multi-part files (never written by us, and each part would have tables of its own). Returns false
// with `problem` set for a malformed header, a window outside 1..kMaxImageSide, or too many tiles.
bool check_header(std::string_view bytes, std::string& problem) {
  if (bytes.size() < 8 || read_le32(bytes.data()) != 20000630) {
    problem = "not an OpenEXR file: the magic number 76 2f 31 01 is missing";
    return false;
  }
  constexpr std::int32_t kDeep = 0x800, kMultiPart = 0x1000;
  if (read_le32(bytes.data() + 4) & (kDeep | kMultiPart)) {
    problem = "deep and multi-part OpenEXR files are not supported (only one part of flat R, G, B)";
    return false;
  }
  HeaderScan scan;
  std::size_t pos = 8;
  auto read_name = [&](std::string_view& name) {
    const std::size_t end = bytes.find('\0', pos);
    if (end == std::string_view::npos || end - pos > 255) return false;
    name = bytes.substr(pos, end - pos);
    pos = end + 1;
    return true;
  };
  for (;;) {
    std::string_view name, type;
    if (!read_name(name)) {
      problem = "header: truncated or malformed attribute list";
      return false;
    }
    if (name.empty()) break;  // end of the header
    if (!read_name(type) || bytes.size() - pos < 4) {
      problem = "header: truncated or malformed attribute list";
      return false;
    }
    const std::int32_t size = read_le32(bytes.data() + pos);
    pos += 4;
    if (size < 0 || std::size_t(size) > bytes.size() - pos) {
      problem = fmt::format("header: attribute '{}' of {} bytes runs past the end of the file", name, size);
      return false;
    }
    const char* value = bytes.data() + pos;
    if (name == "dataWindow" && type == "box2i" && size == 16) {
      scan.x0 = read_le32(value);
      scan.y0 = read_le32(value + 4);
      scan.x1 = read_le32(value + 8);
      scan.y1 = read_le32(value + 12);
      scan.has_window = true;
    } else if (name == "tiles" && type == "tiledesc" && size == 9) {
      scan.tile_x = static_cast<std::uint32_t>(read_le32(value));
      scan.tile_y = static_cast<std::uint32_t>(read_le32(value + 4));
    }
    pos += std::size_t(size);
  }
  const std::int64_t w = scan.x1 - scan.x0 + 1, h = scan.y1 - scan.y0 + 1;
  if (!scan.has_window) {
    problem = "header: no dataWindow attribute";
    return false;
  }
  if (w < 1 || h < 1 || w > kMaxImageSide || h > kMaxImageSide) {
    problem = fmt::format("data window ({}, {})-({}, {}) is {}x{}, outside the supported range 1..{}", scan.x0, scan.y0,
                          scan.x1, scan.y1, w, h, kMaxImageSide);
    return false;
  }
  // Tiles of at least 16x16 on average over a 16384^2 image: 2^20 tiles, 8 MiB of offsets per level.
  constexpr std::int64_t kMaxTiles = std::int64_t{1} << 20;
  if (scan.tile_x != 0 || scan.tile_y != 0) {
    const std::int64_t tx = scan.tile_x, ty = scan.tile_y;
    if (tx < 1 || ty < 1 || ((w + tx - 1) / tx) * ((h + ty - 1) / ty) > kMaxTiles) {
      problem = fmt::format("{}x{} tiles over a {}x{} image: more than {} tiles", tx, ty, w, h, kMaxTiles);
      return false;
    }
  }
  return true;
}

std::string channel_names(const Imf::ChannelList& channels) {
  std::string out;
  for (auto it = channels.begin(); it != channels.end(); ++it) {
    if (!out.empty()) out += ", ";
    out += it.name();
  }
  return out.empty() ? "none" : out;
}

}  // namespace

std::optional<std::string> encode_exr(const ImageRGBf& img, const WriteOptions& opts, std::string& problem) {
  const std::size_t pixels = std::size_t{img.width} * img.height;
  if (!opts.sample_counts.empty() && opts.sample_counts.size() != pixels) {
    problem = fmt::format("{} sample counts for a {}x{} image ({} pixels)", opts.sample_counts.size(), img.width,
                          img.height, pixels);
    return std::nullopt;
  }
  std::string out;
  try {
    Imf::Header header(static_cast<int>(img.width), static_cast<int>(img.height));
    header.compression() = Imf::ZIP_COMPRESSION;
    const Imf::PixelType type = opts.exr_float ? Imf::FLOAT : Imf::HALF;
    Imf::FrameBuffer frame;
    // OpenEXR converts types when reading but not when writing: a half file needs half slices,
    // converted here (Imath rounds to nearest). OpenEXR only reads from the slices when writing,
    // hence the const_casts.
    std::vector<Imath::half> halves;
    char* base = reinterpret_cast<char*>(const_cast<float*>(img.rgb.data()));
    std::size_t sample = sizeof(float);
    if (!opts.exr_float) {
      halves.assign(img.rgb.begin(), img.rgb.end());
      base = reinterpret_cast<char*>(halves.data());
      sample = sizeof(Imath::half);
    }
    const std::size_t row = std::size_t{img.width} * 3 * sample;
    const char* names[] = {"R", "G", "B"};
    for (int c = 0; c < 3; ++c) {
      header.channels().insert(names[c], Imf::Channel(type));
      frame.insert(names[c], Imf::Slice(type, base + c * sample, 3 * sample, row));
    }
    if (!opts.sample_counts.empty()) {
      header.channels().insert("spp", Imf::Channel(Imf::FLOAT));
      char* spp = reinterpret_cast<char*>(const_cast<float*>(opts.sample_counts.data()));
      frame.insert("spp", Imf::Slice(Imf::FLOAT, spp, sizeof(float), std::size_t{img.width} * sizeof(float)));
    }
    MemoryOStream stream(out);
    Imf::OutputFile file(stream, header, /* numThreads = */ 0);
    file.setFrameBuffer(frame);
    file.writePixels(static_cast<int>(img.height));
  } catch (const std::exception& e) {  // the file's destructor has run: `out` is complete or discarded
    problem = fmt::format("encoding failed: {}", e.what());
    return std::nullopt;
  }
  return out;
}

std::optional<ImageRGBf> decode_exr(std::string_view bytes, std::string& problem) {
  if (!check_header(bytes, problem)) return std::nullopt;
  try {
    MemoryIStream stream(bytes);
    Imf::InputFile file(stream, /* numThreads = */ 0);
    const Imath::Box2i window = file.header().dataWindow();
    const std::int64_t w = std::int64_t{window.max.x} - window.min.x + 1;
    const std::int64_t h = std::int64_t{window.max.y} - window.min.y + 1;
    if (w < 1 || h < 1 || w > kMaxImageSide || h > kMaxImageSide) {  // the scan above checked it too
      problem = fmt::format("EXR size {}x{} is outside the supported range 1..{}", w, h, kMaxImageSide);
      return std::nullopt;
    }
    const Imf::ChannelList& channels = file.header().channels();
    if (!channels.findChannel("R") || !channels.findChannel("G") || !channels.findChannel("B")) {
      problem = fmt::format("no R, G and B channels (the file has: {})", channel_names(channels));
      return std::nullopt;
    }
    ImageRGBf img(static_cast<std::uint32_t>(w), static_cast<std::uint32_t>(h));
    Imf::FrameBuffer frame;
    const std::size_t row = std::size_t(w) * 3 * sizeof(float);
    const char* names[] = {"R", "G", "B"};
    for (int c = 0; c < 3; ++c) {
      frame.insert(names[c], Imf::Slice::Make(Imf::FLOAT, img.rgb.data() + c, window, 3 * sizeof(float), row));
    }
    file.setFrameBuffer(frame);
    file.readPixels(window.min.y, window.max.y);
    return img;
  } catch (const std::exception& e) {
    problem = fmt::format("invalid OpenEXR file: {}", e.what());
    return std::nullopt;
  }
}

}  // namespace dtraced::image::detail
