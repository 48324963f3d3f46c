#include "render/reference.h"

#include <array>
#include <cmath>
#include <numbers>

#include <fmt/format.h>

namespace dtraced::render {

namespace {

using math::Vec3d;

struct RectCorners {
  std::array<Vec3d, 4> c;  // in order around the rect
};

RectCorners rect_corners(const scene::Light& l) {
  const Vec3d hu = l.edge_u * 0.5, hv = l.edge_v * 0.5;
  return {{l.position - hu - hv, l.position + hu - hv, l.position + hu + hv, l.position - hu + hv}};
}

// Why a light has no closed form over this plane, or "" when it has one.
std::string light_problem(const scene::Light& l, std::size_t i, const scene::Plane& plane) {
  const auto side = [&plane](const Vec3d& p) { return math::dot(p - plane.point, plane.normal); };
  switch (l.type) {
    case scene::LightType::kPoint:
      return "";
    case scene::LightType::kSphere:
      if (std::abs(side(l.position)) <= l.radius) return fmt::format("light {}: the sphere light cuts the plane", i);
      return "";
    case scene::LightType::kRect: {
      const RectCorners r = rect_corners(l);
      const double s0 = side(r.c[0]);
      for (const Vec3d& c : r.c) {
        if (!(side(c) * s0 > 0.0)) return fmt::format("light {}: the rect light touches or crosses the plane", i);
      }
      return "";
    }
    case scene::LightType::kDisk:
      return fmt::format("light {}: disk lights have no closed form off their axis", i);
  }
  return fmt::format("light {}: unknown type", i);
}

// Irradiance at p (normal n, unit) from a rect of unit radiance seen from its emitting side, by
// Lambert's formula; the rect lies wholly on n's side.
double rect_irradiance(const RectCorners& r, const Vec3d& p, const Vec3d& n) {
  double sum = 0.0;
  for (std::size_t i = 0; i < 4; ++i) {
    const Vec3d a = math::normalize(r.c[i] - p), b = math::normalize(r.c[(i + 1) % 4] - p);
    const Vec3d g = math::cross(a, b);
    const double len = math::length(g);
    if (len == 0.0) continue;
    const double angle = std::atan2(len, math::dot(a, b));
    sum += angle * math::dot(g / len, n);
  }
  return 0.5 * std::abs(sum);
}

// Nearest t > 0 where the ray meets the sphere's outside, or +infinity.
double hit_sphere(const Vec3d& o, const Vec3d& d, const Vec3d& c, double radius) {
  const Vec3d oc = o - c;
  const double b = math::dot(oc, d), cc = math::dot(oc, oc) - radius * radius;
  const double disc = b * b - cc;
  if (cc <= 0.0 || disc < 0.0) return INFINITY;
  const double t = -b - std::sqrt(disc);
  return t > 0.0 ? t : INFINITY;
}

// t > 0 where the ray meets the rect from its emitting side, or +infinity.
double hit_rect(const Vec3d& o, const Vec3d& d, const scene::Light& l) {
  const double dn = math::dot(d, l.normal);
  if (dn >= 0.0) return INFINITY;  // parallel, or reaching the back
  const double t = math::dot(l.position - o, l.normal) / dn;
  if (!(t > 0.0)) return INFINITY;
  // Coordinates of the hit in the (possibly skewed) edge basis: solve q = a u + b v in the plane.
  const Vec3d q = o + d * t - l.position;
  const double uu = math::dot(l.edge_u, l.edge_u), vv = math::dot(l.edge_v, l.edge_v);
  const double uv = math::dot(l.edge_u, l.edge_v), qu = math::dot(q, l.edge_u), qv = math::dot(q, l.edge_v);
  const double det = uu * vv - uv * uv;
  const double a = (qu * vv - qv * uv) / det, b = (qv * uu - qu * uv) / det;
  return std::abs(a) <= 0.5 && std::abs(b) <= 0.5 ? t : INFINITY;
}

}  // namespace

std::optional<image::ImageRGBf> closed_form_reference(const scene::SceneDesc& desc, const RenderScene& scene,
                                                      std::uint32_t grid, std::string& why_not) {
  if (grid < 1 || grid > kMaxReferenceGrid) {
    why_not = fmt::format("reference grid {} is outside [1, {}]", grid, kMaxReferenceGrid);
    return std::nullopt;
  }
  if (desc.objects.size() != 1 || desc.objects[0].type != scene::ObjectType::kPlane) {
    why_not = "closed forms cover one plane and nothing else";
    return std::nullopt;
  }
  const scene::Material& m = desc.objects[0].material;
  if (m.specular != 0.0 || m.reflectivity != 0.0 || m.transparency != 0.0) {
    why_not = "closed forms cover a purely diffuse plane (specular, reflectivity and transparency 0)";
    return std::nullopt;
  }
  const scene::Plane& plane = desc.objects[0].plane;
  const Vec3d cam = desc.camera.position;
  const double cam_side = math::dot(cam - plane.point, plane.normal);
  if (cam_side == 0.0) {
    why_not = "the camera lies in the plane";
    return std::nullopt;
  }
  for (std::size_t i = 0; i < desc.lights.size(); ++i) {
    const scene::Light& l = desc.lights[i];
    std::string problem = light_problem(l, i, plane);
    if (problem.empty() && l.type == scene::LightType::kSphere && math::length(cam - l.position) <= l.radius) {
      problem = fmt::format("light {}: the camera is inside the sphere light", i);
    }
    if (!problem.empty()) {
      why_not = problem;
      return std::nullopt;
    }
  }

  // The side of the plane the camera sees, and so the normal shading uses.
  const Vec3d n = cam_side > 0.0 ? plane.normal : -plane.normal;
  const Vec3d albedo = m.color * (m.diffuse / std::numbers::pi);
  const scene::RenderSettings& s = desc.render;

  const auto radiance = [&](const Vec3d& dir) -> Vec3d {
    const double dn = math::dot(dir, plane.normal);
    double t_plane = dn != 0.0 ? math::dot(plane.point - cam, plane.normal) / dn : INFINITY;
    if (!(t_plane > 0.0)) t_plane = INFINITY;
    // An emitter in front of the plane is what the ray sees.
    double t_light = t_plane;
    Vec3d seen{0, 0, 0};
    for (const scene::Light& l : desc.lights) {
      double t = INFINITY;
      if (l.type == scene::LightType::kSphere) t = hit_sphere(cam, dir, l.position, l.radius);
      if (l.type == scene::LightType::kRect) t = hit_rect(cam, dir, l);
      if (t < t_light) {
        t_light = t;
        seen = l.color * l.intensity;
      }
    }
    if (t_light < t_plane) return seen;
    if (t_plane == INFINITY) return s.background;

    const Vec3d p = cam + dir * t_plane;
    Vec3d e{0, 0, 0};  // irradiance-like sum: I cos / d^2 for points, E for area lights
    for (const scene::Light& l : desc.lights) {
      const Vec3d to = l.position - p;
      const double d2 = math::dot(to, to);
      const Vec3d emitted = l.color * l.intensity;
      if (l.type == scene::LightType::kPoint) {
        const double cos = math::dot(n, to) / std::sqrt(d2);
        if (cos > 0.0) e += emitted * (cos / d2);
      } else if (l.type == scene::LightType::kSphere) {
        const double cos = math::dot(n, to) / std::sqrt(d2);
        if (cos > 0.0) e += emitted * (std::numbers::pi * l.radius * l.radius / d2 * cos);
      } else if (l.type == scene::LightType::kRect) {
        const RectCorners r = rect_corners(l);
        const bool lit_side = math::dot(r.c[0] - p, n) > 0.0;
        const bool emitting_side = math::dot(p - l.position, l.normal) > 0.0;
        if (lit_side && emitting_side) e += emitted * rect_irradiance(r, p, n);
      }
    }
    return {albedo.x * e.x, albedo.y * e.y, albedo.z * e.z};
  };

  image::ImageRGBf out(s.width, s.height);
  const double inv = 1.0 / double(grid);
  const double weight = 1.0 / (double(grid) * double(grid));
  for (std::uint32_t y = 0; y < s.height; ++y) {
    for (std::uint32_t x = 0; x < s.width; ++x) {
      Vec3d sum{0, 0, 0};
      for (std::uint32_t j = 0; j < grid; ++j) {
        for (std::uint32_t i = 0; i < grid; ++i) {
          const math::Ray ray = scene.camera().generate(x + (i + 0.5) * inv, y + (j + 0.5) * inv, s.width, s.height);
          sum += radiance(math::normalize(Vec3d(ray.d)));
        }
      }
      float* px = out.pixel(x, y);
      for (int c = 0; c < 3; ++c) px[c] = float(sum[c] * weight);
    }
  }
  return out;
}

}  // namespace dtraced::render
