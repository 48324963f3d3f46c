#include "scene/obj_mesh.h"

#include <tiny_obj_loader.h>

#include <array>
#include <charconv>
#include <cmath>
#include <numbers>
#include <string_view>
#include <system_error>
#include <utility>

#include <fmt/format.h>

#include "math/det_math.h"

namespace dtraced::scene {
namespace {

using math::Vec3f;

// Errors quoted per mesh: a broken 1M-line OBJ should give a readable report, not a million lines.
constexpr std::size_t kMaxErrorsPerMesh = 10;

// sin and cos of an angle in degrees. Multiples of 90 degrees are exact (a quarter turn must map
// an axis onto an axis, not onto 6e-17 off it); other angles, reduced to one turn, go through
// math::det::sincos in double (the same bits on every host, unlike libm's), whose result is then
// rounded to float with the rest of the transform.
std::pair<double, double> sin_cos_deg(double deg) {
  const double turns = std::fmod(deg, 360.0);
  if (turns == std::floor(turns) && std::fmod(turns, 90.0) == 0.0) {
    switch (static_cast<int>(turns < 0 ? turns + 360.0 : turns)) {
      case 0:
        return {0.0, 1.0};
      case 90:
        return {1.0, 0.0};
      case 180:
        return {0.0, -1.0};
      case 270:
        return {-1.0, 0.0};
      default:
        break;
    }
  }
  const math::det::SinCos sc = math::det::sincos(turns * (std::numbers::pi / 180.0));
  return {sc.sin, sc.cos};
}

using Mat3 = std::array<std::array<double, 3>, 3>;

Mat3 multiply(const Mat3& a, const Mat3& b) {
  Mat3 m{};
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) m[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
  }
  return m;
}

// Rz * Ry * Rx: a point is rotated about X first, then Y, then Z (right-handed, counter-clockwise
// looking down the axis towards the origin).
Mat3 rotation(const math::Vec3d& deg) {
  const auto [sx, cx] = sin_cos_deg(deg.x);
  const auto [sy, cy] = sin_cos_deg(deg.y);
  const auto [sz, cz] = sin_cos_deg(deg.z);
  const Mat3 rx{{{1, 0, 0}, {0, cx, -sx}, {0, sx, cx}}};
  const Mat3 ry{{{cy, 0, sy}, {0, 1, 0}, {-sy, 0, cy}}};
  const Mat3 rz{{{cz, -sz, 0}, {sz, cz, 0}, {0, 0, 1}}};
  return multiply(rz, multiply(ry, rx));
}

// tinyobjloader reads a token it cannot parse as 0 without a word. Every token after "v" must be
// a number std::from_chars reads whole (a leading '+' allowed, as tinyobjloader allows it) and
// finite. Only "v" lines are looked at; everything else is tinyobjloader's business.
void check_vertex_lines(std::string_view text, std::vector<std::string>& errors) {
  std::size_t line_number = 0;
  std::size_t pos = 0;
  while (pos < text.size() && errors.size() < kMaxErrorsPerMesh) {
    std::size_t end = text.find('\n', pos);
    if (end == std::string_view::npos) end = text.size();
    std::string_view line = text.substr(pos, end - pos);
    pos = end + 1;
    ++line_number;
    const std::size_t first = line.find_first_not_of(" \t");
    if (first == std::string_view::npos || line.size() < first + 2 || line[first] != 'v' ||
        (line[first + 1] != ' ' && line[first + 1] != '\t')) {
      continue;
    }
    line.remove_prefix(first + 1);
    int tokens = 0;
    while (true) {
      const std::size_t start = line.find_first_not_of(" \t\r");
      if (start == std::string_view::npos) break;
      line.remove_prefix(start);
      std::size_t stop = line.find_first_of(" \t\r");
      if (stop == std::string_view::npos) stop = line.size();
      const std::string_view token = line.substr(0, stop);
      line.remove_prefix(stop);
      ++tokens;
      std::string_view digits = token;
      if (digits.starts_with('+')) digits.remove_prefix(1);
      double value = 0;
      const auto [ptr, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), value);
      if (ec != std::errc() || ptr != digits.data() + digits.size() || !std::isfinite(value)) {
        errors.push_back(fmt::format("line {}: vertex coordinate \"{}\" is not a finite number", line_number, token));
        break;
      }
    }
    if (tokens < 3 && errors.size() < kMaxErrorsPerMesh) {
      errors.push_back(fmt::format("line {}: a vertex needs 3 coordinates, got {}", line_number, tokens));
    }
  }
}

// tinyobjloader's messages are one or more lines; one line each in ours.
void add_tinyobj_messages(const std::string& text, std::vector<std::string>& errors) {
  std::size_t pos = 0;
  while (pos < text.size()) {
    std::size_t end = text.find('\n', pos);
    if (end == std::string::npos) end = text.size();
    std::string_view line(text.data() + pos, end - pos);
    pos = end + 1;
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.remove_suffix(1);
    if (!line.empty() && errors.size() < kMaxErrorsPerMesh) errors.push_back(fmt::format("tinyobjloader: {}", line));
  }
}

}  // namespace

bool triangle_is_degenerate(const Vec3f& v0, const Vec3f& v1, const Vec3f& v2) {
  const math::Vec3d a(v0), b(v1), c(v2);
  const math::Vec3d n = math::cross(b - a, c - a);
  return !(std::isfinite(n.x) && (n.x != 0.0 || n.y != 0.0 || n.z != 0.0));
}

util::Result<void, util::Errors> build_obj_mesh(Mesh& mesh, std::size_t max_triangles) {
  mesh.vertices.clear();
  mesh.degenerate_triangles = 0;
  std::vector<std::string> errors;
  const auto failed = [&errors, &mesh] {
    mesh.vertices.clear();
    mesh.degenerate_triangles = 0;
    return util::Errors(errors.begin(), errors.end());
  };
  check_vertex_lines(mesh.obj, errors);
  if (!errors.empty()) return failed();

  tinyobj::ObjReaderConfig config;
  config.triangulate = true;
  config.vertex_color = false;
  tinyobj::ObjReader reader;
  // From the string we read ourselves, with no .mtl text: materials come from the scene, and
  // nothing outside the scene's own files (mtllib paths) is opened.
  const bool parsed = reader.ParseFromString(mesh.obj, "", config);
  if (!parsed || !reader.Error().empty()) {
    add_tinyobj_messages(reader.Error().empty() ? std::string("the OBJ does not parse") : reader.Error(), errors);
    return failed();
  }
  // An out-of-range index makes tinyobjloader warn and drop the polygons it triangulates itself;
  // a scene must not lose faces silently.
  if (reader.Warning().find("out of bounds") != std::string::npos ||
      reader.Warning().find("invalid vertex index") != std::string::npos) {
    add_tinyobj_messages(reader.Warning(), errors);
    return failed();
  }

  const std::vector<tinyobj::real_t>& v = reader.GetAttrib().vertices;
  const std::size_t vertex_count = v.size() / 3;
  std::size_t triangles = 0;
  for (const tinyobj::shape_t& shape : reader.GetShapes()) triangles += shape.mesh.indices.size() / 3;
  if (triangles > max_triangles) {
    errors.push_back(fmt::format("{} triangles, more than the {} this scene has left (the limit is per scene)",
                                 triangles, max_triangles));
    return failed();
  }

  const Mat3 r = rotation(mesh.rotate_deg);
  const math::Vec3d s = mesh.scale;
  const math::Vec3d t = mesh.translate;
  // A mirroring transform turns the winding around; swapping two vertices turns it back, so the
  // normal cross(v1 - v0, v2 - v0) keeps facing the side the OBJ's faces say.
  const bool mirrored = (int(s.x < 0) + int(s.y < 0) + int(s.z < 0)) % 2 == 1;
  const auto place = [&](int index, Vec3f& out) {
    if (index < 0 || static_cast<std::size_t>(index) >= vertex_count) {
      if (errors.size() < kMaxErrorsPerMesh) {
        errors.push_back(
            fmt::format("face vertex index {} is out of range (the OBJ has {} vertices)", index + 1, vertex_count));
      }
      return false;
    }
    const std::size_t i = static_cast<std::size_t>(index) * 3;
    const double x = double(v[i]) * s.x, y = double(v[i + 1]) * s.y, z = double(v[i + 2]) * s.z;
    const math::Vec3d p{r[0][0] * x + r[0][1] * y + r[0][2] * z + t.x, r[1][0] * x + r[1][1] * y + r[1][2] * z + t.y,
                        r[2][0] * x + r[2][1] * y + r[2][2] * z + t.z};
    out = Vec3f(p);
    if (!math::is_finite(out)) {
      if (errors.size() < kMaxErrorsPerMesh) {
        errors.push_back(fmt::format("vertex {} ({}, {}, {}) leaves the float range after the transform", index + 1,
                                     v[i], v[i + 1], v[i + 2]));
      }
      return false;
    }
    return true;
  };

  mesh.vertices.resize(triangles * 3);
  std::size_t next = 0;
  bool ok = true;
  for (const tinyobj::shape_t& shape : reader.GetShapes()) {
    const std::vector<tinyobj::index_t>& idx = shape.mesh.indices;
    for (std::size_t k = 0; k + 2 < idx.size(); k += 3) {
      Vec3f* tri = &mesh.vertices[next];
      ok = place(idx[k].vertex_index, tri[0]) && ok;
      ok = place(idx[k + (mirrored ? 2 : 1)].vertex_index, tri[1]) && ok;
      ok = place(idx[k + (mirrored ? 1 : 2)].vertex_index, tri[2]) && ok;
      if (ok && triangle_is_degenerate(tri[0], tri[1], tri[2])) ++mesh.degenerate_triangles;
      next += 3;
    }
  }
  if (!ok) return failed();
  return {};
}

}  // namespace dtraced::scene
