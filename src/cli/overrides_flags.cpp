#include "cli/overrides_flags.h"

#include <cfloat>
#include <cmath>
#include <cstdint>
#include <limits>

#include <fmt/format.h>

#include "scene/description.h"
#include "scene/tiling.h"

namespace dtraced::cli {
namespace {

// A background channel: what a scene file's colours allow (finite, >= 0, within the float range).
CLI::Validator background_channel() {
  return CLI::Validator(
      [](std::string& v) -> std::string {
        double x = 0;
        if (!CLI::detail::lexical_cast(v, x) || !(x >= 0.0 && x <= FLT_MAX)) {
          return "each channel must be a finite number >= 0, got " + v;
        }
        return {};
      },
      "R,G,B");
}

}  // namespace

void add_override_flags(CLI::App& app, scene::Overrides& o, const OverrideFlagOptions& options) {
  const auto help = [&](std::string_view text) { return options.help_prefix + std::string(text); };
  const auto want = [&](OverrideField f) { return (options.fields & f) != 0; };
  std::vector<CLI::Option*> added;
  if (want(kOverrideWidth)) {
    added.push_back(
        app.add_option("--width", o.width, help("Image width in pixels"))->check(CLI::Range(1u, scene::kMaxImageSide)));
  }
  if (want(kOverrideHeight)) {
    added.push_back(app.add_option("--height", o.height, help("Image height in pixels"))
                        ->check(CLI::Range(1u, scene::kMaxImageSide)));
  }
  if (want(kOverrideSamples)) {
    added.push_back(app.add_option("-s,--samples", o.samples, help("Samples per pixel (the most, when adaptive)"))
                        ->check(CLI::Range(1u, scene::kMaxSamples)));
  }
  if (want(kOverrideMaxDepth)) {
    added.push_back(app.add_option("--max-depth", o.max_depth, help("Maximum reflection/refraction depth"))
                        ->check(CLI::Range(0u, scene::kMaxDepth)));
  }
  if (want(kOverrideSeed)) {
    added.push_back(app.add_option("--seed", o.seed, help("Sampling seed (part of every sample's random key)"))
                        ->check(CLI::Range(std::uint64_t{0}, scene::kMaxSeed)));
  }
  if (want(kOverrideFrame)) {
    added.push_back(app.add_option("--frame", o.frame, help("Frame number (part of every sample's random key)")));
  }
  if (want(kOverrideBackground)) {
    added.push_back(app.add_option_function<std::vector<double>>(
                           "--background",
                           [&o](const std::vector<double>& c) {
                             o.background = scene::Color{c.at(0), c.at(1), c.at(2)};
                           },
                           help("Background colour, linear RGB: R,G,B"))
                        ->delimiter(',')
                        ->expected(3)
                        ->check(background_channel()));
  }
  if (want(kOverrideErrorTarget)) {
    added.push_back(
        app.add_option(
               "--error-target", o.error_target,
               help("Adaptive sampling: stop a pixel once its relative standard error is at most this (0: off)"))
            ->check(CLI::Range(0.0, scene::kMaxErrorTarget)));
  }
  if (want(kOverrideMinSamples)) {
    added.push_back(
        app.add_option("--min-samples", o.min_samples, help("Adaptive sampling: samples before the first check"))
            ->check(CLI::Range(1u, scene::kMaxSamples)));
  }
  if (want(kOverrideTileSize)) {
    added.push_back(app.add_option("--tile-size", o.tile_size,
                                   help(fmt::format("Tile side in pixels (default {})", scene::kDefaultTileSize)))
                        ->check(CLI::Range(scene::kMinTileSize, scene::kMaxTileSize)));
  }
  if (want(kOverridePngBitDepth)) {
    added.push_back(app.add_option("--bit-depth", o.png_bit_depth, help("PNG bit depth: 8 or 16 (default 8)"))
                        ->check(CLI::IsMember({8u, 16u})));
  }
  if (!options.group.empty()) {
    for (CLI::Option* opt : added) opt->group(options.group);
  }
}

std::vector<std::string> given_override_flags(const scene::Overrides& o) {
  std::vector<std::string> out;
  const auto note = [&out](bool set, const char* flag) {
    if (set) out.emplace_back(flag);
  };
  note(o.width.has_value(), "--width");
  note(o.height.has_value(), "--height");
  note(o.samples.has_value(), "--samples");
  note(o.max_depth.has_value(), "--max-depth");
  note(o.seed.has_value(), "--seed");
  note(o.frame.has_value(), "--frame");
  note(o.background.has_value(), "--background");
  note(o.error_target.has_value(), "--error-target");
  note(o.min_samples.has_value(), "--min-samples");
  note(o.tile_size.has_value(), "--tile-size");
  note(o.png_bit_depth.has_value(), "--bit-depth");
  return out;
}

}  // namespace dtraced::cli
