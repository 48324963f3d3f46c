// OpenEXR through the C++ API (the EXR row of image_io.h), entirely in memory: the streams below
// stand in for files, so a server can answer with an EXR without touching the disk.
//
// OpenEXR reports errors by exceptions; they are caught here and become `problem`. Files are read
// with numThreads 0 (no global thread pool), and a hostile header's data window is checked by a
// small scan of the header before OpenEXR allocates anything from it.
#include <ImfChannelList.h>
#include <ImfFrameBuffer.h>
#include <ImfHeader.h>
#include <ImfIO.h>
#include <ImfInputFile.h>
#include <ImfOutputFile.h>

#include <cstring>
#include <exception>
#include <string>

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

// The first header's dataWindow (a box2i attribute), found by walking the attribute list:
// name\0 type\0 size value. Checked before OpenEXR sizes tables from it. Returns false with
// `problem` set when the header is malformed or the window is outside 1..kMaxImageSide.
bool check_data_window(std::string_view bytes, std::string& problem) {
  if (bytes.size() < 8 || read_le32(bytes.data()) != 20000630) {
    problem = "not an OpenEXR file: the magic number 76 2f 31 01 is missing";
    return false;
  }
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
    if (!read_name(name)) break;
    if (name.empty()) {
      problem = "header: no dataWindow attribute";
      return false;
    }
    if (!read_name(type) || bytes.size() - pos < 4) break;
    const std::int32_t size = read_le32(bytes.data() + pos);
    pos += 4;
    if (size < 0 || std::size_t(size) > bytes.size() - pos) break;
    if (name == "dataWindow" && type == "box2i" && size == 16) {
      const std::int64_t x0 = read_le32(bytes.data() + pos), y0 = read_le32(bytes.data() + pos + 4);
      const std::int64_t x1 = read_le32(bytes.data() + pos + 8), y1 = read_le32(bytes.data() + pos + 12);
      const std::int64_t w = x1 - x0 + 1, h = y1 - y0 + 1;
      if (w < 1 || h < 1 || w > kMaxImageSide || h > kMaxImageSide) {
        problem = fmt::format("data window ({}, {})-({}, {}) is {}x{}, outside the supported range 1..{}", x0, y0, x1,
                              y1, w, h, kMaxImageSide);
        return false;
      }
      return true;
    }
    pos += std::size_t(size);
  }
  problem = "header: truncated or malformed attribute list";
  return false;
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
    // OpenEXR converts the float slices to the file's half channels (rounding to nearest) itself.
    // It only reads from the slices when writing, hence the const_casts.
    char* base = reinterpret_cast<char*>(const_cast<float*>(img.rgb.data()));
    const std::size_t row = std::size_t{img.width} * 3 * sizeof(float);
    const char* names[] = {"R", "G", "B"};
    for (int c = 0; c < 3; ++c) {
      header.channels().insert(names[c], Imf::Channel(type));
      frame.insert(names[c], Imf::Slice(Imf::FLOAT, base + c * sizeof(float), 3 * sizeof(float), row));
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
  if (!check_data_window(bytes, problem)) return std::nullopt;
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
