#include "render/render_scene.h"

#include <cassert>
#include <cmath>
#include <numbers>

namespace dtraced::render {

namespace {

Vec3f to_f(const Vec3d& v) { return Vec3f(v); }

MaterialF to_material(const scene::Material& m) {
  MaterialF out;
  out.color = to_f(m.color);
  out.diffuse = float(m.diffuse);
  out.specular = float(m.specular);
  out.shininess = float(m.shininess);
  out.reflectivity = float(m.reflectivity);
  out.transparency = float(m.transparency);
  out.ior = float(m.ior);
  // Computed in double so that reflectivity + transparency == 1 gives exactly 0.
  out.local_weight = float(std::max(0.0, 1.0 - m.reflectivity - m.transparency));
  return out;
}

accel::Shape to_shape(const scene::Object& o) {
  accel::Shape s;
  switch (o.type) {
    case scene::ObjectType::kSphere:
      s.type = accel::ShapeType::kSphere;
      s.sphere = {to_f(o.sphere.center), float(o.sphere.radius)};
      break;
    case scene::ObjectType::kBox:
      s.type = accel::ShapeType::kBox;
      s.box = {to_f(o.box.min), to_f(o.box.max)};
      break;
    case scene::ObjectType::kPlane:
      s.type = accel::ShapeType::kPlane;
      s.plane = {to_f(o.plane.point), to_f(math::normalize(o.plane.normal))};
      break;
  }
  return s;
}

}  // namespace

math::Ray CameraF::generate(double fx, double fy, std::uint32_t width, std::uint32_t height) const {
  const double aspect = double(width) / double(height);
  const double sx = (2.0 * fx / double(width) - 1.0) * tan_half_fov * aspect;
  const double sy = (1.0 - 2.0 * fy / double(height)) * tan_half_fov;
  const Vec3d dir = math::normalize(forward + right * sx + up * sy);
  math::Ray ray;
  ray.o = Vec3f(position);
  ray.d = math::normalize(Vec3f(dir));
  return ray;
}

RenderScene RenderScene::build(const scene::SceneDesc& desc, accel::Isa isa) {
  RenderScene rs;
  std::vector<accel::Shape> shapes;
  shapes.reserve(desc.objects.size());
  rs.materials_.reserve(desc.objects.size());
  for (const scene::Object& o : desc.objects) {
    shapes.push_back(to_shape(o));
    rs.materials_.push_back(to_material(o.material));
    rs.has_transparency_ = rs.has_transparency_ || o.material.transparency > 0.0;
  }
  rs.geometry_ = accel::Geometry::build(std::move(shapes), isa);
  for (const scene::PointLight& l : desc.lights) {
    rs.lights_.push_back({to_f(l.position), to_f(l.color * l.intensity)});
  }
  const scene::Camera& c = desc.camera;
  rs.camera_.position = c.position;
  rs.camera_.forward = math::normalize(c.look_at - c.position);
  rs.camera_.right = math::normalize(math::cross(rs.camera_.forward, c.up));
  rs.camera_.up = math::cross(rs.camera_.right, rs.camera_.forward);
  rs.camera_.tan_half_fov = std::tan(c.fov_deg * std::numbers::pi / 360.0);
  assert(math::is_finite(rs.camera_.right));
  return rs;
}

}  // namespace dtraced::render
