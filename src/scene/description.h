// dtraced::scene description: the parsed scene as plain values, kept apart from the render-ready
// scene (render/) that adds a BVH and float data. Positions stay in double here; the render layer
// converts. Values only: thread-safe to share read-only.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "image/display.h"
#include "image/image.h"
#include "math/vec.h"

namespace dtraced::scene {

using math::Vec3d;

// Linear RGB, each channel >= 0.
using Color = Vec3d;

// Whitted material. The shaded colour at a hit is
//   (1 - reflectivity - transparency) * local
//   + reflectivity * colour * L(mirror direction)
//   + transparency * (F * L(reflection) + (1 - F) * L(refraction))
// where local = sum over lights of visibility * I / r^2 * cos * (diffuse * colour / pi
// + specular * (shininess + 8) / (8 pi) * (n.h)^shininess), F the exact dielectric Fresnel term.
struct Material {
  Color color{0.8, 0.8, 0.8};  // [0, kMaxAlbedo] per channel
  double diffuse = 1.0;        // [0, 1]
  double specular = 0.0;       // [0, 1]
  double shininess = 32.0;     // >= 0 (Blinn-Phong exponent)
  double reflectivity = 0.0;   // [0, 1]
  double transparency = 0.0;   // [0, 1], reflectivity + transparency <= 1
  double ior = 1.5;            // [kMinIor, kMaxIor]
  bool operator==(const Material&) const = default;
};

struct Sphere {
  Vec3d center;
  double radius = 1.0;  // > 0, a normal float; centre +- radius within the float range
  bool operator==(const Sphere&) const = default;
};

struct Box {  // axis-aligned, min < max on every axis
  Vec3d min;
  Vec3d max;
  bool operator==(const Box&) const = default;
};

struct Plane {  // infinite plane through `point` with unit `normal` (normalised at load)
  Vec3d point;
  Vec3d normal{0, 1, 0};
  bool operator==(const Plane&) const = default;
};

// A triangle mesh from a Wavefront OBJ, placed by scale, then rotation about X, then Y, then Z
// (degrees), then translation: p' = T * Rz * Ry * Rx * S * p, in double, rounded once to float.
struct Mesh {
  // The OBJ text exactly as read (from "file" or inline "obj"). Kept because it is the mesh's
  // canonical form: canonical_json always writes it inline, so a scene means the same, and has
  // the same digest, whether the mesh came from a file or inline.
  std::string obj;
  // The "file" the scene named (as written), empty for an inline mesh. For messages and for
  // `dtraced submit`; not part of the scene's meaning (operator== and the digest ignore it).
  std::string file;
  Vec3d translate{0, 0, 0};
  Vec3d rotate_deg{0, 0, 0};
  Vec3d scale{1, 1, 1};  // every component non-zero
  // The triangles after the transform, three vertices each (v0, v1, v2: triangle i is
  // vertices[3i..3i+2]), in OBJ face order; the normal is normalize(cross(v1 - v0, v2 - v0)).
  // A transform that mirrors (negative determinant) swaps v1 and v2 so the winding, and so the
  // normal, keeps the side the OBJ's faces say. Every coordinate is finite.
  std::vector<math::Vec3f> vertices;
  // Triangles of zero area in float (cross(v1 - v0, v2 - v0) == 0): kept, never hit.
  std::size_t degenerate_triangles = 0;

  std::size_t triangle_count() const { return vertices.size() / 3; }
  bool operator==(const Mesh& o) const {
    return obj == o.obj && translate == o.translate && rotate_deg == o.rotate_deg && scale == o.scale &&
           vertices == o.vertices && degenerate_triangles == o.degenerate_triangles;
  }
};

enum class ObjectType { kSphere, kBox, kPlane, kMesh };

// The "type" names of scene files, indexed by ObjectType.
inline constexpr std::array<std::string_view, 4> kObjectTypeNames = {"sphere", "box", "plane", "mesh"};
inline std::string_view type_name(ObjectType t) { return kObjectTypeNames[static_cast<std::size_t>(t)]; }

// One object: `type` says which of sphere, box and plane holds its geometry (a mesh's is `mesh`).
// The three share their storage (an object is 144 bytes where one field per type took 224: at
// 10M spheres that is 800 MB), as accel::Shape's members do: set `type` and assign the member
// whole (`o.type = ObjectType::kBox; o.box = {lo, hi};`), and read only that member.
struct Object {
  Object() : sphere() {}
  ObjectType type = ObjectType::kSphere;
  union {
    Sphere sphere;  // valid when type == kSphere
    Box box;        // valid when type == kBox
    Plane plane;    // valid when type == kPlane
  };
  // Valid (not null) when type == kMesh. Shared and immutable: a SceneDesc is copied (job
  // submission, overrides) and a mesh may hold millions of triangles.
  std::shared_ptr<const Mesh> mesh;
  Material material;
  // Compares the member `type` names (and the mesh by value).
  bool operator==(const Object& o) const {
    if (type != o.type || !(material == o.material)) return false;
    switch (type) {
      case ObjectType::kSphere:
        return sphere == o.sphere;
      case ObjectType::kBox:
        return box == o.box;
      case ObjectType::kPlane:
        return plane == o.plane;
      case ObjectType::kMesh:
        break;
    }
    return mesh == o.mesh || (mesh != nullptr && o.mesh != nullptr && *mesh == *o.mesh);
  }
};
static_assert(sizeof(Object) == 144);

enum class LightType { kPoint, kSphere, kRect, kDisk };

// The "type" names of scene files, in the order messages list them, and the type each names.
inline constexpr std::array<std::string_view, 4> kLightTypeNames = {"point", "sphere", "disk", "rect"};
inline constexpr std::array<LightType, 4> kLightTypes = {LightType::kPoint, LightType::kSphere, LightType::kDisk,
                                                         LightType::kRect};
inline std::string_view type_name(LightType t) {
  for (std::size_t i = 0; i < kLightTypes.size(); ++i) {
    if (kLightTypes[i] == t) return kLightTypeNames[i];
  }
  return "?";
}

// A light. `intensity * color` is the emitted quantity: radiant intensity I (W/sr) for a point
// light, radiance Le (W/sr/m^2) leaving every point of an area light's emitting surface.
//
//   point   at `position`.
//   sphere  centre `position`, `radius`; emits outwards from its whole surface.
//   disk    centre `position`, `radius`, unit `normal`: emits on the normal's side only.
//   rect    centre `position`, edge vectors `edge_u` and `edge_v` (full lengths, neither zero,
//           not parallel; a parallelogram when they are not perpendicular), unit `normal` =
//           normalize(cross(edge_u, edge_v)), possibly negated: emits on the normal's side only.
//
// Area lights are sampled by Monte Carlo (`samples` shadow rays per shading point), which gives
// soft shadows. They are seen by camera, mirror and refracted rays (their emitting side shows Le;
// the back of a disk or rect is not seen) but are not geometry: they cast no shadows themselves.
// `cast_shadows` false lets a light's light through every object (no shadow rays are traced).
struct Light {
  Vec3d position;
  Color color{1, 1, 1};
  double intensity = 1.0;  // >= 0; color * intensity <= kMaxRadiance per channel
  LightType type = LightType::kPoint;
  double radius = 0.0;        // sphere, disk: [kMinLightRadius, kMaxLightRadius]
  Vec3d normal{0, -1, 0};     // disk, rect: unit
  Vec3d edge_u{1, 0, 0};      // rect
  Vec3d edge_v{0, 0, 1};      // rect
  std::uint32_t samples = 1;  // area lights: shadow rays per shading point, [1, kMaxLightSamples]
  bool cast_shadows = true;
  bool is_area() const { return type != LightType::kPoint; }
  bool operator==(const Light&) const = default;
};

inline constexpr std::uint32_t kMaxLightSamples = 256;

// Limits that keep shading finite in the renderer's float arithmetic; each is derived, from what
// shading computes, beside the check in load_objects.cpp. docs/scene-format.md states them. Any
// size (a radius, an ior) must also stay a normal float once rounded to float.
inline constexpr double kMaxAlbedo = 1.0;        // material colour, per channel
inline constexpr double kMaxRadiance = 0x1p120;  // light colour * intensity and background, per channel
inline constexpr double kMinIor = 0x1p-31;       // ior in [kMinIor, kMaxIor]
inline constexpr double kMaxIor = 0x1p31;
inline constexpr double kMinLightRadius = 0x1p-63;  // sphere and disk lights: radius in [min, max]
inline constexpr double kMaxLightRadius = 0x1p63;

struct Camera {
  Vec3d position{0, 0, 5};
  Vec3d look_at{0, 0, 0};
  Vec3d up{0, 1, 0};
  double fov_deg = 45.0;  // vertical field of view, in (0, 180)
  bool operator==(const Camera&) const = default;
};

// An inclusive range of frame numbers, every `step`-th: first, first + step, ... <= last.
struct FrameRange {
  std::uint32_t first = 0;
  std::uint32_t last = 0;  // >= first
  std::uint32_t step = 1;  // >= 1
  std::uint32_t count() const { return (last - first) / step + 1; }
  // The i-th frame number of the range, i < count().
  std::uint32_t at(std::uint32_t i) const { return first + i * step; }
  bool operator==(const FrameRange&) const = default;
};

// Render settings. The scene file gives defaults; every field can be overridden by a flag.
struct RenderSettings {
  std::uint32_t width = 640;    // [1, kMaxImageSide]
  std::uint32_t height = 480;   // [1, kMaxImageSide]
  std::uint32_t samples = 1;    // per pixel, [1, kMaxSamples]; the most a pixel takes when adaptive
  std::uint32_t max_depth = 8;  // reflection/refraction bounces, [0, kMaxDepth]
  Color background{0, 0, 0};
  std::uint64_t seed = 0;
  std::uint32_t frame = 0;
  // Adaptive sampling (0: off, every pixel takes `samples`). A pixel stops at the first checkpoint
  // n = min_samples, 2 min_samples, 4 min_samples, ... (< samples) where its estimated relative
  // standard error is below error_target; otherwise it takes all `samples`. [0, kMaxErrorTarget]
  double error_target = 0.0;
  std::uint32_t min_samples = 16;  // [1, kMaxSamples]; the first checkpoint
  // A reflected, refracted or see-through branch whose weight on the pixel (product of the
  // reflectances and transmittances on its path) is below this is not traced: it loses at most
  // this fraction of the radiance along it. 1/255 is one step of an 8-bit output for radiance <= 1.
  // [kMinBranchCutoff, kMaxBranchCutoff]
  double branch_cutoff = 1e-6;
  // Animation: frame n shows the scene at time n / fps seconds (and `frame` also seeds the noise,
  // math/rng.h). `frames` is the range a sequence renders when no flag names one; unset, a render
  // is the single frame `frame`. (0, kMaxFps]; frames.count() <= kMaxFrames.
  double fps = 24;
  std::optional<FrameRange> frames{};
  // How 8- and 16-bit outputs show the linear pixels (image/display.h); the pixels themselves, and
  // PFM and EXR files, are the same whatever this says.
  image::DisplayTransform display{};
  bool operator==(const RenderSettings&) const = default;
};

// The limits of render settings, wherever they come from (a scene file, a flag, a request
// body, a config file): every reader checks against these, and only these.
inline constexpr std::uint32_t kMaxImageSide = image::kMaxImageSide;
inline constexpr std::uint32_t kMaxSamples = 65536;
inline constexpr std::uint32_t kMaxDepth = 64;
inline constexpr double kMaxErrorTarget = 1.0;
inline constexpr double kMinBranchCutoff = 1e-9;
inline constexpr double kMaxBranchCutoff = 0.5;
inline constexpr std::uint64_t kMaxSeed = (1ull << 53) - 1;  // seeds survive a trip through a JS double
inline constexpr double kMaxFps = 1000;
inline constexpr std::uint32_t kMaxFrames = 100'000;  // frames in one range

// Keyframed values of an animated scene (scene/animation.h): null for a static scene.
struct Animation;

struct SceneDesc {
  std::vector<Object> objects;
  std::vector<Light> lights;
  Camera camera;
  RenderSettings render;
  // Null for a static scene. Shared and immutable, like a mesh: a SceneDesc is copied per frame.
  std::shared_ptr<const Animation> animation;
  // Compares animations by value (scene/animation.cpp).
  bool operator==(const SceneDesc&) const;
};

}  // namespace dtraced::scene
