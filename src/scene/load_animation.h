// dtraced::scene loading, internal: animatable values (scene/animation.h). A value that may be
// animated is read either as before (a static value) or as a track object
//   {"keys": [{"t": 0, "value": V}, ...], "interpolation": "linear", "repeat": false, "offset": 0}
// whose every key's value is checked by the static value's own reader, so each is validated, and
// located ("/scene_objects/3/loc/keys/2/value/1: ..."), exactly as a static value would be. The
// track joins the load's Animation; the description's field gets the track's value at t = 0.
//
// One SceneReader per load: not thread-safe; loads share nothing.
#pragma once

#include <functional>
#include <optional>
#include <string_view>
#include <type_traits>

#include <boost/json/object.hpp>
#include <boost/json/value.hpp>

#include "scene/animation.h"
#include "scene/load_objects.h"

namespace dtraced::scene::detail {

// The least and greatest value of each component over time: over a track's keys (which bound
// every interpolated value), or the static value itself. Derived checks (a sphere's bounds, a
// light's colour x intensity) use these, so they hold at every time.
struct Span {
  Vec3d lo, hi;
  static Span of(const Vec3d& v) { return {v, v}; }
  static Span of(const Track& track);
  Vec3d max_abs() const { return math::max(math::abs(lo), math::abs(hi)); }
};

// Whether `v` is written as a track: an object with any key of one. Any other value (an object
// without them too) is read, and reported, as the static value.
bool is_track(const boost::json::value& v);

using ValueReader = std::function<std::optional<Vec3d>(const boost::json::value&, const jsonio::Path&)>;

// Reads the track object `o` at `at` for `target` of the element s.index, each key's value by
// `read_value`, into s.animation; the new track, or nullptr after reporting its problems.
Track* read_track(SceneReader& s, const boost::json::object& o, const jsonio::Path& at, Target target,
                  const ValueReader& read_value);

inline Vec3d to_vec3(double d) { return {d, 0, 0}; }
inline Vec3d to_vec3(const Vec3d& v) { return v; }

// Fields::read for a value that may be animated: `read(value, path) -> std::optional<X>` reads one
// static value (and each key's). `out` (a double or a Vec3d) gets the static value, or the track's
// at t = 0; `span`, when given, the value's range over time; `track_out` the track, if any.
template <typename T, typename Read>
bool read_animatable(SceneReader& s, jsonio::Fields& f, std::string_view key, T& out, jsonio::Need need, Target target,
                     Read read, Span* span = nullptr, Track** track_out = nullptr) {
  static_assert(std::is_same_v<T, double> || std::is_same_v<T, Vec3d>);
  const boost::json::value* v = f.get(key, need);
  if (v == nullptr) {
    if (span != nullptr) *span = Span::of(to_vec3(out));
    return need == jsonio::Need::kOptional;
  }
  if (is_track(*v)) {
    const ValueReader read_value = [&read](const boost::json::value& kv,
                                           const jsonio::Path& kp) -> std::optional<Vec3d> {
      const auto got = read(kv, kp);
      return got ? std::optional<Vec3d>(to_vec3(static_cast<T>(*got))) : std::nullopt;
    };
    Track* track = read_track(s, v->get_object(), f.path(key), target, read_value);
    if (track == nullptr) return false;
    const Vec3d at_zero = evaluate(*track, 0);
    if constexpr (std::is_same_v<T, double>) {
      out = at_zero.x;
    } else {
      out = at_zero;
    }
    if (span != nullptr) *span = Span::of(*track);
    if (track_out != nullptr) *track_out = track;
    return true;
  }
  const bool ok = f.read(key, out, need, read);
  if (span != nullptr) *span = Span::of(to_vec3(out));
  return ok;
}

}  // namespace dtraced::scene::detail
