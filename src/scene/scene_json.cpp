#include "scene/scene_json.h"

#include <cfloat>
#include <cmath>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <utility>

#include <boost/json/array.hpp>
#include <fmt/format.h>

#include "scene/overrides.h"

namespace dtraced::scene {
namespace {

namespace json = boost::json;
using jsonio::Need;
using jsonio::Path;

constexpr double kFloatMax = FLT_MAX;
constexpr std::array<std::string_view, 3> kFramesKeys = {"first", "last", "step"};

std::optional<FrameRange> read_frames(jsonio::Reader& r, const json::value& v, const Path& at) {
  const json::object* o = r.object(v, at);
  if (o == nullptr) return std::nullopt;
  jsonio::Fields f(r, *o, at, kFramesKeys);
  FrameRange range;
  constexpr std::int64_t kMaxFrame = std::numeric_limits<std::uint32_t>::max();
  bool ok = f.integer("first", range.first, 0, kMaxFrame);
  ok = f.integer("last", range.last, 0, kMaxFrame) && ok;
  ok = f.integer("step", range.step, 1, kMaxFrame, Need::kOptional) && ok;
  if (!ok) return std::nullopt;
  if (range.last < range.first) {
    r.error(f.path("last"), fmt::format("must be >= first ({}) (got {})", range.first, range.last));
    return std::nullopt;
  }
  if (range.count() > kMaxFrames) {
    r.error(at, fmt::format("{} frames, more than the limit of {} in one range", range.count(), kMaxFrames));
    return std::nullopt;
  }
  return range;
}

}  // namespace

std::optional<double> read_float(jsonio::Reader& r, const json::value& v, const Path& at) {
  const std::optional<double> d = r.number(v, at);
  if (d && std::abs(*d) > kFloatMax) {
    r.error(at, fmt::format("number {} is outside the float range (magnitude at most {})", *d, kFloatMax));
    return std::nullopt;
  }
  return d;
}

std::optional<Vec3d> read_vec3(jsonio::Reader& r, const json::value& v, const Path& at) {
  const json::array* a = r.tuple(v, at, 3, "numbers");
  if (a == nullptr) return std::nullopt;
  Vec3d out;
  bool ok = true;
  for (std::size_t i = 0; i < 3; ++i) {
    if (const auto c = read_float(r, (*a)[i], at.index(i))) {
      out[i] = *c;
    } else {
      ok = false;
    }
  }
  return ok ? std::optional<Vec3d>(out) : std::nullopt;
}

std::optional<Color> read_color(jsonio::Reader& r, const json::value& v, const Path& at) {
  const std::optional<Vec3d> c = read_vec3(r, v, at);
  if (!c) return std::nullopt;
  bool ok = true;
  for (std::size_t i = 0; i < 3; ++i) {
    ok = r.in_range((*c)[i], at.index(i), 0, std::numeric_limits<double>::infinity()) && ok;
  }
  return ok ? c : std::nullopt;
}

template <typename Settings>
void read_render_settings(jsonio::Fields& f, Settings& s, Need need) {
  jsonio::Reader& r = f.reader();
  f.integer("width", s.width, 1, kMaxImageSide, need);
  f.integer("height", s.height, 1, kMaxImageSide, need);
  f.integer("samples", s.samples, 1, kMaxSamples, need);
  f.integer("max_depth", s.max_depth, 0, kMaxDepth, need);
  f.read("background", s.background, need, [&r](const json::value& v, const Path& at) { return read_color(r, v, at); });
  f.integer("seed", s.seed, 0, static_cast<std::int64_t>(kMaxSeed), need);
  f.integer("frame", s.frame, 0, std::numeric_limits<std::uint32_t>::max(), need);
  f.number("error_target", s.error_target, 0, kMaxErrorTarget, Need::kOptional);
  f.integer("min_samples", s.min_samples, 1, kMaxSamples, Need::kOptional);
  f.number("branch_cutoff", s.branch_cutoff, kMinBranchCutoff, kMaxBranchCutoff, Need::kOptional);
  f.read("fps", s.fps, Need::kOptional, [&r](const json::value& v, const Path& at) -> std::optional<double> {
    const auto d = r.number(v, at);
    if (d && !(*d > 0 && *d <= kMaxFps)) {
      r.error(at, fmt::format("must be in (0, {}] frames per second (got {})", kMaxFps, *d));
      return std::nullopt;
    }
    return d;
  });
  f.read("frames", s.frames, Need::kOptional,
         [&r](const json::value& v, const Path& at) { return read_frames(r, v, at); });
  auto& exposure = [&s]() -> auto& {
    if constexpr (std::is_same_v<Settings, Overrides>) {
      return s.exposure;
    } else {
      return s.display.exposure;
    }
  }
  ();
  auto& tone = [&s]() -> auto& {
    if constexpr (std::is_same_v<Settings, Overrides>) {
      return s.tone;
    } else {
      return s.display.tone;
    }
  }
  ();
  f.number("exposure", exposure, -image::kMaxExposureStops, image::kMaxExposureStops, Need::kOptional);
  f.read("tone", tone, Need::kOptional, [&r](const json::value& v, const Path& at) {
    const auto i = r.choice(v, at, image::kToneCurveNames, "tone curve", "tone curves");
    return i ? std::optional<image::ToneCurve>(static_cast<image::ToneCurve>(*i)) : std::nullopt;
  });
}
template void read_render_settings<RenderSettings>(jsonio::Fields&, RenderSettings&, Need);
template void read_render_settings<Overrides>(jsonio::Fields&, Overrides&, Need);

json::value vec3_value(const Vec3d& v, const json::storage_ptr& sp) {
  json::array a(sp);
  a.reserve(3);
  a.push_back(jsonio::exact_number(v.x, sp));
  a.push_back(jsonio::exact_number(v.y, sp));
  a.push_back(jsonio::exact_number(v.z, sp));
  return json::value(std::move(a));
}

json::value frame_range_value(const FrameRange& range, const json::storage_ptr& sp) {
  json::object frames(3, sp);
  frames["first"] = range.first;
  frames["last"] = range.last;
  frames["step"] = range.step;
  return frames;
}

json::object render_settings_object(const RenderSettings& s, const json::storage_ptr& sp) {
  json::object o(kRenderKeys.size(), sp);
  o["width"] = s.width;
  o["height"] = s.height;
  o["samples"] = s.samples;
  o["max_depth"] = s.max_depth;
  o["background"] = vec3_value(s.background, sp);
  o["seed"] = s.seed;
  o["frame"] = s.frame;
  if (s.error_target > 0 || s.min_samples != RenderSettings{}.min_samples) {
    o["error_target"] = jsonio::exact_number(s.error_target, sp);
    o["min_samples"] = s.min_samples;
  }
  const RenderSettings defaults;
  if (s.fps != defaults.fps) o["fps"] = jsonio::exact_number(s.fps, sp);
  if (s.frames) o["frames"] = frame_range_value(*s.frames, sp);
  if (s.display.exposure != defaults.display.exposure) o["exposure"] = jsonio::exact_number(s.display.exposure, sp);
  if (s.display.tone != defaults.display.tone) o["tone"] = image::to_string(s.display.tone);
  if (s.branch_cutoff != defaults.branch_cutoff) o["branch_cutoff"] = jsonio::exact_number(s.branch_cutoff, sp);
  return o;
}

}  // namespace dtraced::scene
