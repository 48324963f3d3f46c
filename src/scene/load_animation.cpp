// Tracks of animated values (load_animation.h).
#include "scene/load_animation.h"

#include <algorithm>
#include <array>
#include <utility>

#include <boost/json/array.hpp>
#include <fmt/format.h>

namespace dtraced::scene::detail {
namespace {

namespace json = boost::json;
using jsonio::Need;
using jsonio::Path;

constexpr std::array<std::string_view, 4> kTrackKeys = {"keys", "interpolation", "repeat", "offset"};
constexpr std::array<std::string_view, 2> kKeyKeys = {"t", "value"};

// The keys of `list`, each {"t", "value"}, t strictly increasing.
void read_keys(SceneReader& s, const json::array& list, const Path& at, const ValueReader& read_value,
               std::vector<Key>& keys) {
  jsonio::Reader& r = s.r;
  if (list.empty()) r.error(at, "a track needs at least one key");
  keys.reserve(list.size());
  std::optional<double> previous;
  for (std::size_t i = 0; i < list.size(); ++i) {
    const Path key_at = at.index(i);
    const json::object* o = r.object(list[i], key_at);
    if (o == nullptr) continue;
    jsonio::Fields f(r, *o, key_at, kKeyKeys);
    Key key;
    const bool has_t = f.number("t", key.t, -kMaxTrackTime, kMaxTrackTime);
    f.read("value", key.value, Need::kRequired, read_value);
    if (!has_t) continue;
    if (previous && !(key.t > *previous)) {
      r.error(f.path("t"), fmt::format("must be greater than the previous key's t ({})", *previous));
    }
    previous = key.t;
    keys.push_back(key);
  }
}

}  // namespace

bool is_track(const json::value& v) {
  const json::object* o = v.if_object();
  return o != nullptr &&
         std::any_of(kTrackKeys.begin(), kTrackKeys.end(), [o](std::string_view k) { return o->contains(k); });
}

Span Span::of(const Track& track) {
  Span span = of(track.keys.front().value);
  for (const Key& key : track.keys) {
    span.lo = math::min(span.lo, key.value);
    span.hi = math::max(span.hi, key.value);
  }
  return span;
}

Track* read_track(SceneReader& s, const json::object& o, const Path& at, Target target, const ValueReader& read_value) {
  jsonio::Reader& r = s.r;
  const std::size_t errors_before = r.error_count();
  jsonio::Fields f(r, o, at, kTrackKeys);
  Track track;
  track.target = target;
  track.index = s.index;
  f.read("interpolation", track.interpolation, Need::kOptional, [&r](const json::value& v, const Path& p) {
    const auto i = r.choice(v, p, kInterpolationNames, "interpolation", "interpolations");
    return i ? std::optional<Interpolation>(static_cast<Interpolation>(*i)) : std::nullopt;
  });
  f.boolean("repeat", track.repeat, Need::kOptional);
  f.number("offset", track.offset, -kMaxTrackTime, kMaxTrackTime, Need::kOptional);
  if (const json::value* v = f.get("keys", Need::kRequired)) {
    const Path keys_at = f.path("keys");
    if (const json::array* list = r.array(*v, keys_at, kMaxKeys, "keys")) {
      read_keys(s, *list, keys_at, read_value, track.keys);
      if (track.repeat && list->size() < 2) {
        r.error(f.path("repeat"), "a repeating track needs at least two keys (its period is last t - first t)");
      }
    }
  }
  if (r.error_count() != errors_before) return nullptr;
  if (s.animation.tracks.size() >= kMaxTracks) {
    r.error(at, fmt::format("too many animated values in one scene (limit {})", kMaxTracks));
    return nullptr;
  }
  s.animation.tracks.push_back(std::move(track));
  return &s.animation.tracks.back();
}

}  // namespace dtraced::scene::detail
