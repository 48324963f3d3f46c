// dtraced::scene overrides: what a user may set over a scene's `render` block, in one type.
//
// Owns: Overrides, the one set of render-setting overrides that every entry point takes (the
// render verb's flags, a job submission's body, a one-shot collector's flags and config file,
// bench error), and its one apply. Each field is unset unless the user gave it; apply() changes
// exactly the settings that are set. The limits every reader checks a field against are those of
// RenderSettings (description.h) and of tile sizes (tiling.h), so a value valid in one place is
// valid in all.
//
// The CLI flags for these fields come from one helper (cli/overrides_flags.h), the JSON keys from
// one codec (protocol/messages.h): an override added here is added there once, and works
// everywhere.
//
// Plain values, pure functions: thread-safe.
#pragma once

#include <cstdint>
#include <optional>

#include "scene/description.h"
#include "scene/tiling.h"

namespace dtraced::scene {

// PNG bit depths a user may ask for. PPM is always 8-bit and PFM always float.
inline constexpr std::uint32_t kDefaultPngBitDepth = 8;
inline bool is_png_bit_depth(std::uint32_t bits) { return bits == 8 || bits == 16; }

struct Overrides {
  // What the image shows: fields of RenderSettings.
  std::optional<std::uint32_t> width, height;  // [1, kMaxImageSide]
  std::optional<std::uint32_t> samples;        // [1, kMaxSamples]
  std::optional<std::uint32_t> max_depth;      // [0, kMaxDepth]
  std::optional<std::uint64_t> seed;           // [0, kMaxSeed]
  std::optional<std::uint32_t> frame;          // any u32
  std::optional<Color> background;             // each channel finite, >= 0, within the float range
  std::optional<double> error_target;          // [0, kMaxErrorTarget]; 0 turns adaptive sampling off
  std::optional<std::uint32_t> min_samples;    // [1, kMaxSamples]
  std::optional<double> branch_cutoff;         // [kMinBranchCutoff, kMaxBranchCutoff]
  // Animation: the range of a sequence (count() <= kMaxFrames) and the frame rate, (0, kMaxFps].
  std::optional<FrameRange> frames;
  std::optional<double> fps;
  // Display transform of 8- and 16-bit outputs (image/display.h).
  std::optional<double> exposure;  // [-kMaxExposureStops, kMaxExposureStops]
  std::optional<image::ToneCurve> tone;
  // How it is cut and written; the pixels are the same bits whatever these say.
  std::optional<std::uint32_t> tile_size;      // [kMinTileSize, kMaxTileSize]
  std::optional<std::uint32_t> png_bit_depth;  // is_png_bit_depth
  // Only these pixels are rendered and written (an image of crop.width x crop.height); each has
  // the same bits as in the full render. Inside the image, not empty.
  std::optional<TileRect> crop;

  bool operator==(const Overrides&) const = default;
};

// `settings` with every set field of `overrides` applied. An explicit `frame` without `frames`
// wins over the scene's range, and a range of one frame becomes that single frame (frames unset),
// so that a single-frame render keeps the settings, and digest, it always had.
RenderSettings apply(const Overrides& overrides, RenderSettings settings);

// The frames the settings render: `frames`, or the single frame `frame`.
inline FrameRange frame_range(const RenderSettings& s) {
  return s.frames ? *s.frames : FrameRange{s.frame, s.frame, 1};
}

// tile_size, or kDefaultTileSize; png_bit_depth, or kDefaultPngBitDepth.
std::uint32_t tile_size_or_default(const Overrides& overrides);
std::uint32_t png_bit_depth_or_default(const Overrides& overrides);

}  // namespace dtraced::scene
