#include "image/gif_io.h"

#include <gif_lib.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <new>
#include <string>

#include <fmt/format.h>

#include "image/codec.h"

namespace dtraced::image {
namespace {

constexpr std::size_t kMaxPalette = 256;

struct Rgb8 {
  std::uint8_t r = 0, g = 0, b = 0;
};
std::uint32_t pack(Rgb8 c) { return (std::uint32_t{c.r} << 16) | (std::uint32_t{c.g} << 8) | c.b; }
Rgb8 unpack(std::uint32_t v) {
  return {static_cast<std::uint8_t>(v >> 16), static_cast<std::uint8_t>(v >> 8), static_cast<std::uint8_t>(v)};
}
int channel(std::uint32_t packed, int c) { return static_cast<int>((packed >> (16 - 8 * c)) & 0xff); }

// One distinct colour of a frame and how many pixels have it.
struct ColourCount {
  std::uint32_t colour;
  std::uint64_t count;
};

// A median-cut box: a range of the colour list, with its extent.
struct Box {
  std::size_t begin, end;
  int widest_channel = 0;
  int extent = 0;  // max - min of the widest channel
  std::uint64_t pixels = 0;
};

Box make_box(const std::vector<ColourCount>& colours, std::size_t begin, std::size_t end) {
  Box box{begin, end};
  std::array<int, 3> lo{255, 255, 255}, hi{0, 0, 0};
  for (std::size_t i = begin; i < end; ++i) {
    box.pixels += colours[i].count;
    for (int c = 0; c < 3; ++c) {
      lo[c] = std::min(lo[c], channel(colours[i].colour, c));
      hi[c] = std::max(hi[c], channel(colours[i].colour, c));
    }
  }
  for (int c = 0; c < 3; ++c) {
    if (hi[c] - lo[c] > box.extent) {
      box.extent = hi[c] - lo[c];
      box.widest_channel = c;
    }
  }
  return box;
}

// Heckbert's median cut: split the box whose error is likely largest (pixels x extent^2) at the
// pixel-weighted median of its widest channel, until there are 256 boxes or none can split.
std::vector<Rgb8> median_cut(std::vector<ColourCount>& colours) {
  std::vector<Box> boxes{make_box(colours, 0, colours.size())};
  while (boxes.size() < kMaxPalette) {
    auto score = [](const Box& b) { return b.extent == 0 ? 0.0 : double(b.pixels) * b.extent * b.extent; };
    const auto it =
        std::max_element(boxes.begin(), boxes.end(), [&](const Box& a, const Box& b) { return score(a) < score(b); });
    if (score(*it) == 0.0) break;
    const Box box = *it;
    const int c = box.widest_channel;
    std::sort(colours.begin() + box.begin, colours.begin() + box.end, [c](const ColourCount& a, const ColourCount& b) {
      return channel(a.colour, c) != channel(b.colour, c) ? channel(a.colour, c) < channel(b.colour, c)
                                                          : a.colour < b.colour;
    });
    std::uint64_t seen = 0;
    std::size_t split = box.begin + 1;
    for (; split < box.end - 1; ++split) {
      seen += colours[split - 1].count;
      if (2 * seen >= box.pixels) break;
    }
    *it = make_box(colours, box.begin, split);
    boxes.push_back(make_box(colours, split, box.end));
  }
  std::vector<Rgb8> palette;
  for (const Box& box : boxes) {
    std::array<double, 3> sum{};
    for (std::size_t i = box.begin; i < box.end; ++i) {
      for (int c = 0; c < 3; ++c) sum[c] += double(channel(colours[i].colour, c)) * double(colours[i].count);
    }
    auto mean = [&](int c) { return static_cast<std::uint8_t>(std::lround(sum[c] / double(box.pixels))); };
    palette.push_back({mean(0), mean(1), mean(2)});
  }
  return palette;
}

// The frame's palette: its exact colours when there are at most 256, else a median cut.
std::vector<Rgb8> make_palette(const std::vector<std::uint32_t>& pixels) {
  std::vector<std::uint32_t> sorted = pixels;
  std::sort(sorted.begin(), sorted.end());
  std::vector<ColourCount> colours;
  for (std::uint32_t v : sorted) {
    if (colours.empty() || colours.back().colour != v) colours.push_back({v, 0});
    ++colours.back().count;
  }
  if (colours.size() <= kMaxPalette) {
    std::vector<Rgb8> palette;
    for (const ColourCount& c : colours) palette.push_back(unpack(c.colour));
    return palette;
  }
  return median_cut(colours);
}

// Nearest palette entry (squared distance in sRGB codes), behind a direct-mapped cache: a frame
// repeats few distinct colours, and dithering revisits the same ones.
class NearestColour {
 public:
  explicit NearestColour(const std::vector<Rgb8>& palette) : palette_(palette), cache_(kCacheSize, kEmpty) {}

  std::uint8_t operator()(std::uint32_t colour) {
    std::uint64_t& slot = cache_[(colour * 2654435761u) >> (32 - kCacheBits)];
    if ((slot >> 8) == colour) return static_cast<std::uint8_t>(slot & 0xff);
    const Rgb8 c = unpack(colour);
    int best = 0;
    int best_d = 1 << 30;
    for (std::size_t i = 0; i < palette_.size(); ++i) {
      const int dr = int(c.r) - palette_[i].r, dg = int(c.g) - palette_[i].g, db = int(c.b) - palette_[i].b;
      const int d = dr * dr + dg * dg + db * db;
      if (d < best_d) {
        best_d = d;
        best = static_cast<int>(i);
      }
    }
    slot = (std::uint64_t{colour} << 8) | static_cast<std::uint64_t>(best);
    return static_cast<std::uint8_t>(best);
  }

 private:
  static constexpr int kCacheBits = 16;
  static constexpr std::size_t kCacheSize = std::size_t{1} << kCacheBits;
  static constexpr std::uint64_t kEmpty = ~std::uint64_t{0};  // colour field > 24 bits: never matches
  const std::vector<Rgb8>& palette_;
  std::vector<std::uint64_t> cache_;
};

// Palette indices for every pixel, with Floyd-Steinberg error diffusion when asked. The error is
// carried in floats over two rows, so a row costs O(width) memory.
std::vector<GifPixelType> index_pixels(const std::vector<std::uint32_t>& pixels, std::uint32_t width,
                                       std::uint32_t height, const std::vector<Rgb8>& palette, bool dither) {
  NearestColour nearest(palette);
  std::vector<GifPixelType> out(pixels.size());
  if (!dither) {
    for (std::size_t i = 0; i < pixels.size(); ++i) out[i] = nearest(pixels[i]);
    return out;
  }
  // Two rows of error, with a pixel of margin on both sides so the kernel needs no bounds checks.
  std::vector<float> here((width + 2) * 3, 0.0f), below((width + 2) * 3, 0.0f);
  for (std::uint32_t y = 0; y < height; ++y) {
    for (std::uint32_t x = 0; x < width; ++x) {
      const std::size_t i = std::size_t{y} * width + x;
      std::array<float, 3> want{};
      Rgb8 q;
      for (int c = 0; c < 3; ++c)
        want[c] = std::clamp(float(channel(pixels[i], c)) + here[(x + 1) * 3 + c], 0.f, 255.f);
      q = {static_cast<std::uint8_t>(std::lround(want[0])), static_cast<std::uint8_t>(std::lround(want[1])),
           static_cast<std::uint8_t>(std::lround(want[2]))};
      out[i] = nearest(pack(q));
      const Rgb8 got = palette[out[i]];
      const std::array<float, 3> err{want[0] - got.r, want[1] - got.g, want[2] - got.b};
      for (int c = 0; c < 3; ++c) {
        here[(x + 2) * 3 + c] += err[c] * (7.0f / 16);
        below[x * 3 + c] += err[c] * (3.0f / 16);
        below[(x + 1) * 3 + c] += err[c] * (5.0f / 16);
        below[(x + 2) * 3 + c] += err[c] * (1.0f / 16);
      }
    }
    std::swap(here, below);
    std::fill(below.begin(), below.end(), 0.0f);
  }
  return out;
}

std::string gif_problem(std::string_view what, int code) {
  return fmt::format("GIF encoding failed ({}): {}", what, GifErrorString(code) ? GifErrorString(code) : "unknown");
}

}  // namespace

std::uint16_t gif_delay_centiseconds(double fps) {
  if (!(fps > 0.0)) return 65535;
  const double cs = std::round(100.0 / fps);
  return static_cast<std::uint16_t>(std::clamp(cs, 2.0, 65535.0));
}

struct GifEncoder::State {
  std::uint32_t width = 0, height = 0;
  GifOptions options;
  std::vector<std::uint8_t> out;
  GifFileType* gif = nullptr;
  std::uint32_t frames = 0;
  bool spent = false;        // finished or failed: nothing more can be added
  bool out_of_room = false;  // the output callback refused bytes

  State() = default;
  State(const State&) = delete;
  State& operator=(const State&) = delete;
  ~State() {
    if (gif) EGifCloseFile(gif, nullptr);
  }

  // giflib's output callback: append to `out`, within kMaxGifBytes; a short count is an error.
  static int write(GifFileType* gif, const GifByteType* data, int n) {
    auto* self = static_cast<State*>(gif->UserData);
    if (n < 0 || self->out.size() + std::size_t(n) > kMaxGifBytes) {
      self->out_of_room = true;
      return 0;
    }
    try {
      self->out.insert(self->out.end(), data, data + n);
    } catch (const std::bad_alloc&) {
      self->out_of_room = true;
      return 0;
    }
    return n;
  }

  util::Error fail(std::string_view what) {
    spent = true;
    const int code = gif ? gif->Error : 0;
    if (out_of_room) return util::Error(fmt::format("GIF larger than {} bytes or out of memory", kMaxGifBytes));
    return util::Error(gif_problem(what, code));
  }
};

GifEncoder::GifEncoder(std::unique_ptr<State> state) : state_(std::move(state)) {}
GifEncoder::GifEncoder(GifEncoder&&) noexcept = default;
GifEncoder& GifEncoder::operator=(GifEncoder&&) noexcept = default;
GifEncoder::~GifEncoder() = default;

std::uint32_t GifEncoder::frame_count() const { return state_ ? state_->frames : 0; }

util::Result<GifEncoder> GifEncoder::create(std::uint32_t width, std::uint32_t height, const GifOptions& options) {
  if (width == 0 || height == 0 || width > kMaxImageSide || height > kMaxImageSide) {
    return util::Error(fmt::format("GIF size {}x{} is outside 1..{}", width, height, kMaxImageSide));
  }
  if (!(options.fps > 0.0) || !(options.fps <= 1000.0)) {
    return util::Error(fmt::format("GIF fps {} is outside (0, 1000]", options.fps));
  }
  auto state = std::make_unique<State>();
  state->width = width;
  state->height = height;
  state->options = options;
  int error = 0;
  state->gif = EGifOpen(state.get(), &State::write, &error);
  if (!state->gif) return util::Error(gif_problem("open", error));
  GifFileType* gif = state->gif;
  // GIF89a: the graphics control (delay) and application (loop) extensions need it.
  EGifSetGifVersion(gif, true);
  if (EGifPutScreenDesc(gif, int(width), int(height), 8, 0, nullptr) == GIF_ERROR) return state->fail("screen");
  // NETSCAPE2.0 application extension: sub-block 1, loop count 0 = forever (little-endian).
  static constexpr GifByteType kNetscape[] = {'N', 'E', 'T', 'S', 'C', 'A', 'P', 'E', '2', '.', '0'};
  static constexpr GifByteType kLoopForever[] = {1, 0, 0};
  if (EGifPutExtensionLeader(gif, APPLICATION_EXT_FUNC_CODE) == GIF_ERROR ||
      EGifPutExtensionBlock(gif, sizeof kNetscape, kNetscape) == GIF_ERROR ||
      EGifPutExtensionBlock(gif, sizeof kLoopForever, kLoopForever) == GIF_ERROR ||
      EGifPutExtensionTrailer(gif) == GIF_ERROR) {
    return state->fail("loop extension");
  }
  return GifEncoder(std::move(state));
}

util::Status GifEncoder::add_frame(const ImageRGBf& linear) {
  if (!state_ || state_->spent) return util::Error("GIF: the encoder is finished or has failed");
  State& s = *state_;
  if (!linear.is_consistent() || linear.width != s.width || linear.height != s.height) {
    return util::Error(fmt::format("GIF frame {} is {}x{} ({} floats); every frame must be {}x{}", s.frames,
                                   linear.width, linear.height, linear.rgb.size(), s.width, s.height));
  }
  if (s.frames >= kMaxGifFrames) return util::Error(fmt::format("GIF: more than {} frames", kMaxGifFrames));

  std::vector<std::uint32_t> pixels(std::size_t{s.width} * s.height);
  for (std::size_t i = 0; i < pixels.size(); ++i) {
    const float* p = linear.rgb.data() + 3 * i;
    auto code = [&](int c) { return static_cast<std::uint8_t>(detail::encode_sample(p[c], s.options.display, 255)); };
    pixels[i] = pack({code(0), code(1), code(2)});
  }
  const std::vector<Rgb8> palette = make_palette(pixels);
  std::vector<GifPixelType> indices = index_pixels(pixels, s.width, s.height, palette, s.options.dither);

  // The colour table's size is a power of two from 2 to 256; unused entries stay black.
  std::size_t table_size = 2;
  while (table_size < palette.size()) table_size *= 2;
  std::vector<GifColorType> table(table_size, GifColorType{0, 0, 0});
  for (std::size_t i = 0; i < palette.size(); ++i) table[i] = {palette[i].r, palette[i].g, palette[i].b};
  std::unique_ptr<ColorMapObject, void (*)(ColorMapObject*)> map(GifMakeMapObject(int(table_size), table.data()),
                                                                 GifFreeMapObject);
  if (!map) return s.fail("colour table");

  GraphicsControlBlock gcb{};
  gcb.DisposalMode = DISPOSE_DO_NOT;  // every frame covers the whole screen
  gcb.UserInputFlag = false;
  gcb.DelayTime = gif_delay_centiseconds(s.options.fps);
  gcb.TransparentColor = NO_TRANSPARENT_COLOR;
  GifByteType extension[4];
  const std::size_t length = EGifGCBToExtension(&gcb, extension);
  GifFileType* gif = s.gif;
  if (EGifPutExtension(gif, GRAPHICS_EXT_FUNC_CODE, int(length), extension) == GIF_ERROR) return s.fail("delay");
  if (EGifPutImageDesc(gif, 0, 0, int(s.width), int(s.height), false, map.get()) == GIF_ERROR) {
    return s.fail("image descriptor");
  }
  for (std::uint32_t y = 0; y < s.height; ++y) {
    if (EGifPutLine(gif, indices.data() + std::size_t{y} * s.width, int(s.width)) == GIF_ERROR) {
      return s.fail("pixels");
    }
  }
  ++s.frames;
  return {};
}

util::Result<std::vector<std::uint8_t>> GifEncoder::finish() {
  if (!state_ || state_->spent) return util::Error("GIF: the encoder is finished or has failed");
  State& s = *state_;
  if (s.frames == 0) return util::Error("GIF: no frames were added");
  int error = 0;
  const int closed = EGifCloseFile(s.gif, &error);  // writes the trailer and frees, even on failure
  s.gif = nullptr;
  s.spent = true;
  if (closed == GIF_ERROR) {
    if (s.out_of_room) return util::Error(fmt::format("GIF larger than {} bytes or out of memory", kMaxGifBytes));
    return util::Error(gif_problem("trailer", error));
  }
  return std::move(s.out);
}

namespace detail {

std::optional<std::string> encode_gif(const ImageRGBf& img, const DisplayTransform& display, std::string& problem) {
  GifOptions options;
  options.display = display;
  util::Result<GifEncoder> encoder = GifEncoder::create(img.width, img.height, options);
  if (!encoder) {
    problem = encoder.error().message;
    return std::nullopt;
  }
  util::Status added = encoder->add_frame(img);
  if (!added) {
    problem = added.error().message;
    return std::nullopt;
  }
  util::Result<std::vector<std::uint8_t>> bytes = encoder->finish();
  if (!bytes) {
    problem = bytes.error().message;
    return std::nullopt;
  }
  return std::string(bytes->begin(), bytes->end());
}

}  // namespace detail
}  // namespace dtraced::image
