// dtraced::accel geometry: float shapes, robust ray/shape intersection, and the acceleration
// structure over them.
//
// Owns: render-ready shapes (spheres, axis-aligned boxes, infinite planes), a binned-SAH BVH over
// the bounded ones (planes stay outside the tree), nearest-hit queries with conservative
// hit-point error bounds, and the pbrt-v4 style origin offset for secondary rays.
// Thread-safety: a built Geometry is immutable; any number of threads may query it at once.
#pragma once

#include <cstdint>
#include <vector>

#include "math/ray.h"
#include "math/vec.h"

namespace dtraced::accel {

using math::Bounds3f;
using math::Ray;
using math::Vec3f;

struct SphereShape { Vec3f center; float radius = 1.0f; };
struct BoxShape { Vec3f lo, hi; };
struct PlaneShape { Vec3f point; Vec3f normal{0, 1, 0}; };  // normal has unit length

enum class ShapeType : std::uint8_t { kSphere, kBox, kPlane };

struct Shape {
  ShapeType type = ShapeType::kSphere;
  SphereShape sphere;
  BoxShape box;
  PlaneShape plane;
};

// The nearest surface a ray meets.
struct Hit {
  float t = 0.0f;             // ray parameter of the hit, t_min < t < t_max
  std::uint32_t shape = 0;    // index into the shapes given to Geometry::build
  Vec3f p;                    // hit point (computed in the shape's own frame, not as o + t d)
  Vec3f p_error;              // per-axis absolute bound on the rounding error of p
  Vec3f n;                    // unit geometric normal, pointing out of the shape (not flipped)
};

struct BuildStats {
  std::uint32_t nodes = 0;
  std::uint32_t leaves = 0;
  std::uint32_t max_depth = 0;
  double seconds = 0.0;
};

class Geometry {
 public:
  // Builds the BVH (binned SAH) over spheres and boxes; planes are kept in a separate list.
  static Geometry build(std::vector<Shape> shapes);

  // Nearest hit with t in the open interval (ray.t_min, ray.t_max). Returns false on a miss.
  bool intersect(const Ray& ray, Hit& hit) const;

  const std::vector<Shape>& shapes() const { return shapes_; }
  const BuildStats& stats() const { return stats_; }

 private:
  struct Node;
  std::vector<Shape> shapes_;
  std::vector<std::uint32_t> bounded_;  // shape ids in BVH leaf order
  std::vector<std::uint32_t> planes_;   // shape ids of infinite planes
  std::vector<Node> nodes_;
  BuildStats stats_;
};

// Origin for a ray leaving a surface point p (error bound p_error, geometric normal n) in
// direction w: pushed along +-n past the error bound and rounded one more ulp away (pbrt-v4's
// OffsetRayOrigin), so the new ray cannot re-hit the surface it leaves.
Vec3f offset_ray_origin(const Vec3f& p, const Vec3f& p_error, const Vec3f& n, const Vec3f& w);

}  // namespace dtraced::accel
