#include "cli/overrides_flags.h"

#include <cfloat>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <system_error>

#include <fmt/format.h>

#include "image/display.h"
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

// Non-negative decimal integer that fits a u32, all of `text`.
std::optional<std::uint32_t> parse_u32(std::string_view text) {
  std::uint32_t v = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  if (ec != std::errc() || end != text.data() + text.size() || text.empty()) return std::nullopt;
  return v;
}

// A CLI11 option function that parses `text` with `parse` and stores the result in `field`; the
// parse error becomes CLI11's ValidationError, so it reads like every other bad flag.
template <typename T, typename Parse>
std::function<void(const std::string&)> parsed_into(std::optional<T>& field, Parse parse, std::string flag) {
  return [&field, parse, flag = std::move(flag)](const std::string& text) {
    util::Result<T> r = parse(text);
    if (!r) throw CLI::ValidationError(flag, r.error().message);
    field = *r;
  };
}

}  // namespace

util::Result<scene::FrameRange> parse_frame_range(std::string_view text) {
  const auto bad = [&](std::string_view why) {
    return util::Error{
        fmt::format("'{}' is not a frame range: {} (write A-B or A-B:STEP, e.g. 1-24 or 0-47:2)", text, why)};
  };
  std::string_view range = text;
  std::uint32_t step = 1;
  if (const std::size_t colon = text.find(':'); colon != std::string_view::npos) {
    const std::optional<std::uint32_t> st = parse_u32(text.substr(colon + 1));
    if (!st || *st == 0) return bad("the step must be an integer >= 1");
    step = *st;
    range = text.substr(0, colon);
  }
  std::optional<std::uint32_t> first, last;
  if (const std::size_t dash = range.find('-'); dash != std::string_view::npos) {
    first = parse_u32(range.substr(0, dash));
    last = parse_u32(range.substr(dash + 1));
  } else {
    first = last = parse_u32(range);
  }
  if (!first || !last) return bad("frame numbers are integers from 0 to 4294967295");
  if (*last < *first) return bad("the last frame comes before the first");
  const scene::FrameRange r{*first, *last, step};
  if (r.count() > scene::kMaxFrames) return bad(fmt::format("more than {} frames", scene::kMaxFrames));
  return r;
}

util::Result<scene::TileRect> parse_crop(std::string_view text) {
  std::uint32_t v[4] = {};
  std::string_view rest = text;
  for (int i = 0; i < 4; ++i) {
    const std::size_t comma = i < 3 ? rest.find(',') : rest.size();
    const std::optional<std::uint32_t> n =
        comma == std::string_view::npos ? std::nullopt : parse_u32(rest.substr(0, comma));
    if (!n) return util::Error{fmt::format("'{}' is not a crop: write X0,Y0,X1,Y1, four pixel coordinates", text)};
    v[i] = *n;
    rest = i < 3 ? rest.substr(comma + 1) : std::string_view();
  }
  if (v[2] <= v[0] || v[3] <= v[1]) {
    return util::Error{
        fmt::format("'{}' is an empty crop: X1 must exceed X0 and Y1 exceed Y0 (X1, Y1 exclusive)", text)};
  }
  return scene::TileRect{v[0], v[1], v[2] - v[0], v[3] - v[1]};
}

util::Status check_crop(const scene::TileRect& c, std::uint32_t width, std::uint32_t height) {
  if (std::uint64_t{c.x0} + c.width > width || std::uint64_t{c.y0} + c.height > height) {
    return util::Error{fmt::format("--crop {},{},{},{} reaches outside the {}x{} image", c.x0, c.y0,
                                   std::uint64_t{c.x0} + c.width, std::uint64_t{c.y0} + c.height, width, height)};
  }
  return {};
}

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
    added.push_back(
        app.add_option("--tile-size", o.tile_size,
                       help(fmt::format("Tile side in pixels (default {}; `dtraced render` uses {} when adaptive)",
                                        scene::kDefaultTileSize, scene::kDefaultAdaptiveTileSize)))
            ->check(CLI::Range(scene::kMinTileSize, scene::kMaxTileSize)));
  }
  if (want(kOverridePngBitDepth)) {
    added.push_back(app.add_option("--bit-depth", o.png_bit_depth, help("PNG bit depth: 8 or 16 (default 8)"))
                        ->check(CLI::IsMember({8u, 16u})));
  }
  if (want(kOverrideFrames)) {
    added.push_back(app.add_option_function<std::string>(
        "--frames", parsed_into(o.frames, parse_frame_range, "--frames"),
        help("Render a sequence of frames: A-B or A-B:STEP (each frame picks the scene's time and seeds the noise)")));
    added.push_back(app.add_option("--fps", o.fps, help("Frames per second: frame n shows time n / fps"))
                        ->check(CLI::Range(0x1p-20, scene::kMaxFps)));
  }
  if (want(kOverrideDisplay)) {
    added.push_back(app.add_option("--exposure", o.exposure,
                                   help("Exposure of 8- and 16-bit outputs, in stops (PFM and EXR stay linear)"))
                        ->check(CLI::Range(-image::kMaxExposureStops, image::kMaxExposureStops)));
    added.push_back(app.add_option_function<std::string>(
                           "--tone", [&o](const std::string& name) { o.tone = image::tone_curve_from_string(name); },
                           help("Tone curve of 8- and 16-bit outputs: clamp (default), reinhard or filmic"))
                        ->check(CLI::IsMember({"clamp", "reinhard", "filmic"})));
  }
  if (want(kOverrideCrop)) {
    added.push_back(app.add_option_function<std::string>(
        "--crop", parsed_into(o.crop, parse_crop, "--crop"),
        help("Render only the pixels X0 <= x < X1, Y0 <= y < Y1 (same bits as in the full image): X0,Y0,X1,Y1")));
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
  note(o.frames.has_value(), "--frames");
  note(o.fps.has_value(), "--fps");
  note(o.exposure.has_value(), "--exposure");
  note(o.tone.has_value(), "--tone");
  note(o.crop.has_value(), "--crop");
  return out;
}

}  // namespace dtraced::cli
