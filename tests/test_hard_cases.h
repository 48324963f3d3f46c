// Shared pieces of the numerical hard-case tests (test_hard_cases_*.cpp): long-double reference
// geometry, closed forms for Lambertian shading, and a long-double Whitted reference for scenes of
// clear dielectrics.
//
// Every reference here is computed in long double from the very float rays the renderer traces
// (CameraF::generate) and the float shapes it intersects (RenderScene::geometry().shapes()), so
// the only error under test is the renderer's own rounding, not the float conversion of the
// scene description. Images are small (64-128 px, one sample through each pixel centre unless
// said otherwise) so the tests run in a few seconds in a Release build.
//
// Set DTRACED_HARD_VERBOSE=1 to print the measured margins of every check. Nothing here keeps
// state between calls; references are immutable after construction.
#pragma once

#include <cstdint>
#include <limits>
#include <numbers>
#include <vector>

#include "accel/geometry.h"
#include "math/ray.h"
#include "math/vec.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/description.h"

namespace dtraced::testing {

using LD = long double;
using V3L = math::Vec3<LD>;

inline constexpr LD kPi = std::numbers::pi_v<LD>;

// printf to stdout when DTRACED_HARD_VERBOSE is set; nothing otherwise.
__attribute__((format(printf, 1, 2))) void report(const char* format, ...);

inline V3L ld(const math::Vec3f& v) { return V3L(v); }

// ---------------------------------------------------------------------------------------------
// Scenes and images.

// A square image of side x side, one sample per pixel (through its centre), max depth 8, black
// background, seed 1, the camera at `eye` looking at `look_at` with +y up.
scene::SceneDesc make_desc(math::Vec3d eye, math::Vec3d look_at, double fov_deg, std::uint32_t side);

// Vertical field of view (degrees) that shows `half_extent` above and below the look-at point
// from `distance` away.
double fov_for(double half_extent, double distance);

// The ray the renderer traces for the single sample of pixel (x, y): through the pixel centre.
math::Ray pixel_ray(const render::RenderScene& rs, const scene::RenderSettings& s, std::uint32_t x, std::uint32_t y);

render::Tile render_image(const render::RenderScene& rs, const scene::RenderSettings& s);

inline const float* tile_pixel(const render::Tile& t, std::uint32_t x, std::uint32_t y) {
  return &t.rgb[(std::size_t(y) * t.rect.width + x) * 3];
}

// ---------------------------------------------------------------------------------------------
// Long-double reference geometry. Directions need not have unit length: the references are
// about the exact line through the float origin along the float direction.

struct LineSphere {
  LD h = 0;  // distance from the centre to the line
  bool hit = false;
  LD t0 = 0, t1 = 0;  // roots, t0 <= t1, valid when hit
};
LineSphere line_sphere(const V3L& o, const V3L& d, const V3L& c, LD r);

// Parameter of the line's crossing of a plane (infinite when parallel).
LD line_plane(const V3L& o, const V3L& d, const V3L& p, const V3L& n);

struct LineBox {
  bool hit = false;
  LD t_near = 0, t_far = 0;
  int axis = -1;         // axis of the face the line enters through
  LD edge_distance = 0;  // distance of the entry point from the entry face's border
};
LineBox line_box(const V3L& o, const V3L& d, const V3L& lo, const V3L& hi);

// Distance from c to the segment [a, b].
LD segment_point_distance(const V3L& a, const V3L& b, const V3L& c);

LD angle_between(const V3L& a, const V3L& b);

// Radiance of a Lambertian point under one unshadowed point light (the renderer's local term
// with diffuse = 1, specular = 0): albedo / pi * I * max(0, cos) / dist^2.
LD lambert(LD albedo, LD intensity, const V3L& p, const V3L& n, const V3L& light);

LD cos_to_light(const V3L& p, const V3L& n, const V3L& light);

// Control for the acne tests: would a shadow ray that starts exactly at the hit point the
// geometry reports, with no offset, be blocked? Counted on pixels the reference calls lit, it
// shows how much work offset_ray_origin does in each scene (reported, not asserted: it depends
// on how the intersector treats t near 0).
bool naive_shadow_blocked(const render::RenderScene& rs, const math::Ray& camera_ray);

// ---------------------------------------------------------------------------------------------
// Energy bookkeeping for clear dielectrics under a uniform background B and no light.
//
// Whitted splitting gives every leaf of the ray tree the background, with weights that are
// products of F and 1 - F, so the pixel is exactly B when every branch is followed to its end.
// The renderer drops branches whose weight falls below 1e-6 and stops at max_depth; both only
// lose energy. Float rounding of F, 1 - F and the weighted sums can add a few ulps per interface.

struct EnergyStats {
  double min_ratio = std::numeric_limits<double>::infinity();  // min over pixels and channels of L / B
  double max_ratio = 0.0;
  std::uint64_t non_finite = 0;
  std::uint64_t pixels = 0;
};
EnergyStats energy_of(const render::Tile& tile, const math::Vec3d& background);

// Energy never increases: a few ulps per interface on up to ~64 interfaces.
inline constexpr double kEnergyGainTolerance = 1e-5;

// Long-double Whitted reference for scenes made only of clear dielectrics (transparency 1,
// reflectivity 0, spheres and boxes) under a uniform background and no lights. It follows the
// renderer's documented rules: exact Fresnel, total internal reflection, the stack of media the
// path is in (entering when the shape is not on the stack; eta = n_to / n_from; eta == 1
// continues the same ray), no branch below kMinBranchWeight, no bounce past max_depth. It
// returns the fraction of the background that reaches the pixel and, separately, the weight
// dropped by each of the two cut-offs, which must add up to 1: that is the bookkeeping the
// renderer's float result is held to.
class DielectricReference {
 public:
  struct Result {
    LD background = 0;   // fraction of the background colour in the pixel
    LD lost_depth = 0;   // weight of branches stopped at max_depth
    LD lost_cutoff = 0;  // weight of branches below the 1e-6 cut-off
  };

  DielectricReference(const render::RenderScene& rs, std::uint32_t max_depth);

  // A camera ray, starting inside the shapes `media` (shape indices, outermost first).
  Result trace_camera_ray(const math::Ray& ray, const std::vector<std::uint32_t>& media = {}) const;

 private:
  bool nearest(const V3L& o, const V3L& d, LD t_min, LD& t_hit, std::uint32_t& id, V3L& normal) const;
  LD current_ior(const std::vector<std::uint32_t>& media) const;
  void trace(V3L o, const V3L& d, LD t_min, std::uint32_t depth, LD weight, std::vector<std::uint32_t> media,
             Result& out) const;

  std::vector<accel::Shape> shapes_;
  std::vector<float> iors_;
  std::uint32_t max_depth_;
};

// Agreement of the float renderer with the long-double reference, in units of the background:
// float directions, Fresnel terms and weights carried through up to 64 interfaces (measured
// at most 2e-5, on the 64-deep chains of the grazing cube view).
inline constexpr LD kReferenceTolerance = 1e-4;

// Renders a clear-dielectric scene under a uniform background and compares every pixel with the
// long-double reference. `max_diff` is in units of the background.
struct ReferenceComparison {
  EnergyStats energy;
  LD max_diff = 0;  // max over pixels and channels of |L / B - reference|
  LD max_lost = 0;  // max over pixels of the weight the reference drops
  LD max_lost_depth = 0;
  LD max_bookkeeping = 0;  // max |background + lost - 1| of the reference itself
  std::uint32_t over_tolerance = 0;
  render::TraceStats stats;
};
// `camera_media`: the shapes the camera is inside, outermost first, as the reference sees them.
ReferenceComparison compare_with_reference(const scene::SceneDesc& desc, LD tolerance,
                                           const std::vector<std::uint32_t>& camera_media = {});

// Checks a scene of clear dielectrics under a uniform background: no NaN or Inf, no energy
// created, every pixel equal to the long-double reference, and, when loss_tolerance >= 0,
// nothing lost beyond it (energy conservation of Fresnel splitting: F + (1 - F) = 1 at every
// interface, so only the renderer's two cut-offs can lose light).
void check_clear_dielectrics(const char* name, const scene::SceneDesc& desc, double loss_tolerance,
                             const std::vector<std::uint32_t>& camera_media = {});

}  // namespace dtraced::testing
