#include "scene/scene_json.h"

#include <cfloat>
#include <cmath>
#include <cstdint>
#include <limits>
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
  return o;
}

}  // namespace dtraced::scene
