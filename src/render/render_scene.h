// dtraced::render render-ready scene: float materials, lights, camera and the acceleration
// structure, built once from a scene::SceneDesc, and the scene's feature set (what the integrator
// needs to model; see SceneFeatures). For an animated scene, AnimatedScene: the shapes that do
// not move are built once (StaticPart) and every frame adds only the layer of those that move.
//
// Thread-safety: immutable after build(); shared read-only by every render thread. AnimatedScene
// is immutable too; frame() builds a new RenderScene per call and may run on any thread.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "accel/geometry.h"
#include "accel/layered.h"
#include "math/ray.h"
#include "math/vec.h"
#include "scene/description.h"
#include "scene/load.h"
#include "util/prefault.h"
#include "util/result.h"

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

enum class AreaShape : std::uint8_t { kSphere, kDisk, kRect };

// An area light, ready to sample (scene::Light has the contract). Le = colour * intensity is the
// radiance leaving every point of its emitting surface.
struct AreaLightF {
  AreaShape shape = AreaShape::kSphere;
  Vec3f center;               // sphere, disk, rect: centre
  float radius = 0.0f;        // sphere, disk
  Vec3f normal;               // disk, rect: unit, on the emitting side
  Vec3f corner;               // rect: center - edge_u / 2 - edge_v / 2
  Vec3f edge_u, edge_v;       // rect: full edges; disk: unit tangents with cross(edge_u, edge_v) = normal
  float area = 0.0f;          // disk, rect: of the emitting surface
  Vec3f radiance;             // Le per channel, W/sr/m^2
  std::uint32_t samples = 1;  // per shading point, [1, scene::kMaxLightSamples]
  bool cast_shadows = true;
};

// What a scene uses, derived once at build: the integrator runs a path specialised to it (a
// feature that is off costs nothing). Every field is a pure function of the description.
struct SceneFeatures {
  bool reflection = false;    // some material has reflectivity > 0
  bool refraction = false;    // some material has transparency > 0
  bool specular = false;      // some material has specular > 0
  bool shadows = false;       // some light casts shadows (point lights always do)
  bool area_lights = false;   // some sphere, disk or rect light
  bool point_lights = false;  // some point light
  bool operator==(const SceneFeatures&) const = default;

  // Every feature on: what the generic integrator path models.
  static constexpr SceneFeatures all() { return {true, true, true, true, true, true}; }
};

// The features that are on, in the order of SceneFeatures' fields, space-separated:
// "reflection refraction specular shadows area-lights point-lights" for all(); "none" if none.
std::string feature_names(const SceneFeatures& f);

// Pinhole camera. Ray directions are formed in double and rounded once to float.
struct CameraF {
  Vec3d position;
  Vec3d forward, right, up;  // orthonormal
  double tan_half_fov = 0.0;
  // Primary ray through film position (fx, fy) in pixels from the top-left corner.
  math::Ray generate(double fx, double fy, std::uint32_t width, std::uint32_t height) const {
    return through(screen_x(fx, width, height), screen_y(fy, height));
  }
  // generate() in its parts, for callers that share a column's or a row's screen coordinate
  // between rays (a packet's pixel block): the same operations, so the same bits.
  double screen_x(double fx, std::uint32_t width, std::uint32_t height) const {
    const double aspect = double(width) / double(height);
    return (2.0 * fx / double(width) - 1.0) * tan_half_fov * aspect;
  }
  double screen_y(double fy, std::uint32_t height) const { return (1.0 - 2.0 * fy / double(height)) * tan_half_fov; }
  math::Ray through(double sx, double sy) const;
};

// The shapes of an animation's objects that do not move, built once: one accel::Layer shared by
// every frame's RenderScene.
struct StaticPart {
  std::vector<bool> moving;                   // per object of the description: its shapes are built per frame
  std::shared_ptr<const accel::Layer> layer;  // the shapes of the other objects
  std::size_t shape_count = 0;                // of the whole scene
  accel::Isa isa = accel::Isa::kScalar;
  unsigned build_threads = 0;  // for each frame's moving layer too (accel::Layer::build)

  // `moving` has one flag per object of `desc` (asserted); `desc` is any frame of the animation:
  // the objects that do not move are the same in all.
  static std::shared_ptr<const StaticPart> build(const scene::SceneDesc& desc, std::vector<bool> moving, accel::Isa isa,
                                                 unsigned build_threads = 0);
};

class RenderSceneBuilder;

class RenderScene {
 public:
  // The description must have passed validation (scene::load_*); build asserts its invariants.
  // `isa` picks the traversal kernels (accel/isa.h); every choice renders the same bits. The BVH
  // is built on up to `build_threads` threads (accel::Geometry::build; 0: the CPUs this process may use),
  // which changes nothing but the time it takes.
  static RenderScene build(const scene::SceneDesc& desc, accel::Isa isa = accel::best_isa(),
                           unsigned build_threads = 0);

  // One frame of an animation (`frame`: scene::scene_at_frame of the description `part` was built
  // from): the shapes of moving objects are built now, the others are part's shared layer.
  // Renders the same bits as build(frame, part.isa), shape ids staying the description's, but
  // where build splits a static scene by transparency and a shadow ray meets an opaque and a
  // transparent surface at exactly the same t, the transparent one with the smaller shape id: a
  // frame's walk over every shape passes the opaque one there, the split scene's opaque query
  // does not (pixel version 5).
  static RenderScene build_frame(const scene::SceneDesc& frame, const StaticPart& part);

  // Ray queries over the scene's shapes, one layer or two (accel/layered.h); shape ids are
  // scene-wide either way.
  const accel::LayeredGeometry& geometry() const { return geometry_; }
  // The material of the object a shape belongs to.
  const MaterialF& material(std::uint32_t shape) const { return materials_[object(shape)]; }
  // The scene object (index into SceneDesc::objects) a shape belongs to: one shape per sphere,
  // box or plane, one per triangle of a mesh. Shapes of one object share its material, and a
  // closed mesh is one medium, entered through one triangle and left through another.
  std::uint32_t object(std::uint32_t shape) const { return shape_object_.empty() ? shape : shape_object_[shape]; }
  std::size_t object_count() const { return materials_.size(); }
  const MaterialF& object_material(std::uint32_t object) const { return materials_[object]; }
  // Point lights, in scene order (area lights are not among them).
  const std::vector<PointLightF>& lights() const { return lights_; }
  // Sphere, disk and rect lights, in scene order.
  const std::vector<AreaLightF>& area_lights() const { return area_lights_; }
  const SceneFeatures& features() const { return features_; }
  const CameraF& camera() const { return camera_; }
  bool has_transparency() const { return has_transparency_; }
  // The transparent objects that contain the camera, outermost first: the media every camera path
  // starts in, so a camera inside glass sees its first crossing as leaving the glass. Spheres and
  // boxes contain it when it is strictly inside; a mesh (a closed one: an open mesh has no inside)
  // when a ray from the camera crosses it an odd number of times; planes never. Nested media are
  // ordered by where that ray leaves them, farthest first. Empty without transparent objects.
  const std::vector<std::uint32_t>& camera_media() const { return camera_media_; }

 private:
  friend class RenderSceneBuilder;
  static RenderScene assemble(const scene::SceneDesc& desc, const StaticPart& part);
  // Lights, camera and camera media, after geometry_, materials_ and shape_object_.
  void finish(const scene::SceneDesc& desc, const std::vector<std::pair<std::uint32_t, bool>>& transparent);

  accel::LayeredGeometry geometry_;
  std::vector<MaterialF> materials_;  // one per scene object
  // Shape id -> object index: 4 bytes per triangle. Empty when every object is one shape (no
  // meshes: the ids are the same), which saves 4 bytes a sphere.
  std::vector<std::uint32_t> shape_object_;
  std::vector<PointLightF> lights_;
  std::vector<AreaLightF> area_lights_;
  SceneFeatures features_;
  CameraF camera_;
  bool has_transparency_ = false;
  std::vector<std::uint32_t> camera_media_;  // object indices, outermost first
};

// A static scene's RenderScene from its objects one at a time, as a load reads them
// (scene::LoadOptions::object_sink), so that a large scene's description objects (144 bytes a
// sphere) are never held: only the render-ready shape, material and owner (84 bytes a sphere)
// are kept of each, and nothing of the description is alive during the BVH build. The same bits
// as RenderScene::build of the description with those objects (which builds through it).
//
//   render::RenderSceneBuilder builder;
//   scene::LoadOptions options;
//   options.object_sink = &builder;
//   scene::LoadResult loaded = scene::load_scene_file(path, options);
//   if (loaded.ok() && !scene::is_animated(*loaded.scene))
//     rs = std::move(builder).build(*loaded.scene, isa, threads);
//
// Thread-safety: one builder per scene, used by one thread at a time (the load's reader thread,
// then the caller: the load joins its threads before it returns).
class RenderSceneBuilder final : public scene::ObjectSink {
 public:
  void reserve(std::size_t objects) override;
  void add(std::size_t index, const scene::Object& object) override;
  // The scene: the objects added (in order; `index` must count up from 0, asserted), then those
  // of `desc` (none after a load into this builder), and desc's camera and lights. Empties the
  // builder.
  RenderScene build(const scene::SceneDesc& desc, accel::Isa isa = accel::best_isa(), unsigned build_threads = 0) &&;
  std::size_t object_count() const { return materials_.size(); }

  // What build() needs of the objects added so far, for a binary cache of the scene
  // (worker/scene_cache.h): views of the builder's arrays, valid until it changes.
  struct Parts {
    std::span<const accel::Shape> shapes;
    std::span<const MaterialF> materials;
    std::span<const std::uint32_t> shape_object;  // empty unless some object is not one shape
    std::span<const std::pair<std::uint32_t, bool>> transparent;
    SceneFeatures features;  // reflection and specular
  };
  Parts parts() const { return {shapes_, materials_, shape_object_, transparent_, features_}; }
  // A builder holding these parts, as parts() gave them: build() then gives the same scene as the
  // builder they came from. An error names what is inconsistent (counts, an owner or a
  // transparent object out of range, an unknown shape type): the parts came from a file.
  static util::Result<RenderSceneBuilder> from_parts(std::vector<accel::Shape> shapes, std::vector<MaterialF> materials,
                                                     std::vector<std::uint32_t> shape_object,
                                                     std::vector<std::pair<std::uint32_t, bool>> transparent,
                                                     SceneFeatures features);

 private:
  friend class RenderScene;
  // Room for exactly these many objects and shapes (RenderScene::build knows both).
  void reserve_exact(std::size_t objects, std::size_t shapes);

  std::vector<accel::Shape> shapes_;
  std::vector<MaterialF> materials_;
  // Empty while every object so far is one shape (RenderScene::shape_object_); filled from the
  // first mesh (or other object of more or fewer shapes) on, which sets mapped_.
  std::vector<std::uint32_t> shape_object_;
  bool mapped_ = false;
  // (object index, is a mesh) of each transparent object: what camera_media needs of them.
  std::vector<std::pair<std::uint32_t, bool>> transparent_;
  SceneFeatures features_;  // reflection and specular so far
  // Maps the pages of the arrays reserve() made room for, on a thread of its own; joined before
  // they move (reserve, a growing add, build, the builder's end).
  util::Prefault prefault_;
};

// A scene description prepared for rendering any of its frames. Built once per description.
class AnimatedScene {
 public:
  // A static scene (scene::is_animated false) is built once, as RenderScene::build; an animated
  // one gets its StaticPart from scene::moving_objects. The BVHs are built on up to
  // `build_threads` threads (0: the CPUs this process may use): give the render's thread count.
  static AnimatedScene prepare(const scene::SceneDesc& desc, accel::Isa isa = accel::best_isa(),
                               unsigned build_threads = 0);
  // A static scene built already (e.g. through a RenderSceneBuilder, while it loaded): every
  // frame is `scene`.
  static AnimatedScene still(RenderScene scene);
  // An animated scene split by an explicit mask (one flag per object), whatever is_animated says.
  static AnimatedScene prepare(const scene::SceneDesc& desc, std::vector<bool> moving,
                               accel::Isa isa = accel::best_isa(), unsigned build_threads = 0);

  // The render-ready scene of frame n: scene::scene_at_frame, then the frame's moving layer (the
  // static layer shared). For a static scene, the one prepared RenderScene, whatever n. Render
  // with the settings of scene::scene_at_frame(desc, n).render (the frame also seeds the noise).
  std::shared_ptr<const RenderScene> frame(std::uint32_t n) const;

  bool animated() const { return still_ == nullptr; }
  // The shared part of an animated scene; null for a static one.
  const StaticPart* static_part() const { return part_.get(); }

 private:
  std::shared_ptr<const scene::SceneDesc> desc_;  // animated: the description frames come from
  std::shared_ptr<const StaticPart> part_;        // animated
  std::shared_ptr<const RenderScene> still_;      // static
};

}  // namespace dtraced::render
