#include "scene/load.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cfloat>
#include <cmath>
#include <filesystem>
#include <limits>
#include <memory>
#include <span>
#include <utility>

#include <boost/json/monotonic_resource.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "math/vec.h"
#include "scene/json_reader.h"
#include "scene/obj_mesh.h"
#include "util/file.h"

namespace dtraced::scene {
namespace {

namespace json = boost::json;
using math::Vec3f;

constexpr double kFloatMax = FLT_MAX;
constexpr double kMaxShininess = 1e4;
// Decimal fractions such as 0.3 + 0.7 may sum to a hair above 1 in binary; that is not a mistake
// worth rejecting; the shader's weight 1 - reflectivity - transparency then dips at most 1e-9
// below zero, which is harmless.
constexpr double kEnergySlack = 1e-9;
// `up` counts as parallel to the view direction when |up x dir| < kParallelTolerance |up| |dir|.
constexpr double kParallelTolerance = 1e-6;
// A normal this close to unit length is kept as written (see unit_length).
constexpr double kUnitTolerance = 1e-12;

constexpr std::array<std::string_view, 4> kTopKeys = {"camera", "render", "scene_objects", "scene_lights"};
constexpr std::array<std::string_view, 4> kCameraKeys = {"position", "look_at", "up", "fov"};
constexpr std::array<std::string_view, 9> kRenderKeys = {"width", "height", "samples",      "max_depth",  "background",
                                                         "seed",  "frame",  "error_target", "min_samples"};
constexpr std::array<std::string_view, 7> kMaterialKeys = {"color",        "diffuse",      "specular", "shininess",
                                                           "reflectivity", "transparency", "ior"};
constexpr std::array<std::string_view, 4> kSphereKeys = {"type", "loc", "radius", "material"};
constexpr std::array<std::string_view, 6> kBoxKeys = {"type", "loc", "size", "min", "max", "material"};
constexpr std::array<std::string_view, 4> kPlaneKeys = {"type", "loc", "normal", "material"};
constexpr std::array<std::string_view, 7> kMeshKeys = {"type",   "file",  "obj",     "translate",
                                                       "rotate", "scale", "material"};
// Keys checked when an object's type is missing or unknown, so typos are still reported.
constexpr std::array<std::string_view, 13> kAnyObjectKeys = {
    "type", "loc", "radius", "size", "min", "max", "normal", "material", "file", "obj", "translate", "rotate", "scale"};
constexpr std::array<std::string_view, 4> kPointLightKeys = {"type", "loc", "color", "intensity"};
constexpr std::array<std::string_view, 7> kSphereLightKeys = {"type",      "loc",     "radius",      "color",
                                                              "intensity", "samples", "cast_shadows"};
constexpr std::array<std::string_view, 8> kDiskLightKeys = {"type",  "loc",       "radius",  "normal",
                                                            "color", "intensity", "samples", "cast_shadows"};
constexpr std::array<std::string_view, 9> kRectLightKeys = {"type",  "loc",       "u",       "v",           "normal",
                                                            "color", "intensity", "samples", "cast_shadows"};
// Keys checked when a light's type is missing or unknown.
constexpr std::array<std::string_view, 10> kAnyLightKeys = {"type", "loc",   "radius",    "normal",  "u",
                                                            "v",    "color", "intensity", "samples", "cast_shadows"};

// A JSON Pointer built only when an error needs it: validating a 10M-object scene must not
// allocate a path string per field. A Path refers to its parent, so keep chains in one
// expression or in named locals whose parents outlive them.
class Path {
 public:
  Path() = default;  // the document root, ""

  Path key(std::string_view k) const { return Path(this, k, 0, /* is_index = */ false); }
  Path index(std::size_t i) const { return Path(this, {}, i, /* is_index = */ true); }

  std::string str() const {
    if (parent_ == nullptr) return {};
    std::string s = parent_->str();
    s += '/';
    s += is_index_ ? std::to_string(index_) : json_pointer_escape(key_);
    return s;
  }

 private:
  Path(const Path* parent, std::string_view key, std::size_t index, bool is_index)
      : parent_(parent), key_(key), index_(index), is_index_(is_index) {}

  const Path* parent_ = nullptr;
  std::string_view key_;
  std::size_t index_ = 0;
  bool is_index_ = false;
};

std::size_t edit_distance(std::string_view a, std::string_view b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diagonal = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = up;
    }
  }
  return row[b.size()];
}

// Names other renderers and the seed project's users reach for, mapped to ours; spelling
// distance alone would never connect "center" to "loc".
constexpr std::array<std::pair<std::string_view, std::string_view>, 9> kKeyAliases = {{
    {"center", "loc"},
    {"centre", "loc"},
    {"position", "loc"},
    {"pos", "loc"},
    {"fov_deg", "fov"},
    {"spp", "samples"},
    {"objects", "scene_objects"},
    {"lights", "scene_lights"},
    {"eye", "position"},
}};

std::string unknown_key_message(std::string_view key, std::span<const std::string_view> known) {
  for (const auto& [alias, meant] : kKeyAliases) {
    if (key == alias && std::find(known.begin(), known.end(), meant) != known.end()) {
      return fmt::format("unknown key \"{}\" (did you mean \"{}\"?)", key, meant);
    }
  }
  std::string_view best;
  std::size_t best_distance = std::numeric_limits<std::size_t>::max();
  for (const std::string_view k : known) {
    const std::size_t d = edit_distance(key, k);
    if (d < best_distance) {
      best_distance = d;
      best = k;
    }
  }
  // Two edits catch transpositions ("raduis") and British spellings ("colour") without
  // suggesting "loc" for "foo".
  if (best_distance <= 2 && best_distance < key.size()) {
    return fmt::format("unknown key \"{}\" (did you mean \"{}\"?)", key, best);
  }
  return fmt::format("unknown key \"{}\"; known keys: {}", key, fmt::join(known, ", "));
}

// Normalises with a prior scaling so neither tiny nor huge components underflow or overflow.
// A vector already within kUnitTolerance of unit length is returned bit for bit: canonical JSON
// writes the normalised normal, and reading it back must not move it by an ulp.
std::optional<Vec3d> unit_length(const Vec3d& v) {
  const double scale = math::max_component(math::abs(v));
  if (scale == 0) return std::nullopt;
  if (std::abs(math::length_squared(v) - 1.0) <= kUnitTolerance) return v;
  const Vec3d s = v / scale;
  return s / math::length(s);
}

// The 1-based line of the first byte sequence that is not UTF-8 (RFC 3629: no overlong forms, no
// surrogates, nothing above U+10FFFF), or 0 when all of `text` is UTF-8.
std::size_t first_invalid_utf8_line(std::string_view text) {
  std::size_t line = 1;
  for (std::size_t i = 0; i < text.size();) {
    const auto c = static_cast<unsigned char>(text[i]);
    if (c < 0x80) {
      line += c == '\n';
      ++i;
      continue;
    }
    std::size_t n = 0;
    unsigned lo = 0x80, hi = 0xBF;  // allowed range of the second byte
    if (c >= 0xC2 && c <= 0xDF) {
      n = 1;
    } else if (c >= 0xE0 && c <= 0xEF) {
      n = 2;
      if (c == 0xE0) lo = 0xA0;
      if (c == 0xED) hi = 0x9F;
    } else if (c >= 0xF0 && c <= 0xF4) {
      n = 3;
      if (c == 0xF0) lo = 0x90;
      if (c == 0xF4) hi = 0x8F;
    } else {
      return line;
    }
    if (i + n >= text.size()) return line;  // truncated sequence
    for (std::size_t k = 1; k <= n; ++k) {
      const auto b = static_cast<unsigned char>(text[i + k]);
      if (k == 1 ? (b < lo || b > hi) : (b < 0x80 || b > 0xBF)) return line;
    }
    i += n + 1;
  }
  return 0;
}

// Walks the parsed JSON, filling a SceneDesc and recording every problem it meets.
class Validator {
 public:
  Validator(std::string file, const LoadOptions& options)
      : file_(std::move(file)), max_errors_(options.max_errors), options_(options) {}

  void error(std::string path, std::string message) {
    ++error_count_;
    if (errors_.size() < max_errors_) errors_.push_back({std::move(message), std::move(path), file_});
  }
  void error(const Path& at, std::string message) { error(at.str(), std::move(message)); }
  void warning(const Path& at, std::string message) { warnings_.push_back({std::move(message), at.str(), file_}); }

  LoadResult finish(std::optional<SceneDesc> scene) {
    LoadResult result;
    if (error_count_ > errors_.size()) {
      errors_.push_back({fmt::format("{} more errors not shown", error_count_ - errors_.size()), "", file_});
    }
    if (error_count_ == 0) result.scene = std::move(scene);
    result.errors = std::move(errors_);
    result.warnings = std::move(warnings_);
    return result;
  }

  std::optional<SceneDesc> read_scene(const json::value& root_value) {
    const Path root;
    const json::object* root_obj = root_value.if_object();
    if (root_obj == nullptr) {
      error(root, fmt::format("expected a JSON object at the top level, got {}", json_kind_name(root_value)));
      return std::nullopt;
    }
    check_keys(*root_obj, root, kTopKeys);

    SceneDesc scene;
    if (const json::value* v = required(*root_obj, "camera", root)) read_camera(*v, root.key("camera"), scene.camera);
    if (const json::value* v = root_obj->if_contains("render")) read_render(*v, root.key("render"), scene.render);

    if (const json::value* v = required(*root_obj, "scene_objects", root)) {
      const Path at = root.key("scene_objects");
      if (const json::array* list = array(*v, at, kMaxObjects, "objects")) {
        scene.objects.reserve(list->size());
        for (std::size_t i = 0; i < list->size(); ++i) {
          if (auto object = read_object((*list)[i], at.index(i))) scene.objects.push_back(*object);
        }
        if (list->empty()) warning(at, "the scene has no objects: it renders as the background only");
      }
    }
    if (const json::value* v = required(*root_obj, "scene_lights", root)) {
      const Path at = root.key("scene_lights");
      if (const json::array* list = array(*v, at, kMaxLights, "lights")) {
        scene.lights.reserve(list->size());
        for (std::size_t i = 0; i < list->size(); ++i) {
          if (auto light = read_light((*list)[i], at.index(i))) scene.lights.push_back(*light);
        }
        if (list->empty()) warning(at, "the scene has no lights: only reflections of the background will show");
      }
    }
    if (error_count_ != 0) return std::nullopt;
    return scene;
  }

 private:
  // ---- shapes of values --------------------------------------------------------------------

  const json::object* object(const json::value& v, const Path& at) {
    if (const json::object* o = v.if_object()) return o;
    error(at, fmt::format("expected an object, got {}", json_kind_name(v)));
    return nullptr;
  }

  const json::array* array(const json::value& v, const Path& at, std::size_t max_size, std::string_view what) {
    const json::array* a = v.if_array();
    if (a == nullptr) {
      error(at, fmt::format("expected an array, got {}", json_kind_name(v)));
      return nullptr;
    }
    if (a->size() > max_size) {
      // The elements are not validated: the file is unusable anyway and checking 10M+ of them
      // would only bury this message.
      error(at, fmt::format("too many {}: {} (limit {})", what, a->size(), max_size));
      return nullptr;
    }
    return a;
  }

  const json::value* required(const json::object& o, std::string_view key, const Path& at) {
    if (const json::value* v = o.if_contains(key)) return v;
    error(at.key(key), "required key is missing");
    return nullptr;
  }

  void check_keys(const json::object& o, const Path& at, std::span<const std::string_view> known) {
    for (const auto& member : o) {
      const std::string_view key = member.key();
      if (std::find(known.begin(), known.end(), key) == known.end()) {
        error(at.key(key), unknown_key_message(key, known));
      }
    }
  }

  // Any JSON number that fits a float; -0 becomes +0 so the digest does not see the sign of zero.
  std::optional<double> number(const json::value& v, const Path& at) {
    std::string problem;
    const std::optional<double> number = json_finite_number(v, problem);
    if (!number) {
      error(at, problem);
      return std::nullopt;
    }
    const double d = *number;
    if (std::abs(d) > kFloatMax) {
      error(at, fmt::format("number {} is outside the float range (magnitude at most {})", d, kFloatMax));
      return std::nullopt;
    }
    return d == 0 ? 0.0 : d;
  }

  std::optional<Vec3d> vec3(const json::value& v, const Path& at) {
    const json::array* a = v.if_array();
    if (a == nullptr) {
      error(at, fmt::format("expected an array of 3 numbers, got {}", json_kind_name(v)));
      return std::nullopt;
    }
    if (a->size() != 3) {
      error(at, fmt::format("expected an array of 3 numbers, got {} element{}", a->size(), a->size() == 1 ? "" : "s"));
      return std::nullopt;
    }
    Vec3d out;
    bool ok = true;
    for (std::size_t i = 0; i < 3; ++i) {
      const auto c = number((*a)[i], at.index(i));
      if (c) {
        out[i] = *c;
      } else {
        ok = false;
      }
    }
    return ok ? std::optional<Vec3d>(out) : std::nullopt;
  }

  std::optional<Color> color(const json::value& v, const Path& at) {
    auto c = vec3(v, at);
    if (!c) return std::nullopt;
    bool ok = true;
    for (std::size_t i = 0; i < 3; ++i) {
      if ((*c)[i] < 0) {
        error(at.index(i), fmt::format("must be >= 0 (got {})", (*c)[i]));
        ok = false;
      }
    }
    return ok ? c : std::nullopt;
  }

  // An integer in [lo, hi]. An integral double (640.0, 1e3) is accepted: JSON does not tell them
  // apart and some writers always print a fraction.
  std::optional<std::uint64_t> integer(const json::value& v, const Path& at, std::uint64_t lo, std::uint64_t hi) {
    assert(hi <= kMaxSeed);
    const auto out_of_range = [&](auto got) {
      error(at, fmt::format("must be an integer in [{}, {}] (got {})", lo, hi, got));
      return std::nullopt;
    };
    switch (v.kind()) {
      case json::kind::int64: {
        const std::int64_t i = v.get_int64();
        if (i < 0 || static_cast<std::uint64_t>(i) < lo || static_cast<std::uint64_t>(i) > hi) return out_of_range(i);
        return static_cast<std::uint64_t>(i);
      }
      case json::kind::uint64: {
        const std::uint64_t u = v.get_uint64();
        if (u < lo || u > hi) return out_of_range(u);
        return u;
      }
      case json::kind::double_: {
        const double d = v.get_double();
        if (!std::isfinite(d)) {
          error(at, "number is out of range (overflows a double)");
          return std::nullopt;
        }
        if (d != std::floor(d)) {
          error(at, fmt::format("must be an integer (got {})", d));
          return std::nullopt;
        }
        // Compared in double before converting: a value beyond uint64 must never reach the
        // conversion (undefined behaviour). Every bound is at most 2^53, so exact as a double.
        if (d < static_cast<double>(lo) || d > static_cast<double>(hi)) return out_of_range(d);
        return static_cast<std::uint64_t>(d);
      }
      default:
        error(at, fmt::format("expected an integer, got {}", json_kind_name(v)));
        return std::nullopt;
    }
  }

  // ---- ranges -------------------------------------------------------------------------------

  bool positive(double d, const Path& at) {
    if (d > 0) return true;
    error(at, fmt::format("must be > 0 (got {})", d));
    return false;
  }

  bool non_negative(double d, const Path& at) {
    if (d >= 0) return true;
    error(at, fmt::format("must be >= 0 (got {})", d));
    return false;
  }

  bool in_range(double d, double lo, double hi, const Path& at) {
    if (d >= lo && d <= hi) return true;
    error(at, fmt::format("must be in [{}, {}] (got {})", lo, hi, d));
    return false;
  }

  // Reads optional key `key` of `o` with `read(value, path) -> optional<T>`, storing into
  // `target` (which keeps its default when the key is absent).
  template <typename T, typename Read>
  void optional_field(const json::object& o, std::string_view key, const Path& at, T& target, Read read) {
    if (const json::value* v = o.if_contains(key)) {
      if (auto got = read(*v, at.key(key))) target = static_cast<T>(*got);
    }
  }

  auto number_in(double lo, double hi) {
    return [this, lo, hi](const json::value& v, const Path& at) -> std::optional<double> {
      auto d = number(v, at);
      return d && in_range(*d, lo, hi, at) ? d : std::nullopt;
    };
  }
  auto integer_in(std::uint64_t lo, std::uint64_t hi) {
    return [this, lo, hi](const json::value& v, const Path& at) { return integer(v, at, lo, hi); };
  }
  auto vec3_reader() {
    return [this](const json::value& v, const Path& at) { return vec3(v, at); };
  }
  auto color_reader() {
    return [this](const json::value& v, const Path& at) { return color(v, at); };
  }

  // ---- sections -----------------------------------------------------------------------------

  void read_camera(const json::value& v, const Path& at, Camera& camera) {
    const json::object* o = object(v, at);
    if (o == nullptr) return;
    check_keys(*o, at, kCameraKeys);
    const std::size_t errors_before = error_count_;
    optional_field(*o, "position", at, camera.position, vec3_reader());
    optional_field(*o, "look_at", at, camera.look_at, vec3_reader());
    optional_field(*o, "up", at, camera.up, vec3_reader());
    if (const json::value* f = o->if_contains("fov")) {
      const Path fov_at = at.key("fov");
      if (auto d = number(*f, fov_at)) {
        if (*d > 0 && *d < 180) {
          camera.fov_deg = *d;
        } else {
          error(fov_at, fmt::format("must be in the open interval (0, 180) (got {})", *d));
        }
      }
    }
    if (error_count_ != errors_before) return;  // the geometry checks need every vector

    // Compared as floats because the renderer builds its camera from floats.
    if (Vec3f(camera.position) == Vec3f(camera.look_at)) {
      error(at.key("look_at"), "must differ from the camera position");
      return;
    }
    const double up_scale = math::max_component(math::abs(camera.up));
    if (up_scale == 0) {
      error(at.key("up"), "must not be the zero vector");
      return;
    }
    const Vec3d dir = camera.look_at - camera.position;
    const Vec3d u = camera.up / up_scale;
    const Vec3d d = dir / math::max_component(math::abs(dir));
    if (math::length(math::cross(u, d)) < kParallelTolerance * math::length(u) * math::length(d)) {
      error(at.key("up"), "must not be parallel to the view direction (look_at - position)");
    }
  }

  void read_render(const json::value& v, const Path& at, RenderSettings& render) {
    const json::object* o = object(v, at);
    if (o == nullptr) return;
    check_keys(*o, at, kRenderKeys);
    optional_field(*o, "width", at, render.width, integer_in(1, kMaxImageSide));
    optional_field(*o, "height", at, render.height, integer_in(1, kMaxImageSide));
    optional_field(*o, "samples", at, render.samples, integer_in(1, kMaxSamples));
    optional_field(*o, "max_depth", at, render.max_depth, integer_in(0, kMaxDepth));
    optional_field(*o, "background", at, render.background, color_reader());
    optional_field(*o, "seed", at, render.seed, integer_in(0, kMaxSeed));
    optional_field(*o, "frame", at, render.frame, integer_in(0, std::numeric_limits<std::uint32_t>::max()));
    optional_field(*o, "error_target", at, render.error_target, number_in(0, kMaxErrorTarget));
    optional_field(*o, "min_samples", at, render.min_samples, integer_in(1, kMaxSamples));
  }

  void read_material(const json::value& v, const Path& at, Material& m) {
    const json::object* o = object(v, at);
    if (o == nullptr) return;
    check_keys(*o, at, kMaterialKeys);
    const std::size_t errors_before = error_count_;
    optional_field(*o, "color", at, m.color, color_reader());
    optional_field(*o, "diffuse", at, m.diffuse, number_in(0, 1));
    optional_field(*o, "specular", at, m.specular, number_in(0, 1));
    optional_field(*o, "shininess", at, m.shininess, number_in(0, kMaxShininess));
    optional_field(*o, "reflectivity", at, m.reflectivity, number_in(0, 1));
    optional_field(*o, "transparency", at, m.transparency, number_in(0, 1));
    if (const json::value* i = o->if_contains("ior")) {
      const Path ior_at = at.key("ior");
      if (auto d = number(*i, ior_at); d && positive(*d, ior_at)) m.ior = *d;
    }
    if (error_count_ == errors_before && m.reflectivity + m.transparency > 1 + kEnergySlack) {
      error(at, fmt::format("reflectivity + transparency must be <= 1 (got {} + {})", m.reflectivity, m.transparency));
    }
  }

  std::optional<Object> read_object(const json::value& v, const Path& at) {
    const json::object* o = object(v, at);
    if (o == nullptr) return std::nullopt;
    const std::size_t errors_before = error_count_;

    Object out;
    bool known_type = false;
    if (const json::value* t = required(*o, "type", at)) {
      const Path type_at = at.key("type");
      if (const json::string* s = t->if_string()) {
        known_type = true;
        if (*s == "sphere") {
          out.type = ObjectType::kSphere;
        } else if (*s == "box") {
          out.type = ObjectType::kBox;
        } else if (*s == "plane") {
          out.type = ObjectType::kPlane;
        } else if (*s == "mesh") {
          out.type = ObjectType::kMesh;
        } else {
          known_type = false;
          error(type_at,
                fmt::format("unknown object type \"{}\"; known types: sphere, box, plane, mesh", std::string_view(*s)));
        }
      } else {
        error(type_at, fmt::format("expected a string (sphere, box, plane or mesh), got {}", json_kind_name(*t)));
      }
    }

    if (!known_type) {
      check_keys(*o, at, kAnyObjectKeys);
    } else {
      switch (out.type) {
        case ObjectType::kSphere:
          read_sphere(*o, at, out.sphere);
          break;
        case ObjectType::kBox:
          read_box(*o, at, out.box);
          break;
        case ObjectType::kPlane:
          read_plane(*o, at, out.plane);
          break;
        case ObjectType::kMesh:
          read_mesh(*o, at, out);
          break;
      }
    }
    if (const json::value* m = o->if_contains("material")) read_material(*m, at.key("material"), out.material);
    if (!known_type || error_count_ != errors_before) return std::nullopt;
    return out;
  }

  void read_sphere(const json::object& o, const Path& at, Sphere& sphere) {
    check_keys(o, at, kSphereKeys);
    if (const json::value* v = required(o, "loc", at)) {
      if (auto c = vec3(*v, at.key("loc"))) sphere.center = *c;
    }
    if (const json::value* v = required(o, "radius", at)) {
      const Path radius_at = at.key("radius");
      if (auto r = number(*v, radius_at); r && positive(*r, radius_at)) sphere.radius = *r;
    }
  }

  // A box is written either as centre and full edge lengths ("loc", "size"; the friendly form)
  // or as corners ("min", "max"; the canonical form, which round-trips bit for bit).
  void read_box(const json::object& o, const Path& at, Box& box) {
    check_keys(o, at, kBoxKeys);
    const bool centre_form = o.contains("loc") || o.contains("size");
    const bool corner_form = o.contains("min") || o.contains("max");
    if (centre_form && corner_form) {
      error(at, "a box takes either \"loc\" and \"size\" or \"min\" and \"max\", not both");
      return;
    }
    if (corner_form) {
      const json::value* min_v = required(o, "min", at);
      const json::value* max_v = required(o, "max", at);
      const Path min_at = at.key("min");
      const Path max_at = at.key("max");
      const std::optional<Vec3d> lo_read = min_v ? vec3(*min_v, min_at) : std::nullopt;
      const std::optional<Vec3d> hi_read = max_v ? vec3(*max_v, max_at) : std::nullopt;
      if (!lo_read || !hi_read) return;
      // Plain copies: GCC 12 warns (falsely) that the optionals' payloads may be uninitialised.
      const Vec3d lo = lo_read.value(), hi = hi_read.value();
      for (std::size_t i = 0; i < 3; ++i) {
        if (!(lo[i] < hi[i])) {
          error(max_at.index(i), fmt::format("must be greater than min (got {} <= {})", hi[i], lo[i]));
        }
      }
      box = Box{lo, hi};
      return;
    }
    const json::value* loc_v = required(o, "loc", at);
    const json::value* size_v = required(o, "size", at);
    const Path size_at = at.key("size");
    const auto centre = loc_v ? vec3(*loc_v, at.key("loc")) : std::nullopt;
    const auto size = size_v ? vec3(*size_v, size_at) : std::nullopt;
    bool ok = centre && size;
    if (size) {
      for (std::size_t i = 0; i < 3; ++i) ok = positive((*size)[i], size_at.index(i)) && ok;
    }
    if (!ok) return;
    const Vec3d half = *size * 0.5;
    box = Box{*centre - half, *centre + half};
    for (std::size_t i = 0; i < 3; ++i) {
      if (!(box.min[i] < box.max[i])) {
        error(size_at.index(i), "too small to be represented at this location (min and max round to the same value)");
        return;
      }
    }
    if (math::max_component(math::max(math::abs(box.min), math::abs(box.max))) > kFloatMax) {
      error(at, "box extends beyond the float range");
    }
  }

  void read_plane(const json::object& o, const Path& at, Plane& plane) {
    check_keys(o, at, kPlaneKeys);
    if (const json::value* v = required(o, "loc", at)) {
      if (auto p = vec3(*v, at.key("loc"))) plane.point = *p;
    }
    if (const json::value* v = required(o, "normal", at)) {
      const Path normal_at = at.key("normal");
      if (auto n = vec3(*v, normal_at)) {
        if (auto unit = unit_length(*n)) {
          plane.normal = *unit;
        } else {
          error(normal_at, "must not be zero length");
        }
      }
    }
  }

  // "scale": one number for all axes or one per axis; each non-zero (a zero flattens the mesh
  // into degenerate triangles, surely a mistake) and within the float range.
  std::optional<Vec3d> scale(const json::value& v, const Path& at) {
    std::optional<Vec3d> s;
    if (v.is_array()) {
      s = vec3(v, at);
    } else if (auto d = number(v, at)) {
      s = Vec3d{*d, *d, *d};
    }
    if (!s) return std::nullopt;
    for (std::size_t i = 0; i < 3; ++i) {
      if ((*s)[i] == 0) {
        error(v.is_array() ? at.index(i).str() : at.str(), "must not be zero");
        return std::nullopt;
      }
    }
    return s;
  }

  // A Wavefront OBJ, from a file or inline, placed by scale, rotate, translate (description.h).
  void read_mesh(const json::object& o, const Path& at, Object& out) {
    check_keys(o, at, kMeshKeys);
    const std::size_t errors_before = error_count_;
    auto mesh = std::make_shared<Mesh>();
    optional_field(o, "translate", at, mesh->translate, vec3_reader());
    optional_field(o, "rotate", at, mesh->rotate_deg, vec3_reader());
    optional_field(o, "scale", at, mesh->scale, [this](const json::value& v, const Path& p) { return scale(v, p); });

    const json::value* file_v = o.if_contains("file");
    const json::value* obj_v = o.if_contains("obj");
    if (file_v != nullptr && obj_v != nullptr) {
      error(at, "a mesh takes either \"file\" (an OBJ file) or \"obj\" (the OBJ text inline), not both");
      return;
    }
    if (file_v == nullptr && obj_v == nullptr) {
      error(at, "a mesh needs \"file\" (an OBJ file) or \"obj\" (the OBJ text inline)");
      return;
    }
    const Path source_at = at.key(file_v != nullptr ? "file" : "obj");
    const json::value& source = file_v != nullptr ? *file_v : *obj_v;
    const json::string* text = source.if_string();
    if (text == nullptr) {
      error(source_at, fmt::format("expected a string, got {}", json_kind_name(source)));
      return;
    }
    if (file_v != nullptr) {
      mesh->file = std::string(*text);
      if (!read_mesh_file(*mesh, source_at)) return;
    } else {
      mesh->obj = std::string(*text);
    }
    if (error_count_ != errors_before) return;

    // Messages about a file's content name the file, so "line 7" can be found.
    const std::string prefix = mesh->file.empty() ? std::string() : mesh->file + ": ";
    std::vector<std::string> problems;
    if (!build_obj_mesh(*mesh, options_.max_triangles - triangles_, problems)) {
      for (const std::string& p : problems) error(source_at, prefix + p);
      return;
    }
    triangles_ += mesh->triangle_count();
    if (mesh->triangle_count() == 0) warning(source_at, prefix + "the OBJ has no faces: the mesh is invisible");
    out.mesh = std::move(mesh);
  }

  bool read_mesh_file(Mesh& mesh, const Path& at) {
    if (!options_.allow_mesh_files) {
      error(at, fmt::format("mesh file \"{}\" not accepted here: a scene sent to a collector or worker must carry its "
                            "meshes inline as \"obj\" (dtraced submit inlines them)",
                            mesh.file));
      return false;
    }
    if (mesh.file.empty()) {
      error(at, "must name an OBJ file");
      return false;
    }
    const std::filesystem::path relative(mesh.file);
    const std::filesystem::path path = relative.is_absolute() || options_.base_dir.empty()
                                           ? relative
                                           : std::filesystem::path(options_.base_dir) / relative;
    std::string read_error;
    std::optional<std::string> text = util::read_file_limited(path.string(), options_.max_obj_bytes, read_error);
    if (!text) {
      error(at, read_error);
      return false;
    }
    // The canonical form carries the text inside a JSON string, which must be UTF-8.
    if (const std::size_t line = first_invalid_utf8_line(*text); line != 0) {
      error(at, fmt::format("{}: line {}: not valid UTF-8 (an OBJ is inlined into the scene as JSON text)", mesh.file,
                            line));
      return false;
    }
    mesh.obj = std::move(*text);
    return true;
  }

  std::optional<Light> read_light(const json::value& v, const Path& at) {
    const json::object* o = object(v, at);
    if (o == nullptr) return std::nullopt;
    const std::size_t errors_before = error_count_;
    Light light;
    bool known_type = false;
    if (const json::value* t = required(*o, "type", at)) {
      const json::string* s = t->if_string();
      if (s == nullptr) {
        error(at.key("type"),
              fmt::format("expected a string (point, sphere, disk or rect), got {}", json_kind_name(*t)));
      } else if (auto type = light_type(*s)) {
        light.type = *type;
        known_type = true;
      } else {
        error(at.key("type"),
              fmt::format("unknown light type \"{}\"; known types: point, sphere, disk, rect", std::string_view(*s)));
      }
    }
    if (!known_type) {
      check_keys(*o, at, kAnyLightKeys);
    } else {
      switch (light.type) {
        case LightType::kPoint:
          check_keys(*o, at, kPointLightKeys);
          break;
        case LightType::kSphere:
          check_keys(*o, at, kSphereLightKeys);
          break;
        case LightType::kDisk:
          check_keys(*o, at, kDiskLightKeys);
          break;
        case LightType::kRect:
          check_keys(*o, at, kRectLightKeys);
          break;
      }
    }
    if (const json::value* p = required(*o, "loc", at)) {
      if (auto loc = vec3(*p, at.key("loc"))) light.position = *loc;
    }
    optional_field(*o, "color", at, light.color, color_reader());
    if (const json::value* i = o->if_contains("intensity")) {
      const Path intensity_at = at.key("intensity");
      if (auto d = number(*i, intensity_at); d && non_negative(*d, intensity_at)) light.intensity = *d;
    }
    if (!known_type) return std::nullopt;
    if (light.is_area()) {
      optional_field(*o, "samples", at, light.samples, integer_in(1, kMaxLightSamples));
      if (const json::value* c = o->if_contains("cast_shadows")) {
        if (c->is_bool()) {
          light.cast_shadows = c->get_bool();
        } else {
          error(at.key("cast_shadows"), fmt::format("expected true or false, got {}", json_kind_name(*c)));
        }
      }
    }
    if (light.type == LightType::kSphere || light.type == LightType::kDisk) {
      if (const json::value* r = required(*o, "radius", at)) {
        const Path radius_at = at.key("radius");
        if (auto d = number(*r, radius_at); d && positive(*d, radius_at)) light.radius = *d;
      }
    }
    if (light.type == LightType::kDisk) {
      if (const json::value* n = required(*o, "normal", at)) {
        const Path normal_at = at.key("normal");
        if (auto got = vec3(*n, normal_at)) {
          if (auto unit = unit_length(*got)) {
            light.normal = *unit;
          } else {
            error(normal_at, "must not be zero length");
          }
        }
      }
    }
    if (light.type == LightType::kRect) read_rect_light(*o, at, light);
    if (error_count_ != errors_before) return std::nullopt;
    return light;
  }

  static std::optional<LightType> light_type(std::string_view name) {
    if (name == "point") return LightType::kPoint;
    if (name == "sphere") return LightType::kSphere;
    if (name == "disk") return LightType::kDisk;
    if (name == "rect") return LightType::kRect;
    return std::nullopt;
  }

  // A rect light's edges and emitting side: "u" and "v" are required; "normal" is optional (by
  // default the side of cross(u, v)) and, when given, must be parallel to cross(u, v).
  void read_rect_light(const json::object& o, const Path& at, Light& light) {
    std::optional<Vec3d> u, v;
    if (const json::value* j = required(o, "u", at)) u = vec3(*j, at.key("u"));
    if (const json::value* j = required(o, "v", at)) v = vec3(*j, at.key("v"));
    if (!u || !v) return;
    const double u_scale = math::max_component(math::abs(*u)), v_scale = math::max_component(math::abs(*v));
    if (u_scale == 0 || v_scale == 0) {
      error(at.key(u_scale == 0 ? "u" : "v"), "must not be the zero vector");
      return;
    }
    const Vec3d us = *u / u_scale, vs = *v / v_scale;
    const Vec3d c = math::cross(us, vs);
    // Parallel edges: the rectangle would have no area. Same tolerance as the camera's up.
    if (math::length(c) < kParallelTolerance * math::length(us) * math::length(vs)) {
      error(at.key("v"), "must not be parallel to \"u\": the rectangle would have no area");
      return;
    }
    light.edge_u = *u;
    light.edge_v = *v;
    Vec3d normal = c / math::length(c);
    if (const json::value* j = o.if_contains("normal")) {
      const Path normal_at = at.key("normal");
      const auto n = vec3(*j, normal_at);
      if (!n) return;
      const auto unit = unit_length(*n);
      if (!unit) {
        error(normal_at, "must not be zero length");
        return;
      }
      const double cosine = math::dot(*unit, normal);
      if (std::abs(cosine) < 1.0 - 1e-6) {
        error(normal_at,
              "must be perpendicular to both edges \"u\" and \"v\" (it only picks the side the light emits on)");
        return;
      }
      if (cosine < 0) normal = -normal;
    }
    light.normal = normal;
  }

  std::string file_;
  std::size_t max_errors_;
  const LoadOptions& options_;
  std::size_t triangles_ = 0;  // of the meshes read so far, against options_.max_triangles
  std::size_t error_count_ = 0;
  util::Errors errors_;
  util::Errors warnings_;
};

}  // namespace

std::string format_errors(const util::Errors& errors) {
  std::string out;
  for (const util::Error& e : errors) {
    out += e.to_string();
    out += '\n';
  }
  return out;
}

LoadResult load_scene_string(std::string_view text, const std::string& file_name, const LoadOptions& options) {
  Validator validator(file_name, options);
  if (text.size() > options.max_bytes) {
    validator.error(std::string(), fmt::format("scene is {} bytes, larger than the limit of {} bytes", text.size(),
                                               options.max_bytes));
    return validator.finish(std::nullopt);
  }
  // The parsed tree lives only for this call; a monotonic arena makes building and dropping a
  // large one cheap.
  json::monotonic_resource arena;
  JsonDocument doc = read_json_strict(text, kMaxJsonDepth, options.max_errors, &arena);
  for (JsonIssue& issue : doc.issues) validator.error(std::move(issue.path), std::move(issue.message));
  if (!doc.parsed) return validator.finish(std::nullopt);
  // Duplicate keys do not stop validation: the rest of the file still gets checked.
  return validator.finish(validator.read_scene(doc.value));
}

LoadResult load_scene_file(const std::string& path, const LoadOptions& options) {
  std::string read_error;
  const std::optional<std::string> text = util::read_file_limited(path, options.max_bytes, read_error);
  if (!text) {
    // read_file_limited prefixes its message with the path, which the Error carries already.
    const std::string prefix = path + ": ";
    if (read_error.starts_with(prefix)) read_error.erase(0, prefix.size());
    LoadResult result;
    result.errors.push_back({std::move(read_error), "", path});
    return result;
  }
  // Mesh files are named relative to the scene file, wherever the process runs from.
  LoadOptions with_base = options;
  with_base.base_dir = std::filesystem::path(path).parent_path().string();
  return load_scene_string(*text, path, with_base);
}

}  // namespace dtraced::scene
