#include "scene/digest.h"

#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/monotonic_resource.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>

#include "jsonio/parse.h"
#include "scene/scene_json.h"
#include "util/sha256.h"

namespace dtraced::scene {
namespace {

namespace json = boost::json;
using jsonio::exact_number;

// Objects are built key by key: boost::json::object keeps insertion order, which is the
// canonical order. Every value shares the caller's arena (`sp`): a value moved between storages
// is copied, and a 100k-object tree built on the heap costs more than its serialisation. Numbers
// are jsonio::exact_number: the loader has already turned -0 into +0, so dropping the sign there
// loses nothing.
json::value material(const Material& m, const json::storage_ptr& sp) {
  json::object o(7, sp);
  o["color"] = vec3_value(m.color, sp);
  o["diffuse"] = exact_number(m.diffuse, sp);
  o["specular"] = exact_number(m.specular, sp);
  o["shininess"] = exact_number(m.shininess, sp);
  o["reflectivity"] = exact_number(m.reflectivity, sp);
  o["transparency"] = exact_number(m.transparency, sp);
  o["ior"] = exact_number(m.ior, sp);
  return json::value(std::move(o));
}

json::value scene_object(const Object& object, const json::storage_ptr& sp) {
  json::object o(6, sp);
  o["type"] = type_name(object.type);
  switch (object.type) {
    case ObjectType::kSphere:
      o["loc"] = vec3_value(object.sphere.center, sp);
      o["radius"] = exact_number(object.sphere.radius, sp);
      break;
    case ObjectType::kBox:
      // Corners, not centre and size: min -> centre/size -> min does not round-trip in double.
      o["min"] = vec3_value(object.box.min, sp);
      o["max"] = vec3_value(object.box.max, sp);
      break;
    case ObjectType::kPlane:
      o["loc"] = vec3_value(object.plane.point, sp);
      o["normal"] = vec3_value(object.plane.normal, sp);
      break;
    case ObjectType::kMesh:
      // Always inline, whether the scene named a file or not: the canonical form must load on a
      // host that has no such file, and a mesh means its text, not where the text was kept. The
      // scale is written per axis (a number and [s, s, s] mean the same).
      o["obj"] = json::string(object.mesh->obj, sp);
      o["translate"] = vec3_value(object.mesh->translate, sp);
      o["rotate"] = vec3_value(object.mesh->rotate_deg, sp);
      o["scale"] = vec3_value(object.mesh->scale, sp);
      break;
  }
  o["material"] = material(object.material, sp);
  return json::value(std::move(o));
}

json::value scene_light(const Light& light, const json::storage_ptr& sp) {
  json::object o(9, sp);
  o["type"] = type_name(light.type);
  o["loc"] = vec3_value(light.position, sp);
  if (light.type == LightType::kSphere || light.type == LightType::kDisk) {
    o["radius"] = exact_number(light.radius, sp);
  }
  if (light.type == LightType::kDisk || light.type == LightType::kRect) o["normal"] = vec3_value(light.normal, sp);
  if (light.type == LightType::kRect) {
    o["u"] = vec3_value(light.edge_u, sp);
    o["v"] = vec3_value(light.edge_v, sp);
  }
  o["color"] = vec3_value(light.color, sp);
  o["intensity"] = exact_number(light.intensity, sp);
  if (light.is_area()) {
    o["samples"] = light.samples;
    o["cast_shadows"] = light.cast_shadows;
  }
  return json::value(std::move(o));
}

}  // namespace

std::string canonical_json(const SceneDesc& desc) {
  json::monotonic_resource arena;
  const json::storage_ptr sp(&arena);
  json::object root(4, sp);

  json::object camera(4, sp);
  camera["position"] = vec3_value(desc.camera.position, sp);
  camera["look_at"] = vec3_value(desc.camera.look_at, sp);
  camera["up"] = vec3_value(desc.camera.up, sp);
  camera["fov"] = exact_number(desc.camera.fov_deg, sp);
  root["camera"] = std::move(camera);
  root["render"] = render_settings_object(desc.render, sp);

  json::array objects(sp);
  objects.reserve(desc.objects.size());
  for (const Object& object : desc.objects) objects.push_back(scene_object(object, sp));
  root["scene_objects"] = std::move(objects);

  json::array lights(sp);
  lights.reserve(desc.lights.size());
  for (const Light& light : desc.lights) lights.push_back(scene_light(light, sp));
  root["scene_lights"] = std::move(lights);

  return json::serialize(root);
}

std::string scene_digest(const SceneDesc& desc) { return util::sha256_hex(canonical_json(desc)); }

}  // namespace dtraced::scene
