#include "render/render_scene.h"

#include <cassert>
#include <cmath>
#include <limits>
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
    case scene::ObjectType::kMesh:
      assert(false && "meshes become one shape per triangle (append_shapes)");
      break;
  }
  return s;
}

// The shapes of one object: one, or one triangle per mesh triangle. Degenerate triangles are
// kept (the accel layer never hits them) so shape ids stay in the description's triangle order.
void append_shapes(const scene::Object& o, std::vector<accel::Shape>& shapes) {
  if (o.type != scene::ObjectType::kMesh) {
    shapes.push_back(to_shape(o));
    return;
  }
  assert(o.mesh != nullptr);
  const std::vector<Vec3f>& v = o.mesh->vertices;
  accel::Shape s;
  s.type = accel::ShapeType::kTriangle;
  for (std::size_t i = 0; i + 2 < v.size(); i += 3) {
    s.triangle = {v[i], v[i + 1], v[i + 2]};
    shapes.push_back(s);
  }
}

// A unit vector perpendicular to unit n (any one: the disk is symmetric about its normal).
Vec3d perpendicular(const Vec3d& n) {
  const Vec3d a = std::abs(n.x) < 0.9 ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0};
  return math::normalize(math::cross(n, a));
}

AreaLightF to_area_light(const scene::Light& l) {
  AreaLightF a;
  a.center = to_f(l.position);
  a.radiance = to_f(l.color * l.intensity);
  a.samples = l.samples;
  a.cast_shadows = l.cast_shadows;
  switch (l.type) {
    case scene::LightType::kSphere:
      a.shape = AreaShape::kSphere;
      a.radius = float(l.radius);
      break;
    case scene::LightType::kDisk: {
      a.shape = AreaShape::kDisk;
      a.radius = float(l.radius);
      const Vec3d n = math::normalize(l.normal);
      const Vec3d t = perpendicular(n);
      a.normal = to_f(n);
      a.edge_u = to_f(t);
      a.edge_v = to_f(math::cross(n, t));
      a.area = float(std::numbers::pi * l.radius * l.radius);
      break;
    }
    case scene::LightType::kRect:
      a.shape = AreaShape::kRect;
      a.normal = to_f(math::normalize(l.normal));
      a.edge_u = to_f(l.edge_u);
      a.edge_v = to_f(l.edge_v);
      a.corner = to_f(l.position - l.edge_u * 0.5 - l.edge_v * 0.5);
      a.area = float(math::length(math::cross(l.edge_u, l.edge_v)));
      break;
    case scene::LightType::kPoint:
      assert(false && "point lights are PointLightF");
      break;
  }
  assert(a.samples >= 1 && a.samples <= scene::kMaxLightSamples);
  return a;
}

}  // namespace

std::string feature_names(const SceneFeatures& f) {
  std::string out;
  const auto add = [&out](bool on, const char* name) {
    if (!on) return;
    if (!out.empty()) out += ' ';
    out += name;
  };
  add(f.reflection, "reflection");
  add(f.refraction, "refraction");
  add(f.specular, "specular");
  add(f.shadows, "shadows");
  add(f.area_lights, "area-lights");
  add(f.point_lights, "point-lights");
  return out.empty() ? "none" : out;
}

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
  std::size_t shape_count = 0;
  for (const scene::Object& o : desc.objects) {
    shape_count += o.type == scene::ObjectType::kMesh ? o.mesh->triangle_count() : 1;
  }
  // Shape ids are 32-bit (accel::Hit::shape); the loader's limits keep far below that.
  assert(shape_count <= std::numeric_limits<std::uint32_t>::max());
  std::vector<accel::Shape> shapes;
  shapes.reserve(shape_count);
  rs.shape_object_.reserve(shape_count);
  rs.materials_.reserve(desc.objects.size());
  for (std::size_t i = 0; i < desc.objects.size(); ++i) {
    const scene::Object& o = desc.objects[i];
    append_shapes(o, shapes);
    rs.shape_object_.resize(shapes.size(), static_cast<std::uint32_t>(i));
    rs.materials_.push_back(to_material(o.material));
    rs.has_transparency_ = rs.has_transparency_ || o.material.transparency > 0.0;
    rs.features_.reflection = rs.features_.reflection || o.material.reflectivity > 0.0;
    rs.features_.specular = rs.features_.specular || o.material.specular > 0.0;
  }
  rs.features_.refraction = rs.has_transparency_;
  rs.geometry_ = accel::Geometry::build(std::move(shapes), isa);
  for (const scene::Light& l : desc.lights) {
    if (l.is_area()) {
      rs.area_lights_.push_back(to_area_light(l));
      rs.features_.area_lights = true;
      rs.features_.shadows = rs.features_.shadows || l.cast_shadows;
    } else {
      rs.lights_.push_back({to_f(l.position), to_f(l.color * l.intensity)});
      rs.features_.point_lights = true;
      rs.features_.shadows = true;
    }
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
