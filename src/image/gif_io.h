// dtraced::image GIF: animated (or single-frame) GIF files encoded in memory with giflib.
//
// Owns: the palette of each frame (the exact colours when a frame has at most 256, else a median
// cut of its colours, as a local colour table), optional Floyd-Steinberg dithering, the frame delay
// derived from fps, and the NETSCAPE2.0 extension that loops the animation forever.
//
// Frames arrive one at a time and are compressed at once: an encoder holds the compressed bytes
// so far, never the float frames of a long animation. Frames are display-encoded (display.h, then
// sRGB to 8 bits) exactly as PNG and PPM encode them, then quantised to the palette.
//
// Thread safety: a GifEncoder is a plain object with no shared state; one thread at a time uses a
// given encoder, different encoders are independent.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "image/display.h"
#include "image/image.h"
#include "util/result.h"

namespace dtraced::image {

// Sides are at most kMaxImageSide (image.h), well inside the format's 16-bit fields.
inline constexpr std::uint32_t kMaxGifFrames = 100'000;  // one frame range (scene::kMaxFrames)
// Compressed output larger than this is refused rather than grown further (4 GiB).
inline constexpr std::uint64_t kMaxGifBytes = std::uint64_t{1} << 32;

struct GifOptions {
  double fps = 24;  // (0, 1000]; each frame shows for round(100 / fps) centiseconds, at least 2
  bool dither = false;
  DisplayTransform display{};
};

// The delay of every frame, in centiseconds: round(100 / fps), at least 2 (browsers show faster
// frames at 10 cs), at most 65535 (the field's size).
std::uint16_t gif_delay_centiseconds(double fps);

class GifEncoder {
 public:
  // Fails (naming the field) for a zero or too large side, or an fps outside (0, 1000].
  static util::Result<GifEncoder> create(std::uint32_t width, std::uint32_t height, const GifOptions& options);

  GifEncoder(GifEncoder&&) noexcept;
  GifEncoder& operator=(GifEncoder&&) noexcept;
  ~GifEncoder();

  // Appends one frame of linear RGB. It must have the encoder's size; more than kMaxGifFrames
  // frames, a frame after finish() or after a failure are errors.
  util::Status add_frame(const ImageRGBf& linear);

  // The whole file. At least one frame must have been added; the encoder is spent afterwards.
  util::Result<std::vector<std::uint8_t>> finish();

  std::uint32_t frame_count() const;

 private:
  struct State;
  explicit GifEncoder(std::unique_ptr<State> state);
  std::unique_ptr<State> state_;
};

}  // namespace dtraced::image
