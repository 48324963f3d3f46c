// Objects, their materials and meshes, and lights: the elements of "scene_objects" and
// "scene_lights" (load_objects.h).
#include "scene/load_objects.h"

#include <cfloat>
#include <cmath>
#include <filesystem>
#include <limits>
#include <memory>
#include <span>

#include <boost/json/object.hpp>
#include <boost/json/string.hpp>
#include <fmt/format.h>

#include "jsonio/utf8.h"
#include "math/vec.h"
#include "scene/load_animation.h"
#include "scene/obj_mesh.h"
#include "scene/scene_json.h"
#include "util/file.h"

namespace dtraced::scene::detail {
namespace {

namespace json = boost::json;
using jsonio::Need;
using jsonio::Path;

constexpr double kFloatMax = FLT_MAX;
constexpr double kInfinity = std::numeric_limits<double>::infinity();
constexpr double kMaxShininess = 1e4;
// Decimal fractions such as 0.3 + 0.7 may sum to a hair above 1 in binary; that is not a mistake
// worth rejecting; the shader's weight 1 - reflectivity - transparency then dips at most 1e-9
// below zero, which is harmless.
constexpr double kEnergySlack = 1e-9;
// Edges count as parallel when |u x v| < kParallelTolerance |u| |v| (as the camera's up does).
constexpr double kParallelTolerance = 1e-6;
// A normal this close to unit length is kept as written (see unit_length).
constexpr double kUnitTolerance = 1e-12;

// The limits of description.h, derived from what shading computes in float (render/).
//
// Sizes: the renderer holds every size as a float, so a radius or an ior must round to a normal
// float (1e-46 rounds to 0: the sphere vanishes, or an ior of 0 divides by zero).
//
// ior: a refraction uses eta = ior_after / ior_before, both scene iors (or 1, outside), and
// computes eta^2, 1 / eta and eta * cos (render/shading.h, dielectric_interface). With every ior
// in [2^-31, 2^31], eta lies in [2^-62, 2^62] and eta^2 in [2^-124, 2^124]: a normal float, never
// 0 or +Inf (an Inf eta^2 made the Fresnel term Inf / Inf = NaN).
//
// Sphere and disk light radius: light sampling squares the radius in float (r^2 of a sphere's
// cone, pi r^2 the disk's area), so r in [2^-63, 2^63] keeps r^2 in [2^-126, 2^126] (and
// pi r^2 < 2^128): normal and finite.
//
// Radiance and albedo: a path's radiance is, at each bounce, the direct light (each light's term
// clamped to render::kMaxLightTerm = 2^100, at most kMaxLights < 2^14 lights: < 2^114) plus at
// most (reflectivity + transparency) <= 1 (+1e-9) times colour times what the next bounce returns;
// a path ends in the background, an area light's emission, or after max_depth <= 64 bounces. With
// material colour <= 1 (kMaxAlbedo) nothing is amplified, so a sample is at most
// (64 + 1) * max(2^114, emission, background) * (1 + 1e-9)^64 < 2^7 * max(2^114, E): with
// light colour * intensity and background <= 2^120 (kMaxRadiance), < 2^127 < FLT_MAX. A colour
// above 1 is no such bound: between two mirrors it multiplies radiance by colour^max_depth (a
// colour of 3.4e38 overflows in one bounce), and an emission near FLT_MAX overflows as soon as
// two terms are summed.

// Whether d becomes a normal float (not 0, not subnormal, not infinite) once rounded to float.
bool normal_as_float(double d) { return std::fpclassify(static_cast<float>(d)) == FP_NORMAL; }

using Keys = std::span<const std::string_view>;
constexpr std::array<std::string_view, 7> kMaterialKeys = {"color",        "diffuse",      "specular", "shininess",
                                                           "reflectivity", "transparency", "ior"};
// The material's plain numbers and their ranges, kMaterialKeys[1] to [5] in that order: the one
// table both read_material and the events' fast path (plain_material) check against.
struct MaterialRange {
  std::string_view key;
  double lo, hi;
  double Material::*field;
};
constexpr std::array<MaterialRange, 5> kMaterialRanges = {{
    {"diffuse", 0, 1, &Material::diffuse},
    {"specular", 0, 1, &Material::specular},
    {"shininess", 0, kMaxShininess, &Material::shininess},
    {"reflectivity", 0, 1, &Material::reflectivity},
    {"transparency", 0, 1, &Material::transparency},
}};
constexpr bool ranges_follow_color() {
  for (std::size_t i = 0; i < kMaterialRanges.size(); ++i) {
    if (kMaterialRanges[i].key != kMaterialKeys[i + 1]) return false;
  }
  return kMaterialKeys[0] == "color" && kMaterialKeys[kMaterialRanges.size() + 1] == "ior";
}
static_assert(ranges_follow_color());
constexpr std::array<std::string_view, 4> kSphereKeys = {"type", "loc", "radius", "material"};
constexpr std::array<std::string_view, 6> kBoxKeys = {"type", "loc", "size", "min", "max", "material"};
constexpr std::array<std::string_view, 4> kPlaneKeys = {"type", "loc", "normal", "material"};
constexpr std::array<std::string_view, 7> kMeshKeys = {"type",   "file",  "obj",     "translate",
                                                       "rotate", "scale", "material"};
// Keys checked when an object's type is missing or unknown, so typos are still reported.
constexpr std::array<std::string_view, 13> kAnyObjectKeys = {
    "type", "loc", "radius", "size", "min", "max", "normal", "material", "file", "obj", "translate", "rotate", "scale"};
// Indexed by the position of the type in kLightTypeNames (point, sphere, disk, rect).
constexpr std::array<std::string_view, 4> kPointLightKeys = {"type", "loc", "color", "intensity"};
constexpr std::array<std::string_view, 7> kSphereLightKeys = {"type",      "loc",     "radius",      "color",
                                                              "intensity", "samples", "cast_shadows"};
constexpr std::array<std::string_view, 8> kDiskLightKeys = {"type",  "loc",       "radius",  "normal",
                                                            "color", "intensity", "samples", "cast_shadows"};
constexpr std::array<std::string_view, 9> kRectLightKeys = {"type",  "loc",       "u",       "v",           "normal",
                                                            "color", "intensity", "samples", "cast_shadows"};
constexpr std::array<Keys, 4> kLightKeys = {kPointLightKeys, kSphereLightKeys, kDiskLightKeys, kRectLightKeys};
// Keys checked when a light's type is missing or unknown.
constexpr std::array<std::string_view, 10> kAnyLightKeys = {"type", "loc",   "radius",    "normal",  "u",
                                                            "v",    "color", "intensity", "samples", "cast_shadows"};

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
    const std::size_t n = jsonio::utf8_at(text, i).length;
    if (n == 0) return line;
    line += text[i] == '\n';
    i += n;
  }
  return 0;
}

// Reads one object or light; holds only references, so one is made per element.
class ObjectReader {
 public:
  explicit ObjectReader(SceneReader& s) : s_(s), r_(s.r) {}

 private:
  // ---- value readers, for jsonio::Fields::read --------------------------------------------------

  auto vec3() {
    return [this](const json::value& v, const Path& at) { return read_vec3(r_, v, at); };
  }
  auto color() {
    return [this](const json::value& v, const Path& at) { return read_color(r_, v, at); };
  }
  auto float_in(double lo, double hi) {
    return [this, lo, hi](const json::value& v, const Path& at) -> std::optional<double> {
      const auto d = read_float(r_, v, at);
      return d && r_.in_range(*d, at, lo, hi) ? d : std::nullopt;
    };
  }
  auto positive_float() {
    return [this](const json::value& v, const Path& at) -> std::optional<double> {
      const auto d = read_float(r_, v, at);
      if (!d || !r_.positive(*d, at)) return std::nullopt;
      if (!normal_as_float(*d)) {
        r_.error(at, fmt::format("{} is too small for the renderer's float arithmetic: it must round to a normal "
                                 "float (at least {:g})",
                                 *d, double(FLT_MIN)));
        return std::nullopt;
      }
      return d;
    };
  }
  // A positive size in [lo, hi], with why in the message.
  auto size_in(double lo, double hi, std::string_view why) {
    return [this, lo, hi, why](const json::value& v, const Path& at) -> std::optional<double> {
      const auto d = read_float(r_, v, at);
      if (!d || !r_.positive(*d, at)) return std::nullopt;
      if (!(*d >= lo && *d <= hi)) {
        r_.error(at, fmt::format("must be in [{:g}, {:g}] ({}) (got {})", lo, hi, why, *d));
        return std::nullopt;
      }
      return d;
    };
  }
  // A material colour: every channel in [0, kMaxAlbedo].
  auto albedo() {
    return [this](const json::value& v, const Path& at) -> std::optional<Color> {
      const auto c = read_color(r_, v, at);
      if (!c) return std::nullopt;
      bool ok = true;
      for (std::size_t i = 0; i < 3; ++i) {
        if ((*c)[i] > kMaxAlbedo) {
          r_.error(at.index(i), fmt::format("must be at most {} (a surface reflects no more light than it receives; "
                                            "above 1, light between mirrors grows without bound) (got {})",
                                            kMaxAlbedo, (*c)[i]));
          ok = false;
        }
      }
      return ok ? c : std::nullopt;
    };
  }
  auto unit_vector() {
    return [this](const json::value& v, const Path& at) -> std::optional<Vec3d> {
      const auto n = read_vec3(r_, v, at);
      if (!n) return std::nullopt;
      const auto unit = unit_length(*n);
      if (!unit) r_.error(at, "must not be zero length");
      return unit;
    };
  }

  // A value that may be animated (load_animation.h).
  template <typename T, typename Read>
  bool animatable(jsonio::Fields& f, std::string_view key, T& out, Need need, Target target, Read read,
                  Span* span = nullptr, Track** track = nullptr) {
    return read_animatable(s_, f, key, out, need, target, read, span, track);
  }

  void check_keys(const json::object& o, const Path& at, Keys known) { r_.check_keys(o, at, known, kKeyAliases); }

  // The index in `names` of the required "type", or nullopt after reporting why there is none.
  std::optional<std::size_t> type_of(const json::object& o, const Path& at, Keys names, std::string_view what) {
    const json::value* t = r_.get(o, "type", at, Need::kRequired);
    return t != nullptr ? r_.choice(*t, at.key("type"), names, what, "types") : std::nullopt;
  }

  // ---- objects -------------------------------------------------------------------------------

  void read_material(const json::value& v, const Path& at, Material& m) {
    const json::object* o = r_.object(v, at);
    if (o == nullptr) return;
    jsonio::Fields f(r_, *o, at, kMaterialKeys, kKeyAliases);
    const std::size_t errors_before = r_.error_count();
    animatable(f, "color", m.color, Need::kOptional, Target::kMaterialColor, albedo());
    for (const MaterialRange& range : kMaterialRanges) {
      f.read(range.key, m.*range.field, Need::kOptional, float_in(range.lo, range.hi));
    }
    f.read("ior", m.ior, Need::kOptional,
           size_in(kMinIor, kMaxIor, "2^-31 to 2^31: refraction squares ratios of iors"));
    if (r_.error_count() == errors_before && m.reflectivity + m.transparency > 1 + kEnergySlack) {
      r_.error(at,
               fmt::format("reflectivity + transparency must be <= 1 (got {} + {})", m.reflectivity, m.transparency));
    }
  }

  void read_sphere(jsonio::Fields& f, Sphere& sphere) {
    const std::size_t errors_before = r_.error_count();
    check_keys(f.object(), f.at(), kSphereKeys);
    Span centre, radius;
    animatable(f, "loc", sphere.center, Need::kRequired, Target::kObjectLoc, vec3(), &centre);
    animatable(f, "radius", sphere.radius, Need::kRequired, Target::kSphereRadius, positive_float(), &radius);
    // The renderer skips a sphere whose bounds are not finite floats: say so rather than lose it.
    // Checked at the largest centre and radius the keys reach, so it holds at every time.
    if (r_.error_count() != errors_before) return;
    for (std::size_t i = 0; i < 3; ++i) {
      if (!std::isfinite(static_cast<float>(centre.max_abs()[i] + radius.hi.x))) {
        r_.error(f.path("radius"), "sphere extends beyond the float range");
        return;
      }
    }
  }

  // A box is written either as centre and full edge lengths ("loc", "size"; the friendly form)
  // or as corners ("min", "max"; the canonical form, which round-trips bit for bit).
  void read_box(jsonio::Fields& f, Box& box) {
    check_keys(f.object(), f.at(), kBoxKeys);
    const bool centre_form = f.has("loc") || f.has("size");
    const bool corner_form = f.has("min") || f.has("max");
    if (centre_form && corner_form) {
      r_.error(f.at(), "a box takes either \"loc\" and \"size\" or \"min\" and \"max\", not both");
      return;
    }
    if (corner_form) {
      std::optional<Vec3d> lo, hi;
      f.read("min", lo, Need::kRequired, vec3());
      f.read("max", hi, Need::kRequired, vec3());
      if (!lo || !hi) return;
      const Path max_at = f.path("max");
      for (std::size_t i = 0; i < 3; ++i) {
        if (!((*lo)[i] < (*hi)[i])) {
          r_.error(max_at.index(i), fmt::format("must be greater than min (got {} <= {})", (*hi)[i], (*lo)[i]));
        }
      }
      box = Box{*lo, *hi};
      return;
    }
    Vec3d centre;
    Span span;
    Track* track = nullptr;
    std::optional<Vec3d> size;
    bool ok = animatable(f, "loc", centre, Need::kRequired, Target::kObjectLoc, vec3(), &span, &track);
    f.read("size", size, Need::kRequired, vec3());
    const Path size_at = f.path("size");
    ok = ok && size;
    if (size) {
      for (std::size_t i = 0; i < 3; ++i) ok = r_.positive((*size)[i], size_at.index(i)) && ok;
    }
    if (!ok) return;
    const Vec3d half = *size * 0.5;
    box = Box{centre - half, centre + half};
    if (track != nullptr) track->box_size = *size;  // the box at time t is loc(t) -+ size / 2
    // A moving box keeps min < max wherever its centre goes within the keys' range: the two
    // roundings of c -+ half err by at most one spacing of doubles at |c| + half, together.
    const Vec3d far = span.max_abs() + half;
    for (std::size_t i = 0; i < 3; ++i) {
      const bool collapses =
          track == nullptr ? !(box.min[i] < box.max[i]) : !(2 * half[i] > std::nextafter(far[i], kInfinity) - far[i]);
      if (collapses) {
        r_.error(size_at.index(i),
                 "too small to be represented at this location (min and max round to the same value)");
        return;
      }
    }
    const Vec3d reach = math::max(math::abs(box.min), math::abs(box.max));
    if (math::max_component(track == nullptr ? reach : math::max(reach, far)) > kFloatMax) {
      r_.error(f.at(), "box extends beyond the float range");
    }
  }

  void read_plane(jsonio::Fields& f, Plane& plane) {
    check_keys(f.object(), f.at(), kPlaneKeys);
    animatable(f, "loc", plane.point, Need::kRequired, Target::kObjectLoc, vec3());
    f.read("normal", plane.normal, Need::kRequired, unit_vector());
  }

  // "scale": one number for all axes or one per axis; each non-zero (a zero flattens the mesh
  // into degenerate triangles, surely a mistake) and within the float range.
  std::optional<Vec3d> scale(const json::value& v, const Path& at) {
    std::optional<Vec3d> s;
    if (v.is_array()) {
      s = read_vec3(r_, v, at);
    } else if (auto d = read_float(r_, v, at)) {
      s = Vec3d{*d, *d, *d};
    }
    if (!s) return std::nullopt;
    for (std::size_t i = 0; i < 3; ++i) {
      if ((*s)[i] == 0) {
        r_.error(v.is_array() ? at.index(i).str() : at.str(), "must not be zero");
        return std::nullopt;
      }
    }
    return s;
  }

  // A Wavefront OBJ, from a file or inline, placed by scale, rotate, translate (description.h).
  void read_mesh(jsonio::Fields& f, Object& out) {
    check_keys(f.object(), f.at(), kMeshKeys);
    const std::size_t errors_before = r_.error_count();
    auto mesh = std::make_shared<Mesh>();
    Span translate, scale_span;
    Track* scale_track = nullptr;
    const std::size_t tracks_before = s_.animation.tracks.size();
    animatable(f, "translate", mesh->translate, Need::kOptional, Target::kMeshTranslate, vec3(), &translate);
    animatable(f, "rotate", mesh->rotate_deg, Need::kOptional, Target::kMeshRotate, vec3());
    animatable(
        f, "scale", mesh->scale, Need::kOptional, Target::kMeshScale,
        [this](const json::value& v, const Path& at) { return scale(v, at); }, &scale_span, &scale_track);
    if (scale_track != nullptr) check_scale_signs(*scale_track, f.path("scale"));
    const bool moves = s_.animation.tracks.size() != tracks_before;

    const bool from_file = f.has("file");
    if (from_file && f.has("obj")) {
      r_.error(f.at(), "a mesh takes either \"file\" (an OBJ file) or \"obj\" (the OBJ text inline), not both");
      return;
    }
    if (!from_file && !f.has("obj")) {
      r_.error(f.at(), "a mesh needs \"file\" (an OBJ file) or \"obj\" (the OBJ text inline)");
      return;
    }
    const Path source_at = f.path(from_file ? "file" : "obj");
    std::string text;
    if (!f.string(from_file ? "file" : "obj", text, std::numeric_limits<std::size_t>::max())) return;
    if (from_file) {
      mesh->file = std::move(text);
      if (!read_mesh_file(*mesh, source_at)) return;
    } else {
      mesh->obj = std::move(text);
    }
    if (r_.error_count() != errors_before) return;

    // Messages about a file's content name the file, so "line 7" can be found. Both the name and
    // the messages (which quote the OBJ text) come from the scene: escaped for display.
    const std::string prefix = mesh->file.empty() ? std::string() : jsonio::printable(mesh->file) + ": ";
    const auto built = build_obj_mesh(*mesh, s_.options.max_triangles - s_.triangles);
    if (!built) {
      for (const util::Error& e : built.error()) r_.error(source_at, prefix + jsonio::printable(e.message));
      return;
    }
    if (moves && !stays_in_float_range(*mesh, translate, scale_span, source_at)) return;
    s_.triangles += mesh->triangle_count();
    if (mesh->triangle_count() == 0) s_.warning(source_at, prefix + "the OBJ has no faces: the mesh is invisible");
    out.mesh = std::move(mesh);
  }

  // Between two keys of opposite sign a scale would pass through zero (a flat mesh, or a mirrored
  // one: neither is a motion anyone means).
  void check_scale_signs(const Track& track, const Path& at) {
    const Path keys_at = at.key("keys");
    const Vec3d first = track.keys.front().value;
    for (std::size_t k = 1; k < track.keys.size(); ++k) {
      for (std::size_t c = 0; c < 3; ++c) {
        if ((track.keys[k].value[c] > 0) != (first[c] > 0)) {
          const Path key_at = keys_at.index(k);
          r_.error(key_at.key("value"),
                   fmt::format("component {} must have the sign of the first key's ({}): between them the scale "
                               "would pass through zero (got {})",
                               c, first[c], track.keys[k].value[c]));
          return;
        }
      }
    }
  }

  // A moving mesh stays within the float range at every time: each vertex p lands within
  // |translate| + max|scale| |p| of the origin per axis (a rotation keeps lengths), and both are
  // bounded by the keys.
  bool stays_in_float_range(const Mesh& mesh, const Span& translate, const Span& scale, const Path& at) {
    Mesh probe;  // the OBJ's own coordinates (already checked to parse)
    probe.obj = mesh.obj;
    if (!build_obj_mesh(probe, mesh.triangle_count())) return true;
    double radius = 0;
    for (const math::Vec3f& v : probe.vertices) radius = std::max(radius, math::length(Vec3d(v)));
    radius *= 1 + 0x1p-23;  // the probe's coordinates were rounded to float
    const double reach = math::max_component(scale.max_abs()) * radius;
    for (std::size_t c = 0; c < 3; ++c) {
      if (!(translate.max_abs()[c] + reach <= kFloatMax)) {
        r_.error(at, fmt::format("the mesh's keys move or scale it beyond the float range (up to {:g} along axis {})",
                                 translate.max_abs()[c] + reach, c));
        return false;
      }
    }
    return true;
  }

  bool read_mesh_file(Mesh& mesh, const Path& at) {
    if (!s_.options.allow_mesh_files) {
      r_.error(at, fmt::format("mesh file {} not accepted here: a scene sent to a collector or worker must carry "
                               "its meshes inline as \"obj\" (dtraced submit inlines them)",
                               jsonio::quoted(mesh.file)));
      return false;
    }
    if (mesh.file.empty()) {
      r_.error(at, "must name an OBJ file");
      return false;
    }
    const std::filesystem::path relative(mesh.file);
    const std::string& base = s_.options.base_dir;
    const std::filesystem::path path =
        relative.is_absolute() || base.empty() ? relative : std::filesystem::path(base) / relative;
    util::Result<std::string> text = util::read_file_limited(path.string(), s_.options.max_obj_bytes);
    if (!text) {
      r_.error(at, jsonio::printable(text.error().to_string()));  // it names the file
      return false;
    }
    // The canonical form carries the text inside a JSON string, which must be UTF-8.
    if (const std::size_t line = first_invalid_utf8_line(*text); line != 0) {
      r_.error(at, fmt::format("{}: line {}: not valid UTF-8 (an OBJ is inlined into the scene as JSON text)",
                               jsonio::printable(mesh.file), line));
      return false;
    }
    mesh.obj = std::move(*text);
    return true;
  }

  // ---- lights --------------------------------------------------------------------------------

  // A rect light's edges and emitting side: "u" and "v" are required; "normal" is optional (by
  // default the side of cross(u, v)) and, when given, must be parallel to cross(u, v).
  void read_rect_light(jsonio::Fields& f, Light& light) {
    std::optional<Vec3d> u, v;
    f.read("u", u, Need::kRequired, vec3());
    f.read("v", v, Need::kRequired, vec3());
    if (!u || !v) return;
    const double u_scale = math::max_component(math::abs(*u)), v_scale = math::max_component(math::abs(*v));
    if (u_scale == 0 || v_scale == 0) {
      r_.error(f.path(u_scale == 0 ? "u" : "v"), "must not be the zero vector");
      return;
    }
    const Vec3d us = *u / u_scale, vs = *v / v_scale;
    const Vec3d c = math::cross(us, vs);
    // Parallel edges: the rectangle would have no area. Same tolerance as the camera's up.
    if (math::length(c) < kParallelTolerance * math::length(us) * math::length(vs)) {
      r_.error(f.path("v"), "must not be parallel to \"u\": the rectangle would have no area");
      return;
    }
    light.edge_u = *u;
    light.edge_v = *v;
    Vec3d normal = c / math::length(c);
    if (f.has("normal")) {
      std::optional<Vec3d> unit;
      if (!f.read("normal", unit, Need::kOptional, unit_vector())) return;
      const double cosine = math::dot(*unit, normal);
      if (std::abs(cosine) < 1.0 - 1e-6) {
        r_.error(f.path("normal"),
                 "must be perpendicular to both edges \"u\" and \"v\" (it only picks the side the light emits on)");
        return;
      }
      if (cosine < 0) normal = -normal;
    }
    light.normal = normal;
  }

 public:
  // ---- entry points (after the helpers, whose return types they deduce) ---------------------
  // Each takes the element as an object, or nullptr when it was not one (already reported).

  std::optional<Object> object(const json::object* o, const Path& at) {
    if (o == nullptr) return std::nullopt;
    const std::size_t errors_before = r_.error_count();
    Object out;
    const std::optional<std::size_t> type = type_of(*o, at, kObjectTypeNames, "object type");
    if (!type) {
      check_keys(*o, at, kAnyObjectKeys);
    } else {
      out.type = static_cast<ObjectType>(*type);
      jsonio::Fields f(r_, *o, at);
      switch (out.type) {
        case ObjectType::kSphere:
          out.sphere = Sphere{};
          read_sphere(f, out.sphere);
          break;
        case ObjectType::kBox:
          out.box = Box{};
          read_box(f, out.box);
          break;
        case ObjectType::kPlane:
          out.plane = Plane{};
          read_plane(f, out.plane);
          break;
        case ObjectType::kMesh:
          read_mesh(f, out);
          break;
      }
    }
    if (const json::value* m = o->if_contains("material")) read_material(*m, at.key("material"), out.material);
    if (!type || r_.error_count() != errors_before) return std::nullopt;
    return out;
  }

  std::optional<Light> light(const json::object* o, const Path& at) {
    if (o == nullptr) return std::nullopt;
    const std::size_t errors_before = r_.error_count();
    Light light;
    const std::optional<std::size_t> type = type_of(*o, at, kLightTypeNames, "light type");
    check_keys(*o, at, type ? kLightKeys[*type] : Keys(kAnyLightKeys));
    jsonio::Fields f(r_, *o, at);
    Span color_span, intensity_span;
    animatable(f, "loc", light.position, Need::kRequired, Target::kLightPosition, vec3());
    animatable(f, "color", light.color, Need::kOptional, Target::kLightColor, color(), &color_span);
    animatable(f, "intensity", light.intensity, Need::kOptional, Target::kLightIntensity, float_in(0, kInfinity),
               &intensity_span);
    if (!type) return std::nullopt;
    light.type = kLightTypes[*type];
    if (light.is_area()) {
      f.integer("samples", light.samples, 1, kMaxLightSamples, Need::kOptional);
      f.boolean("cast_shadows", light.cast_shadows, Need::kOptional);
    }
    if (light.type == LightType::kSphere || light.type == LightType::kDisk) {
      f.read("radius", light.radius, Need::kRequired,
             size_in(kMinLightRadius, kMaxLightRadius, "2^-63 to 2^63: light sampling squares it"));
    }
    if (light.type == LightType::kDisk) f.read("normal", light.normal, Need::kRequired, unit_vector());
    if (light.type == LightType::kRect) read_rect_light(f, light);
    if (r_.error_count() != errors_before) return std::nullopt;
    // At the largest colour and intensity the keys reach, so it holds at every time.
    for (std::size_t i = 0; i < 3; ++i) {
      const double emitted = color_span.hi[i] * intensity_span.hi.x;
      if (emitted > kMaxRadiance) {
        r_.error(f.has("intensity") ? f.path("intensity") : f.path("color"),
                 fmt::format("color x intensity must be at most 2^120 ({:g}) per channel, or shading overflows "
                             "(got {} in channel {})",
                             kMaxRadiance, emitted, i));
        return std::nullopt;
      }
    }
    return light;
  }

 private:
  SceneReader& s_;
  jsonio::Reader& r_;
};

// ---- plain spheres from parse events (read_plain_sphere) ---------------------------------------
// Each check below is one read_object makes on a sphere; a value that fails it sends the element
// to read_object, which reports it.

using jsonio::EventLog;

// The next event as read_float would read it: a finite number within the float range, -0 as +0.
std::optional<double> plain_float(EventLog::Cursor& c) {
  if (!c.next()) return std::nullopt;
  double d = 0;
  switch (c.kind()) {
    case EventLog::Kind::kInt64:
      d = static_cast<double>(c.event().i);
      break;
    case EventLog::Kind::kUint64:
      d = static_cast<double>(c.event().u);
      break;
    case EventLog::Kind::kDouble:
    case EventLog::Kind::kDoubleValue:
      d = c.double_value();
      break;
    default:
      return std::nullopt;
  }
  if (!std::isfinite(d) || std::abs(d) > kFloatMax) return std::nullopt;
  return d == 0 ? 0.0 : d;
}

// [x, y, z] of plain_float (read_vec3); an object (an animation track) is not plain.
bool plain_vec3(EventLog::Cursor& c, Vec3d& out) {
  if (!c.next(EventLog::Kind::kArrayBegin)) return false;
  for (std::size_t i = 0; i < 3; ++i) {
    const std::optional<double> d = plain_float(c);
    if (!d) return false;
    out[i] = *d;
  }
  return c.next(EventLog::Kind::kArrayEnd);
}

// A number in [lo, hi] (float_in).
bool plain_float_in(EventLog::Cursor& c, double lo, double hi, double& out) {
  const std::optional<double> d = plain_float(c);
  if (!d || !(*d >= lo && *d <= hi)) return false;
  out = *d;
  return true;
}

// read_material's checks, each key once.
bool plain_material(EventLog::Cursor& c, Material& m) {
  if (!c.next(EventLog::Kind::kObjectBegin)) return false;
  unsigned seen = 0;
  while (c.next()) {
    if (c.kind() == EventLog::Kind::kObjectEnd) {
      return m.reflectivity + m.transparency <= 1 + kEnergySlack;
    }
    const std::string_view key = c.text();  // a key: an object holds keys and values
    std::size_t k = 0;
    while (k < kMaterialKeys.size() && kMaterialKeys[k] != key) ++k;
    if (k == kMaterialKeys.size() || (seen & (1u << k)) != 0) return false;
    seen |= 1u << k;
    bool ok = false;
    if (k == 0) {  // color: albedo(), each channel in [0, kMaxAlbedo]
      ok = plain_vec3(c, m.color) && m.color.x >= 0 && m.color.y >= 0 && m.color.z >= 0 && m.color.x <= kMaxAlbedo &&
           m.color.y <= kMaxAlbedo && m.color.z <= kMaxAlbedo;
    } else if (k <= kMaterialRanges.size()) {
      const MaterialRange& range = kMaterialRanges[k - 1];
      ok = plain_float_in(c, range.lo, range.hi, m.*range.field);
    } else {  // ior: size_in(kMinIor, kMaxIor), positive first
      ok = plain_float_in(c, kMinIor, kMaxIor, m.ior) && m.ior > 0;
    }
    if (!ok) return false;
  }
  return false;
}

}  // namespace

std::optional<Object> read_plain_sphere(const jsonio::EventLog& log, jsonio::EventLog::Mark from,
                                        jsonio::EventLog::Mark to) {
  EventLog::Cursor c(log, from, to);
  if (!c.next(EventLog::Kind::kObjectBegin)) return std::nullopt;
  // As read_object builds it.
  Object out;
  out.type = ObjectType::kSphere;
  out.sphere = Sphere{};
  constexpr unsigned kType = 1, kLoc = 2, kRadius = 4, kMaterial = 8;
  unsigned seen = 0;
  bool closed = false;
  while (c.next()) {
    if (c.kind() == EventLog::Kind::kObjectEnd) {
      closed = true;
      break;
    }
    const std::string_view key = c.text();
    unsigned bit = 0;
    bool ok = false;
    if (key == "type") {
      bit = kType;
      ok = c.next(EventLog::Kind::kString) && c.text() == kObjectTypeNames[0];
    } else if (key == "loc") {
      bit = kLoc;
      ok = plain_vec3(c, out.sphere.center);
    } else if (key == "radius") {
      bit = kRadius;
      // positive_float(): > 0 and a normal float.
      const std::optional<double> r = plain_float(c);
      ok = r && *r > 0 && normal_as_float(*r);
      if (ok) out.sphere.radius = *r;
    } else if (key == "material") {
      bit = kMaterial;
      ok = plain_material(c, out.material);
    }
    if (!ok || (seen & bit) != 0) return std::nullopt;
    seen |= bit;
  }
  if (!closed || !c.done() || (seen & (kType | kLoc | kRadius)) != (kType | kLoc | kRadius)) {
    return std::nullopt;
  }
  // read_sphere: the bounds are finite floats.
  for (std::size_t i = 0; i < 3; ++i) {
    if (!std::isfinite(static_cast<float>(std::abs(out.sphere.center[i]) + out.sphere.radius))) return std::nullopt;
  }
  return out;
}

std::optional<Object> read_object(SceneReader& s, const json::value& v, const Path& at) {
  return ObjectReader(s).object(s.r.object(v, at), at);
}

std::optional<Light> read_light(SceneReader& s, const json::value& v, const Path& at) {
  return ObjectReader(s).light(s.r.object(v, at), at);
}

}  // namespace dtraced::scene::detail
