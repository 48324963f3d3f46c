#include "scene/digest.h"

#include <cmath>
#include <cstdint>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/monotonic_resource.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>

#include "util/sha256.h"

namespace dtraced::scene {
namespace {

namespace json = boost::json;

// Integral values print as integers ("640", not Boost's "6.4E2") for a readable canonical
// file. Within 2^53 an integer converts back to the identical double. The loader has already
// turned -0 into +0, so dropping the sign here loses nothing.
json::value number(double d, const json::storage_ptr& sp) {
  constexpr double kExactIntegers = 9007199254740992.0;  // 2^53
  if (d == std::floor(d) && std::abs(d) <= kExactIntegers) return json::value(static_cast<std::int64_t>(d), sp);
  // Boost serialises doubles with Ryu: the shortest digits that read back (correctly rounded,
  // as the loader reads them) to the same double.
  return json::value(d, sp);
}

json::value vec3(const math::Vec3d& v, const json::storage_ptr& sp) {
  json::array a(sp);
  a.reserve(3);
  a.push_back(number(v.x, sp));
  a.push_back(number(v.y, sp));
  a.push_back(number(v.z, sp));
  return json::value(std::move(a));
}

// Objects are built key by key: boost::json::object keeps insertion order, which is the
// canonical order. Every value shares the caller's arena (`sp`): a value moved between storages
// is copied, and a 100k-object tree built on the heap costs more than its serialisation.
json::value material(const Material& m, const json::storage_ptr& sp) {
  json::object o(7, sp);
  o["color"] = vec3(m.color, sp);
  o["diffuse"] = number(m.diffuse, sp);
  o["specular"] = number(m.specular, sp);
  o["shininess"] = number(m.shininess, sp);
  o["reflectivity"] = number(m.reflectivity, sp);
  o["transparency"] = number(m.transparency, sp);
  o["ior"] = number(m.ior, sp);
  return json::value(std::move(o));
}

json::value scene_object(const Object& object, const json::storage_ptr& sp) {
  json::object o(6, sp);
  switch (object.type) {
    case ObjectType::kSphere:
      o["type"] = "sphere";
      o["loc"] = vec3(object.sphere.center, sp);
      o["radius"] = number(object.sphere.radius, sp);
      break;
    case ObjectType::kBox:
      // Corners, not centre and size: min -> centre/size -> min does not round-trip in double.
      o["type"] = "box";
      o["min"] = vec3(object.box.min, sp);
      o["max"] = vec3(object.box.max, sp);
      break;
    case ObjectType::kPlane:
      o["type"] = "plane";
      o["loc"] = vec3(object.plane.point, sp);
      o["normal"] = vec3(object.plane.normal, sp);
      break;
    case ObjectType::kMesh:
      // Always inline, whether the scene named a file or not: the canonical form must load on a
      // host that has no such file, and a mesh means its text, not where the text was kept. The
      // scale is written per axis (a number and [s, s, s] mean the same).
      o["type"] = "mesh";
      o["obj"] = json::string(object.mesh->obj, sp);
      o["translate"] = vec3(object.mesh->translate, sp);
      o["rotate"] = vec3(object.mesh->rotate_deg, sp);
      o["scale"] = vec3(object.mesh->scale, sp);
      break;
  }
  o["material"] = material(object.material, sp);
  return json::value(std::move(o));
}

}  // namespace

std::string canonical_json(const SceneDesc& desc) {
  json::monotonic_resource arena;
  const json::storage_ptr sp(&arena);
  json::object root(4, sp);

  json::object camera(4, sp);
  camera["position"] = vec3(desc.camera.position, sp);
  camera["look_at"] = vec3(desc.camera.look_at, sp);
  camera["up"] = vec3(desc.camera.up, sp);
  camera["fov"] = number(desc.camera.fov_deg, sp);
  root["camera"] = std::move(camera);

  json::object render(9, sp);
  render["width"] = desc.render.width;
  render["height"] = desc.render.height;
  render["samples"] = desc.render.samples;
  render["max_depth"] = desc.render.max_depth;
  render["background"] = vec3(desc.render.background, sp);
  render["seed"] = desc.render.seed;
  render["frame"] = desc.render.frame;
  // Only when adaptive sampling is on, so scenes without it keep the digests they always had.
  if (desc.render.error_target > 0 || desc.render.min_samples != RenderSettings{}.min_samples) {
    render["error_target"] = number(desc.render.error_target, sp);
    render["min_samples"] = desc.render.min_samples;
  }
  root["render"] = std::move(render);

  json::array objects(sp);
  objects.reserve(desc.objects.size());
  for (const Object& object : desc.objects) objects.push_back(scene_object(object, sp));
  root["scene_objects"] = std::move(objects);

  json::array lights(sp);
  lights.reserve(desc.lights.size());
  for (const Light& light : desc.lights) {
    json::object o(9, sp);
    switch (light.type) {
      case LightType::kPoint:
        o["type"] = "point";
        break;
      case LightType::kSphere:
        o["type"] = "sphere";
        break;
      case LightType::kDisk:
        o["type"] = "disk";
        break;
      case LightType::kRect:
        o["type"] = "rect";
        break;
    }
    o["loc"] = vec3(light.position, sp);
    if (light.type == LightType::kSphere || light.type == LightType::kDisk) o["radius"] = number(light.radius, sp);
    if (light.type == LightType::kDisk || light.type == LightType::kRect) o["normal"] = vec3(light.normal, sp);
    if (light.type == LightType::kRect) {
      o["u"] = vec3(light.edge_u, sp);
      o["v"] = vec3(light.edge_v, sp);
    }
    o["color"] = vec3(light.color, sp);
    o["intensity"] = number(light.intensity, sp);
    if (light.is_area()) {
      o["samples"] = light.samples;
      o["cast_shadows"] = light.cast_shadows;
    }
    lights.push_back(json::value(std::move(o)));
  }
  root["scene_lights"] = std::move(lights);

  return json::serialize(root);
}

std::string scene_digest(const SceneDesc& desc) { return util::sha256_hex(canonical_json(desc)); }

}  // namespace dtraced::scene
