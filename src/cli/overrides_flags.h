// dtraced::cli override flags: the one place the command line spells scene::Overrides.
//
// Owns the flags of every render-setting override (--width, --height, -s/--samples, --max-depth,
// --seed, --frame, --background R,G,B, --error-target, --min-samples, --tile-size, --bit-depth,
// --frames A-B[:STEP], --fps, --exposure, --tone, --crop X0,Y0,X1,Y1),
// their help texts and their checks, which are the limits of scene/ (description.h, tiling.h,
// overrides.h): the same a scene file, a request body or a config file is checked against. The
// render verb, submit, the one-shot collector and bench error all add them through here, so an
// override added to scene::Overrides is added to every entry point at once.
//
// Not thread-safe: CLI11 parsing happens once, on main's thread.
#pragma once

#include <string>
#include <string_view>
#include <vector>

#include <CLI/CLI.hpp>

#include "scene/overrides.h"
#include "util/result.h"

namespace dtraced::cli {

// Which fields of scene::Overrides get a flag.
enum OverrideField : unsigned {
  kOverrideWidth = 1u << 0,
  kOverrideHeight = 1u << 1,
  kOverrideSamples = 1u << 2,
  kOverrideMaxDepth = 1u << 3,
  kOverrideSeed = 1u << 4,
  kOverrideFrame = 1u << 5,
  kOverrideBackground = 1u << 6,
  kOverrideErrorTarget = 1u << 7,
  kOverrideMinSamples = 1u << 8,
  kOverrideTileSize = 1u << 9,
  kOverridePngBitDepth = 1u << 10,
  kOverrideFrames = 1u << 11,   // --frames and --fps
  kOverrideDisplay = 1u << 12,  // --exposure and --tone
  kOverrideCrop = 1u << 13,
  kAllOverrides = (1u << 14) - 1,
};

struct OverrideFlagOptions {
  unsigned fields = kAllOverrides;
  std::string group;        // CLI11 help group ("" = the app's default)
  std::string help_prefix;  // put before every help text ("One-shot: ")
};

// "A-B" or "A-B:STEP" (or a single "A"), A <= B, STEP >= 1, at most scene::kMaxFrames frames;
// the error says what is wrong with `text`.
util::Result<scene::FrameRange> parse_frame_range(std::string_view text);

// "X0,Y0,X1,Y1": the pixels x in [X0, X1), y in [Y0, Y1), not empty. Whether it lies inside the
// image is checked once the image size is known (check_crop).
util::Result<scene::TileRect> parse_crop(std::string_view text);
// Whether `crop` lies inside a width x height image; the error names --crop.
util::Status check_crop(const scene::TileRect& crop, std::uint32_t width, std::uint32_t height);

// Adds the selected flags to `app`, each filling its field of `overrides` when given.
void add_override_flags(CLI::App& app, scene::Overrides& overrides, const OverrideFlagOptions& options = {});

// The long flag names of the fields `overrides` sets ("--width", ...), for messages such as
// "--width needs --scene".
std::vector<std::string> given_override_flags(const scene::Overrides& overrides);

}  // namespace dtraced::cli
