// dtraced::render render-ready scene: float materials, lights, camera and the acceleration
// structure, built once from a scene::SceneDesc.
//
// Thread-safety: immutable after build(); shared read-only by every render thread.
#pragma once

#include <cstddef>
#include <cstdint>
#include <vector>

#include "accel/geometry.h"
#include "math/ray.h"
#include "math/vec.h"
#include "scene/description.h"

namespace dtraced::render {

using math::Vec3d;
using math::Vec3f;

struct MaterialF {
  Vec3f color;
  float diffuse = 1.0f;
  float specular = 0.0f;
  float shininess = 32.0f;
  float reflectivity = 0.0f;
  float transparency = 0.0f;
  float ior = 1.5f;
  float local_weight = 1.0f;  // 1 - reflectivity - transparency, computed once
};

struct PointLightF {
  Vec3f position;
  Vec3f intensity;  // colour * intensity, W/sr per channel
};

// Pinhole camera. Ray directions are formed in double and rounded once to float.
struct CameraF {
  Vec3d position;
  Vec3d forward, right, up;  // orthonormal
  double tan_half_fov = 0.0;
  // Primary ray through film position (fx, fy) in pixels from the top-left corner.
  math::Ray generate(double fx, double fy, std::uint32_t width, std::uint32_t height) const;
};

class RenderScene {
 public:
  // The description must have passed validation (scene::load_*); build asserts its invariants.
  // `isa` picks the traversal kernels (accel/isa.h); every choice renders the same bits.
  static RenderScene build(const scene::SceneDesc& desc, accel::Isa isa = accel::best_isa());

  const accel::Geometry& geometry() const { return geometry_; }
  // The material of the object a shape belongs to.
  const MaterialF& material(std::uint32_t shape) const { return materials_[shape_object_[shape]]; }
  // The scene object (index into SceneDesc::objects) a shape belongs to: one shape per sphere,
  // box or plane, one per triangle of a mesh. Shapes of one object share its material, and a
  // closed mesh is one medium, entered through one triangle and left through another.
  std::uint32_t object(std::uint32_t shape) const { return shape_object_[shape]; }
  std::size_t object_count() const { return materials_.size(); }
  const MaterialF& object_material(std::uint32_t object) const { return materials_[object]; }
  const std::vector<PointLightF>& lights() const { return lights_; }
  const CameraF& camera() const { return camera_; }
  bool has_transparency() const { return has_transparency_; }

 private:
  accel::Geometry geometry_;
  std::vector<MaterialF> materials_;         // one per scene object
  std::vector<std::uint32_t> shape_object_;  // shape id -> object index: 4 bytes per triangle
  std::vector<PointLightF> lights_;
  CameraF camera_;
  bool has_transparency_ = false;
};

}  // namespace dtraced::render
