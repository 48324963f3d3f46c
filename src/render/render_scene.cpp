#include "render/render_scene.h"

#include <algorithm>
#include <cassert>
#include <cmath>
#include <limits>
#include <numbers>

#include <fmt/format.h>

#include "math/det_math.h"
#include "scene/animation.h"
#include "util/huge_pages.h"

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

std::size_t shape_count_of(const scene::Object& o) {
  return o.type == scene::ObjectType::kMesh ? o.mesh->triangle_count() : 1;
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

// Whether the point o is strictly inside a sphere or box (as the renderer has them, in float).
bool solid_contains(const accel::Shape& s, const Vec3f& o) {
  if (s.type == accel::ShapeType::kSphere) {
    const Vec3d f = Vec3d(o) - Vec3d(s.sphere.center);
    const double r = s.sphere.radius;
    return math::dot(f, f) < r * r;
  }
  if (s.type == accel::ShapeType::kBox) {
    const accel::BoxShape& b = s.box;
    return o.x > b.lo.x && o.x < b.hi.x && o.y > b.lo.y && o.y < b.hi.y && o.z > b.lo.z && o.z < b.hi.z;
  }
  return false;
}

// Whether a static scene's shapes are worth splitting into an opaque and a transparent layer
// (`clear`: the ids of the transparent ones, sorted). Only with a tree for the opaque shapes (at
// least 64 bounded ones: Geometry::build gives a scene of under 64 shapes none) and a transparent
// part that is small beside the scene, its bounding box's diagonal at most a quarter of the opaque
// shapes' (their bounds from at most 65,536 of them, evenly spaced in id order): every camera and
// secondary ray then queries both layers, which pays only where most rays can skip the
// transparent one (LayeredGeometry culls them by its bounding sphere). Measured, render phase against one layer
// (medians of base and split alternated, 1 thread): scenes/mesh.json (one glass mesh, diagonal ratio 0.05) 1.05x on
// AVX-512 and 1.07x on SSE4 (10 pairs each; 2 threads 1.08x and 1.06x); split as well, whitted10 (11 shapes, no tree)
// 0.92x and 0.91x, spheres10k (glass spheres over the whole field, ratio about 1) 0.90x and 0.85x (5 pairs each).
bool split_pays(const std::vector<accel::Shape>& shapes, const std::vector<std::uint32_t>& clear) {
  constexpr std::size_t kMinShapes = 64;
  constexpr std::size_t kSample = 65536;
  if (clear.empty() || shapes.size() - clear.size() < kMinShapes) return false;
  math::Bounds3f glass;
  for (const std::uint32_t id : clear) glass.extend(accel::shape_bounds(shapes[id]));
  const std::size_t step = (shapes.size() + kSample - 1) / kSample;
  math::Bounds3f all;
  std::size_t bounded = 0;  // opaque shapes of the sample with finite bounds
  std::size_t next = 0;     // the index into `clear` of the first transparent id >= i
  for (std::size_t i = 0; i < shapes.size(); i += step) {
    while (next < clear.size() && clear[next] < i) ++next;
    if (next < clear.size() && clear[next] == i) continue;
    const math::Bounds3f b = accel::shape_bounds(shapes[i]);
    if (b.empty() || !math::is_finite(b.lo) || !math::is_finite(b.hi)) continue;  // a plane, an invalid shape
    all.extend(b);
    ++bounded;
  }
  // Every shape was looked at where step is 1; past 65,536 shapes a sample of at most 65,536
  // stands for them.
  if (glass.empty() || bounded < kMinShapes) return false;
  const Vec3f g = glass.extent(), a = all.extent();
  const float g2 = math::dot(g, g), a2 = math::dot(a, a);
  // Infinite or NaN bounds (a transparent plane) compare false: no split.
  return g2 * 16.0f <= a2;
}

// (object index, is a mesh) of each transparent object of `objects`, in order.
std::vector<std::pair<std::uint32_t, bool>> transparent_objects(const std::vector<scene::Object>& objects) {
  std::vector<std::pair<std::uint32_t, bool>> out;
  for (std::uint32_t i = 0; i < objects.size(); ++i) {
    if (objects[i].material.transparency > 0.0) out.push_back({i, objects[i].type == scene::ObjectType::kMesh});
  }
  return out;
}

// The first shape of `object`, which has one at least: shape ids follow the objects' order, so
// `shape_object` (RenderScene::shape_object_, empty for the identity) never decreases.
std::uint32_t first_shape_of(const std::vector<std::uint32_t>& shape_object, std::uint32_t object) {
  if (shape_object.empty()) return object;
  return std::uint32_t(std::lower_bound(shape_object.begin(), shape_object.end(), object) - shape_object.begin());
}

// See RenderScene::camera_media(). `transparent`: (object index, is a mesh) of each transparent
// object, in order; `shape_object`: RenderScene::shape_object_ (empty: the identity).
// Nothing per object or per shape is allocated unless a transparent mesh needs its crossings
// counted: for a scene of 1M spheres, some of glass, that was 12 MB faulted in during the load
// and kept by the allocator through the render.
std::vector<std::uint32_t> find_camera_media(const accel::LayeredGeometry& geometry, std::size_t object_count,
                                             const std::vector<std::pair<std::uint32_t, bool>>& transparent,
                                             const std::vector<std::uint32_t>& shape_object, const Vec3f& camera) {
  // Any direction serves closed shapes; this one lies off every axis and diagonal, so a probe from
  // a camera placed on a round coordinate does not run along the edges of a mesh laid out on a grid.
  math::Ray probe;
  probe.o = camera;
  probe.d = math::normalize(Vec3f{0.5361f, 0.6712f, 0.5118f});
  // Meshes: count the probe's crossings of each object, walking from hit to hit as a path through
  // an index-matched surface does (t_min moves to the hit, so a ray through an edge shared by two
  // triangles crosses once).
  std::vector<std::uint32_t> crossings;
  std::vector<float> last_t;
  const bool meshes = std::any_of(transparent.begin(), transparent.end(), [](const auto& t) { return t.second; });
  if (meshes) {
    crossings.assign(object_count, 0);
    last_t.assign(object_count, 0.0f);
    math::Ray walk = probe;
    accel::Hit hit;
    for (std::size_t n = 0; n < geometry.shape_count() && geometry.intersect(walk, hit); ++n) {
      const std::uint32_t object = shape_object.empty() ? hit.shape : shape_object[hit.shape];
      ++crossings[object];
      last_t[object] = hit.t;
      walk.t_min = hit.t;
    }
  }
  struct Medium {
    float exit_t;
    std::uint32_t object;
  };
  std::vector<Medium> media;
  for (const auto& [i, is_mesh] : transparent) {
    if (is_mesh) {
      if (crossings[i] % 2 == 1) media.push_back({last_t[i], i});
      continue;
    }
    const std::uint32_t first = first_shape_of(shape_object, i);
    const accel::Shape& shape = geometry.shape(first);
    if (!solid_contains(shape, camera)) continue;
    accel::Hit exit;
    const bool found = accel::intersect_shape(shape, first, probe, exit);
    media.push_back({found ? exit.t : std::numeric_limits<float>::infinity(), i});
  }
  // Outermost (farthest exit) first; ties in scene order.
  std::stable_sort(media.begin(), media.end(), [](const Medium& a, const Medium& b) { return a.exit_t > b.exit_t; });
  std::vector<std::uint32_t> out;
  for (const Medium& m : media) out.push_back(m.object);
  return out;
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

math::Ray CameraF::through(double sx, double sy) const {
  const Vec3d dir = math::normalize(forward + right * sx + up * sy);
  math::Ray ray;
  ray.o = Vec3f(position);
  ray.d = math::normalize(Vec3f(dir));
  return ray;
}

std::shared_ptr<const StaticPart> StaticPart::build(const scene::SceneDesc& desc, std::vector<bool> moving,
                                                    accel::Isa isa, unsigned build_threads) {
  assert(moving.size() == desc.objects.size());
  auto part = std::make_shared<StaticPart>();
  std::vector<accel::Shape> shapes;
  std::vector<std::uint32_t> ids;
  for (std::size_t i = 0; i < desc.objects.size(); ++i) {
    const std::size_t first = part->shape_count;
    part->shape_count += shape_count_of(desc.objects[i]);
    if (moving[i]) continue;
    append_shapes(desc.objects[i], shapes);
    for (std::size_t id = first; id < part->shape_count; ++id) ids.push_back(static_cast<std::uint32_t>(id));
  }
  assert(part->shape_count <= std::numeric_limits<std::uint32_t>::max());
  part->layer = accel::Layer::build(std::move(shapes), std::move(ids), isa, build_threads);
  part->moving = std::move(moving);
  part->isa = isa;
  part->build_threads = build_threads;
  return part;
}

RenderScene RenderScene::build(const scene::SceneDesc& desc, accel::Isa isa, unsigned build_threads) {
  RenderSceneBuilder builder;
  std::size_t shape_count = 0;
  for (const scene::Object& o : desc.objects) shape_count += shape_count_of(o);
  builder.reserve_exact(desc.objects.size(), shape_count);
  return std::move(builder).build(desc, isa, build_threads);
}

RenderScene RenderScene::build_frame(const scene::SceneDesc& frame, const StaticPart& part) {
  return assemble(frame, part);
}

// Only the shapes of moving objects are built, into the frame's own layer; the others are part's.
RenderScene RenderScene::assemble(const scene::SceneDesc& desc, const StaticPart& part) {
  assert(part.moving.size() == desc.objects.size());
  RenderScene rs;
  std::size_t shape_count = 0;
  for (const scene::Object& o : desc.objects) shape_count += shape_count_of(o);
  // Shape ids are 32-bit (accel::Hit::shape); the loader's limits keep far below that.
  assert(shape_count <= std::numeric_limits<std::uint32_t>::max());
  assert(part.shape_count == shape_count);
  std::vector<accel::Shape> shapes;  // the moving ones
  std::vector<std::uint32_t> ids;    // the scene-wide id of each of `shapes`
  rs.shape_object_.reserve(shape_count);
  rs.materials_.reserve(desc.objects.size());
  util::advise_huge_pages_for(rs.shape_object_);  // first touches are costly page faults (util/huge_pages.h)
  util::advise_huge_pages_for(rs.materials_);
  for (std::size_t i = 0; i < desc.objects.size(); ++i) {
    const scene::Object& o = desc.objects[i];
    const std::size_t first = rs.shape_object_.size();
    const std::size_t end = first + shape_count_of(o);
    if (part.moving[i]) {
      append_shapes(o, shapes);
      for (std::size_t id = first; id < end; ++id) ids.push_back(static_cast<std::uint32_t>(id));
    }
    rs.shape_object_.resize(end, static_cast<std::uint32_t>(i));
    rs.materials_.push_back(to_material(o.material));
    rs.features_.reflection = rs.features_.reflection || o.material.reflectivity > 0.0;
    rs.features_.specular = rs.features_.specular || o.material.specular > 0.0;
  }
  const auto transparent = transparent_objects(desc.objects);
  rs.has_transparency_ = !transparent.empty();
  rs.features_.refraction = rs.has_transparency_;
  rs.geometry_ = accel::LayeredGeometry(
      part.layer, accel::Layer::build(std::move(shapes), std::move(ids), part.isa, part.build_threads), shape_count);
  rs.finish(desc, transparent);
  return rs;
}

void RenderScene::finish(const scene::SceneDesc& desc, const std::vector<std::pair<std::uint32_t, bool>>& transparent) {
  for (const scene::Light& l : desc.lights) {
    if (l.is_area()) {
      area_lights_.push_back(to_area_light(l));
      features_.area_lights = true;
      features_.shadows = features_.shadows || l.cast_shadows;
    } else {
      lights_.push_back({to_f(l.position), to_f(l.color * l.intensity)});
      features_.point_lights = true;
      features_.shadows = true;
    }
  }
  const scene::Camera& c = desc.camera;
  camera_.position = c.position;
  camera_.forward = math::normalize(c.look_at - c.position);
  camera_.right = math::normalize(math::cross(camera_.forward, c.up));
  camera_.up = math::cross(camera_.right, camera_.forward);
  camera_.tan_half_fov = math::det::tan(c.fov_deg * std::numbers::pi / 360.0);
  assert(math::is_finite(camera_.right));
  if (has_transparency_) {
    // Where camera rays start (CameraF::generate).
    const Vec3f origin(camera_.position);
    camera_media_ = find_camera_media(geometry_, materials_.size(), transparent, shape_object_, origin);
  }
}

void RenderSceneBuilder::reserve(std::size_t objects) {
  if (objects <= materials_.capacity() && objects <= shapes_.capacity()) return;
  prefault_.join();  // before the arrays move
  // Spheres, boxes and planes are one shape each; a mesh's triangles grow the shapes beyond.
  if (objects > materials_.capacity()) {
    materials_.reserve(objects);
    util::advise_huge_pages_for(materials_);  // first touches are costly page faults (util/huge_pages.h)
  }
  if (objects > shapes_.capacity()) {
    shapes_.reserve(objects);
    util::advise_huge_pages_for(shapes_);
  }
  // The loader reserves once it can predict the object count (1M spheres: 80 MB); the arrays'
  // pages are mapped on another thread while this one parses (util/prefault.h).
  prefault_.start({util::capacity_range(shapes_), util::capacity_range(materials_)});
}

void RenderSceneBuilder::reserve_exact(std::size_t objects, std::size_t shapes) {
  reserve(objects);
  if (shapes > shapes_.capacity()) {
    prefault_.join();  // before the shapes move
    shapes_.reserve(shapes);
    util::advise_huge_pages_for(shapes_);
  }
  if (shapes != objects && shapes > shape_object_.capacity()) {
    shape_object_.reserve(shapes);
    util::advise_huge_pages_for(shape_object_);
  }
}

void RenderSceneBuilder::add(std::size_t index, const scene::Object& o) {
  assert(index == materials_.size());
  const std::size_t first = shapes_.size();
  const std::size_t count = shape_count_of(o);
  if (first + count > shapes_.capacity()) prefault_.join();  // the shapes move
  if (!mapped_ && count != 1) {
    // The first object that is not one shape: the ids so far were the object indices.
    mapped_ = true;
    shape_object_.reserve(std::max(shapes_.capacity(), first + count));
    shape_object_.resize(first);
    for (std::size_t id = 0; id < first; ++id) shape_object_[id] = static_cast<std::uint32_t>(id);
  }
  append_shapes(o, shapes_);
  if (mapped_) shape_object_.resize(first + count, static_cast<std::uint32_t>(index));
  materials_.push_back(to_material(o.material));
  if (o.material.transparency > 0.0) {
    transparent_.push_back({static_cast<std::uint32_t>(index), o.type == scene::ObjectType::kMesh});
  }
  features_.reflection = features_.reflection || o.material.reflectivity > 0.0;
  features_.specular = features_.specular || o.material.specular > 0.0;
}

util::Result<RenderSceneBuilder> RenderSceneBuilder::from_parts(std::vector<accel::Shape> shapes,
                                                                std::vector<MaterialF> materials,
                                                                std::vector<std::uint32_t> shape_object,
                                                                std::vector<std::pair<std::uint32_t, bool>> transparent,
                                                                SceneFeatures features) {
  const std::size_t objects = materials.size();
  if (shape_object.empty() ? shapes.size() != objects : shape_object.size() != shapes.size()) {
    return util::Error{fmt::format("{} shapes, {} objects and {} owners do not fit together", shapes.size(), objects,
                                   shape_object.size())};
  }
  for (std::size_t i = 0; i < shapes.size(); ++i) {
    if (static_cast<std::uint8_t>(shapes[i].type) > static_cast<std::uint8_t>(accel::ShapeType::kTriangle)) {
      return util::Error{fmt::format("shape {} has an unknown type", i)};
    }
  }
  // Owners count up from 0 by at most one, as add() makes them, and end at the last object.
  for (std::size_t i = 0; i < shape_object.size(); ++i) {
    const std::uint32_t previous = i == 0 ? 0 : shape_object[i - 1];
    if (shape_object[i] < previous || shape_object[i] > previous + 1 || (i == 0 && shape_object[0] != 0)) {
      return util::Error{fmt::format("shape {} has owner {} after {}", i, shape_object[i], previous)};
    }
  }
  if (!shape_object.empty() && shape_object.back() + std::size_t{1} != objects) {
    return util::Error{fmt::format("the last shape's owner is not the last of {} objects", objects)};
  }
  for (const auto& [object, mesh] : transparent) {
    if (object >= objects) return util::Error{fmt::format("transparent object {} of {}", object, objects)};
  }
  RenderSceneBuilder b;
  b.mapped_ = !shape_object.empty();
  b.shapes_ = std::move(shapes);
  b.materials_ = std::move(materials);
  b.shape_object_ = std::move(shape_object);
  b.transparent_ = std::move(transparent);
  b.features_ = features;
  return b;
}

RenderScene RenderSceneBuilder::build(const scene::SceneDesc& desc, accel::Isa isa, unsigned build_threads) && {
  prefault_.join();
  for (const scene::Object& o : desc.objects) add(materials_.size(), o);
  // Shape ids are 32-bit (accel::Hit::shape); the loader's limits keep far below that.
  assert(shapes_.size() <= std::numeric_limits<std::uint32_t>::max());
  RenderScene rs;
  rs.materials_ = std::move(materials_);
  rs.shape_object_ = std::move(shape_object_);
  rs.features_ = features_;
  rs.has_transparency_ = !transparent_.empty();
  rs.features_.refraction = rs.has_transparency_;
  // The shapes a shadow ray crosses (Tracer::shadow_crossing passes light where the float
  // transparency is > 0) go to a layer of their own, their places in the opaque layer holes, when
  // the scene has both kinds and split_pays: a shadow ray then asks the opaque layer for any hit
  // and walks its crossings over the transparent layer only.
  std::vector<accel::Shape> clear;
  std::vector<std::uint32_t> clear_ids;
  const auto passes = [&](std::uint32_t object) { return rs.materials_[object].transparency > 0.0f; };
  if (rs.shape_object_.empty()) {
    for (const auto& [object, mesh] : transparent_) {
      if (passes(object)) clear_ids.push_back(object);
    }
    // In object order from a load; parts from a file may come in any order.
    std::sort(clear_ids.begin(), clear_ids.end());
    clear_ids.erase(std::unique(clear_ids.begin(), clear_ids.end()), clear_ids.end());
  } else if (!transparent_.empty()) {
    for (std::size_t id = 0; id < shapes_.size(); ++id) {
      if (passes(rs.shape_object_[id])) clear_ids.push_back(static_cast<std::uint32_t>(id));
    }
  }
  if (split_pays(shapes_, clear_ids)) {
    clear.reserve(clear_ids.size());
    for (const std::uint32_t id : clear_ids) {
      clear.push_back(shapes_[id]);
      shapes_[id] = accel::LayeredGeometry::hole();
    }
    auto layer = accel::Layer::build(std::move(clear), std::move(clear_ids), isa, build_threads);
    rs.geometry_ =
        accel::LayeredGeometry(accel::Geometry::build(std::move(shapes_), isa, build_threads), std::move(layer));
  } else {
    rs.geometry_ = accel::LayeredGeometry(accel::Geometry::build(std::move(shapes_), isa, build_threads));
  }
  rs.finish(desc, transparent_);
  *this = RenderSceneBuilder();
  return rs;
}

AnimatedScene AnimatedScene::prepare(const scene::SceneDesc& desc, accel::Isa isa, unsigned build_threads) {
  if (!scene::is_animated(desc)) {
    AnimatedScene out;
    out.still_ = std::make_shared<const RenderScene>(RenderScene::build(desc, isa, build_threads));
    return out;
  }
  return prepare(desc, scene::moving_objects(desc), isa, build_threads);
}

AnimatedScene AnimatedScene::still(RenderScene scene) {
  AnimatedScene out;
  out.still_ = std::make_shared<const RenderScene>(std::move(scene));
  return out;
}

AnimatedScene AnimatedScene::prepare(const scene::SceneDesc& desc, std::vector<bool> moving, accel::Isa isa,
                                     unsigned build_threads) {
  AnimatedScene out;
  out.desc_ = std::make_shared<const scene::SceneDesc>(desc);
  // Objects that do not move are the same at every time; time 0 is as good as any.
  out.part_ = StaticPart::build(scene::scene_at(desc, 0.0), std::move(moving), isa, build_threads);
  return out;
}

std::shared_ptr<const RenderScene> AnimatedScene::frame(std::uint32_t n) const {
  if (still_) return still_;
  return std::make_shared<const RenderScene>(RenderScene::build_frame(scene::scene_at_frame(*desc_, n), *part_));
}

}  // namespace dtraced::render
