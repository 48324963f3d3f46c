// Loading objects into a sink (scene::LoadOptions::object_sink) and render::RenderSceneBuilder,
// which builds a RenderScene from them: the sink gets exactly the objects the description would
// hold, with the same errors and warnings, and the builder's scene is RenderScene::build's, bit for
// bit (shapes, materials, owners, features, camera media and rendered pixels).
#include <bit>
#include <cstdint>
#include <cstring>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "render/render_scene.h"
#include "render/tile.h"
#include "scene/generate.h"
#include "scene/tiling.h"
#include "scene_testing.h"

namespace {

using namespace scene_testing;
namespace scene = dtraced::scene;
namespace render = dtraced::render;
namespace accel = dtraced::accel;

// Keeps what it is given: the indices, the objects and every reserve() asked for.
class Keeper final : public scene::ObjectSink {
 public:
  void reserve(std::size_t objects) override { reserves.push_back(objects); }
  void add(std::size_t index, const scene::Object& object) override {
    indices.push_back(index);
    objects.push_back(object);
  }
  std::vector<std::size_t> reserves;
  std::vector<std::size_t> indices;
  std::vector<scene::Object> objects;
};

// A transparent closed mesh (a tetrahedron) around the camera, a glass sphere around it too, a box,
// a plane, mirrors and diffuse spheres: every kind of shape, and camera media of both kinds.
std::string mixed_scene() {
  const std::string tetra = R"(v -4 -4 -4\nv 12 -4 -4\nv -4 12 -4\nv -4 -4 12\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n)";
  return fmt::format(R"({{
    "camera": {{"position": [0.1, 0.2, 0.3], "look_at": [0, 0, -5]}},
    "render": {{"width": 24, "height": 16, "samples": 1, "max_depth": 6}},
    "scene_objects": [
      {{"type": "plane", "loc": [0, -2, 0], "normal": [0, 1, 0]}},
      {{"type": "sphere", "loc": [0, 0, -5], "radius": 1, "material": {{"specular": 0.5, "reflectivity": 0.3}}}},
      {{"type": "mesh", "obj": "{}", "material": {{"transparency": 0.9, "ior": 1.3}}}},
      {{"type": "box", "min": [1, -1, -7], "max": [2, 0, -6]}},
      {{"type": "sphere", "loc": [0, 0, 0], "radius": 3, "material": {{"transparency": 0.5, "ior": 1.2}}}},
      {{"type": "sphere", "loc": [-2, 0, -6], "radius": 0.5}}
    ],
    "scene_lights": [{{"type": "point", "loc": [0, 5, 0]}}]
  }})",
                     tetra);
}

// The floats of a shape's member, as bits (memcmp of whole shapes would compare padding).
std::vector<std::uint32_t> shape_bits(const accel::Shape& s) {
  std::vector<float> f;
  switch (s.type) {
    case accel::ShapeType::kSphere:
      f = {s.sphere.center.x, s.sphere.center.y, s.sphere.center.z, s.sphere.radius};
      break;
    case accel::ShapeType::kBox:
      f = {s.box.lo.x, s.box.lo.y, s.box.lo.z, s.box.hi.x, s.box.hi.y, s.box.hi.z};
      break;
    case accel::ShapeType::kPlane:
      f = {s.plane.point.x, s.plane.point.y, s.plane.point.z, s.plane.normal.x, s.plane.normal.y, s.plane.normal.z};
      break;
    case accel::ShapeType::kTriangle:
      for (const auto* v : {&s.triangle.v0, &s.triangle.v1, &s.triangle.v2}) f.insert(f.end(), {v->x, v->y, v->z});
      break;
  }
  std::vector<std::uint32_t> bits{std::uint32_t(s.type)};
  for (const float x : f) bits.push_back(std::bit_cast<std::uint32_t>(x));
  return bits;
}

// `same_tree`: both built for one isa (the SIMD isas build other trees than the scalar one).
// The shapes are compared scene-wide (LayeredGeometry::shape), so that a scene split by
// transparency compares its real shapes, not the opaque layer's holes.
void require_same_scene(const render::RenderScene& a, const render::RenderScene& b, bool same_tree = true) {
  const accel::LayeredGeometry& ga = a.geometry();
  const accel::LayeredGeometry& gb = b.geometry();
  REQUIRE(ga.shape_count() == gb.shape_count());
  REQUIRE((ga.transparent() == nullptr) == (gb.transparent() == nullptr));
  for (std::uint32_t i = 0; i < ga.shape_count(); ++i) {
    INFO("shape " << i);
    REQUIRE(shape_bits(ga.shape(i)) == shape_bits(gb.shape(i)));
    REQUIRE(a.object(i) == b.object(i));
  }
  REQUIRE(a.object_count() == b.object_count());
  for (std::uint32_t i = 0; i < a.object_count(); ++i) {
    REQUIRE(std::memcmp(&a.object_material(i), &b.object_material(i), sizeof(render::MaterialF)) == 0);
  }
  CHECK(a.features() == b.features());
  CHECK(a.has_transparency() == b.has_transparency());
  CHECK(a.camera_media() == b.camera_media());
  CHECK(a.lights().size() == b.lights().size());
  if (same_tree) {
    CHECK(ga.fixed()->geometry.stats().tree_hash == gb.fixed()->geometry.stats().tree_hash);
    if (ga.transparent() != nullptr) {
      CHECK(ga.transparent()->geometry.stats().tree_hash == gb.transparent()->geometry.stats().tree_hash);
    }
  }
}

}  // namespace

TEST_CASE("a sink gets the objects the description would hold, in order, with the same warnings", "[scene][sink]") {
  const std::string json = canonical_json(scene::generate_sphere_field(3000, 7));
  for (const std::uint64_t parallel : {std::uint64_t(0), scene::kParallelLoadBytes}) {
    INFO("parallel_min_bytes " << parallel);
    LoadOptions plain;
    plain.parallel_min_bytes = parallel;
    const LoadResult whole = load_scene_string(json, "s.json", plain);
    REQUIRE(whole.ok());
    Keeper keeper;
    LoadOptions options = plain;
    options.object_sink = &keeper;
    const LoadResult sunk = load_scene_string(json, "s.json", options);
    REQUIRE(sunk.ok());
    CHECK(sunk.scene->objects.empty());
    REQUIRE(keeper.objects.size() == whole.scene->objects.size());
    CHECK(keeper.objects == whole.scene->objects);
    for (std::size_t i = 0; i < keeper.indices.size(); ++i) REQUIRE(keeper.indices[i] == i);
    // Room was asked for before the objects came, and never for fewer than had come.
    REQUIRE_FALSE(keeper.reserves.empty());
    CHECK(keeper.reserves.back() >= keeper.objects.size());
    // Everything but the objects is the description's.
    SceneDesc rest = *whole.scene;
    rest.objects.clear();
    CHECK(canonical_json(rest) == canonical_json(*sunk.scene));
    CHECK(sunk.warnings.size() == whole.warnings.size());
  }
}

TEST_CASE("a load into a sink reports the same errors, by path", "[scene][sink]") {
  SceneParts p;
  p.objects =
      R"([{"type": "sphere", "loc": [0, 0, 0], "radius": -1}, {"type": "box", "min": [1, 1, 1], "max": [0, 2, 2]}])";
  const LoadResult whole = load_scene_string(p.json(), kFile);
  Keeper keeper;
  LoadOptions options;
  options.object_sink = &keeper;
  const LoadResult sunk = load_scene_string(p.json(), kFile, options);
  REQUIRE_FALSE(whole.ok());
  REQUIRE_FALSE(sunk.ok());
  CHECK(format_errors(sunk.errors) == format_errors(whole.errors));
  CHECK(has_error(sunk, "/scene_objects/0/radius", "must be"));
  CHECK(keeper.objects.empty());  // neither object was valid
}

TEST_CASE("RenderSceneBuilder builds RenderScene::build's scene, bit for bit", "[scene][sink][render]") {
  const std::string json = mixed_scene();
  const SceneDesc desc = load_ok(json);
  const render::RenderScene reference = render::RenderScene::build(desc, accel::Isa::kScalar, 1);
  // The camera is inside the glass sphere and inside the glass mesh: both are media.
  REQUIRE(reference.camera_media().size() == 2);

  render::RenderSceneBuilder builder;
  LoadOptions options;
  options.object_sink = &builder;
  const LoadResult sunk = load_scene_string(json, "ok.json", options);
  INFO(format_errors(sunk.errors));
  REQUIRE(sunk.ok());
  CHECK(builder.object_count() == desc.objects.size());
  const render::RenderScene built = std::move(builder).build(*sunk.scene, accel::Isa::kScalar, 1);
  CHECK(builder.object_count() == 0);  // emptied
  require_same_scene(reference, built);

  const scene::TileRect whole{0, 0, desc.render.width, desc.render.height};
  const render::Tile a = render::render_tile(reference, desc.render, whole);
  const render::Tile b = render::render_tile(built, sunk.scene->render, whole);
  REQUIRE(a.rgb.size() == b.rgb.size());
  CHECK(std::memcmp(a.rgb.data(), b.rgb.data(), a.rgb.size() * sizeof(float)) == 0);
}

TEST_CASE("RenderSceneBuilder adds the description's own objects after those given to it", "[scene][sink][render]") {
  const SceneDesc desc = load_ok(mixed_scene());
  render::RenderSceneBuilder builder;
  for (std::size_t i = 0; i < 3; ++i) builder.add(i, desc.objects[i]);
  SceneDesc rest = desc;
  rest.objects.erase(rest.objects.begin(), rest.objects.begin() + 3);
  const render::RenderScene built = std::move(builder).build(rest, accel::Isa::kScalar, 1);
  require_same_scene(render::RenderScene::build(desc, accel::Isa::kScalar, 1), built);
}

TEST_CASE("a sphere field loaded into RenderSceneBuilder renders RenderScene::build's pixels on every isa",
          "[scene][sink][render]") {
  const std::string json = canonical_json(scene::generate_sphere_field(2000, 3));
  const SceneDesc desc = load_ok(json);
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene reference = render::RenderScene::build(desc, isa, 2);
    render::RenderSceneBuilder builder;
    LoadOptions options;
    options.object_sink = &builder;
    options.parallel_min_bytes = 0;  // the reader thread gives the objects to the builder
    const LoadResult sunk = load_scene_string(json, "ok.json", options);
    REQUIRE(sunk.ok());
    const render::RenderScene built = std::move(builder).build(*sunk.scene, isa, 2);
    require_same_scene(reference, built);
    scene::RenderSettings settings = desc.render;
    settings.width = 48;
    settings.height = 27;
    const scene::TileRect whole{0, 0, settings.width, settings.height};
    const render::Tile a = render::render_tile(reference, settings, whole);
    const render::Tile b = render::render_tile(built, settings, whole);
    REQUIRE(a.rgb.size() == b.rgb.size());
    CHECK(std::memcmp(a.rgb.data(), b.rgb.data(), a.rgb.size() * sizeof(float)) == 0);
  }
}

TEST_CASE("a large sphere scene's shapes come back from the build bit for bit, and answer as the scalar tree's",
          "[scene][sink][accel]") {
  // Past the size where the build holds the shapes as bare spheres (bvh.cpp, HeldShapes), with a
  // plane among them; the scalar build never holds them.
  const SceneDesc desc = scene::generate_sphere_field(40000, 5);
  const render::RenderScene scalar = render::RenderScene::build(desc, accel::Isa::kScalar, 2);
  const render::RenderScene wide = render::RenderScene::build(desc, accel::best_isa(), 2);
  require_same_scene(scalar, wide, /* same_tree = */ false);
  REQUIRE(wide.geometry().transparent() == nullptr);  // one tree: its glass is spread over the field
  const accel::Geometry& a = scalar.geometry().fixed()->geometry;
  const accel::Geometry& b = wide.geometry().fixed()->geometry;
  REQUIRE(a.shapes().size() == 40001);
  REQUIRE(a.shapes()[0].type == accel::ShapeType::kPlane);
  int hits = 0;
  for (std::uint32_t i = 0; i < 400; ++i) {
    const render::CameraF& c = scalar.camera();
    const dtraced::math::Ray ray = c.generate(0.5 + (i % 20) * 3.1, 0.5 + (i / 20) * 1.7, 64, 36);
    accel::Hit ha, hb;
    const bool fa = a.intersect(ray, ha);
    REQUIRE(fa == b.intersect(ray, hb));
    if (!fa) continue;
    ++hits;
    REQUIRE(ha.shape == hb.shape);
    REQUIRE(std::bit_cast<std::uint32_t>(ha.t) == std::bit_cast<std::uint32_t>(hb.t));
  }
  CHECK(hits > 300);
}

TEST_CASE("RenderSceneBuilder's arrays hold what was added while their pages are mapped beside it",
          "[scene][sink][render]") {
  // reserve() past util::kPrefaultMinBytes of shapes maps their pages on a thread of its own while
  // add() writes them; adding past the reservation moves the arrays (the thread is joined first).
  // Either way the arrays must hold exactly what a builder that never reserved holds.
  const SceneDesc desc = scene::generate_sphere_field(300000, 11);
  REQUIRE(desc.objects.size() * sizeof(accel::Shape) > dtraced::util::kPrefaultMinBytes);
  render::RenderSceneBuilder plain;
  for (std::size_t i = 0; i < desc.objects.size(); ++i) plain.add(i, desc.objects[i]);
  for (const std::size_t reserved : {desc.objects.size(), desc.objects.size() - 60000}) {
    INFO("reserved " << reserved);
    render::RenderSceneBuilder prefaulted;
    prefaulted.reserve(reserved);
    for (std::size_t i = 0; i < desc.objects.size(); ++i) prefaulted.add(i, desc.objects[i]);
    const render::RenderSceneBuilder::Parts a = plain.parts(), b = prefaulted.parts();
    REQUIRE(a.shapes.size() == b.shapes.size());
    REQUIRE(a.materials.size() == b.materials.size());
    CHECK(std::memcmp(a.shapes.data(), b.shapes.data(), a.shapes.size_bytes()) == 0);
    CHECK(std::memcmp(a.materials.data(), b.materials.data(), a.materials.size_bytes()) == 0);
  }
}

TEST_CASE("objects map to their shapes whether or not meshes come first, or have no triangles",
          "[scene][sink][render]") {
  const std::string empty_mesh = R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\n"})";
  const std::string tri_mesh = R"({"type": "mesh", "obj": "v 0 0 -3\nv 1 0 -3\nv 0 1 -3\nf 1 2 3\nf 1 3 2\n"})";
  const std::string sphere = R"({"type": "sphere", "loc": [0, 0, -2], "radius": 0.5})";
  for (const std::string& objects : {"[" + empty_mesh + ", " + std::string(kSphere) + ", " + sphere + "]",
                                     "[" + sphere + ", " + tri_mesh + ", " + std::string(kSphere) + "]",
                                     "[" + sphere + ", " + std::string(kSphere) + "]"}) {
    INFO(objects);
    SceneParts p;
    p.objects = objects;
    const SceneDesc desc = load_ok(p.json());
    render::RenderSceneBuilder builder;
    for (std::size_t i = 0; i < desc.objects.size(); ++i) builder.add(i, desc.objects[i]);
    SceneDesc rest = desc;
    rest.objects.clear();
    const render::RenderScene rs = std::move(builder).build(rest, accel::Isa::kScalar, 1);
    // Each shape's owner, from the objects' own shape counts.
    std::vector<std::uint32_t> owner;
    for (std::uint32_t i = 0; i < desc.objects.size(); ++i) {
      const auto& o = desc.objects[i];
      owner.insert(owner.end(), o.type == ObjectType::kMesh ? o.mesh->triangle_count() : 1, i);
    }
    REQUIRE(rs.geometry().shape_count() == owner.size());
    for (std::uint32_t id = 0; id < owner.size(); ++id) CHECK(rs.object(id) == owner[id]);
  }
}
