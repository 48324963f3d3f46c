#include "scene/digest.h"

#include <cstring>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/monotonic_resource.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>

#include "jsonio/parse.h"
#include "scene/animation.h"
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
// A track in full: every key, then interpolation, repeat and offset, defaults included.
json::value track_value(const Track& track, const json::storage_ptr& sp) {
  json::array keys(sp);
  keys.reserve(track.keys.size());
  for (const Key& key : track.keys) {
    json::object k(2, sp);
    k["t"] = exact_number(key.t, sp);
    k["value"] = is_scalar(track.target) ? exact_number(key.value.x, sp) : vec3_value(key.value, sp);
    keys.push_back(json::value(std::move(k)));
  }
  json::object o(4, sp);
  o["keys"] = std::move(keys);
  o["interpolation"] = kInterpolationNames[static_cast<std::size_t>(track.interpolation)];
  o["repeat"] = track.repeat;
  o["offset"] = exact_number(track.offset, sp);
  return json::value(std::move(o));
}

// Writes the values that may be animated: a value's track when it has one, else the value.
class Writer {
 public:
  Writer(const Animation* animation, std::uint32_t index, const json::storage_ptr& sp)
      : animation_(animation), index_(index), sp_(sp) {}
  json::value vec3(Target target, const Vec3d& v) const {
    const Track* t = find_track(animation_, target, index_);
    return t != nullptr ? track_value(*t, sp_) : vec3_value(v, sp_);
  }
  json::value number(Target target, double d) const {
    const Track* t = find_track(animation_, target, index_);
    return t != nullptr ? track_value(*t, sp_) : exact_number(d, sp_);
  }

 private:
  const Animation* animation_;
  std::uint32_t index_;
  const json::storage_ptr& sp_;
};

json::value material(const Material& m, const Writer& w, const json::storage_ptr& sp) {
  json::object o(7, sp);
  o["color"] = w.vec3(Target::kMaterialColor, m.color);
  o["diffuse"] = exact_number(m.diffuse, sp);
  o["specular"] = exact_number(m.specular, sp);
  o["shininess"] = exact_number(m.shininess, sp);
  o["reflectivity"] = exact_number(m.reflectivity, sp);
  o["transparency"] = exact_number(m.transparency, sp);
  o["ior"] = exact_number(m.ior, sp);
  return json::value(std::move(o));
}

json::value scene_object(const Object& object, const Writer& w, const Track* box_track, const json::storage_ptr& sp) {
  json::object o(6, sp);
  o["type"] = type_name(object.type);
  switch (object.type) {
    case ObjectType::kSphere:
      o["loc"] = w.vec3(Target::kObjectLoc, object.sphere.center);
      o["radius"] = w.number(Target::kSphereRadius, object.sphere.radius);
      break;
    case ObjectType::kBox:
      if (box_track != nullptr) {  // a moving box: its centre's track and its size, as read
        o["loc"] = track_value(*box_track, sp);
        o["size"] = vec3_value(box_track->box_size, sp);
        break;
      }
      // Corners, not centre and size: min -> centre/size -> min does not round-trip in double.
      o["min"] = vec3_value(object.box.min, sp);
      o["max"] = vec3_value(object.box.max, sp);
      break;
    case ObjectType::kPlane:
      o["loc"] = w.vec3(Target::kObjectLoc, object.plane.point);
      o["normal"] = vec3_value(object.plane.normal, sp);
      break;
    case ObjectType::kMesh:
      // Always inline, whether the scene named a file or not: the canonical form must load on a
      // host that has no such file, and a mesh means its text, not where the text was kept. The
      // scale is written per axis (a number and [s, s, s] mean the same).
      o["obj"] = json::string(object.mesh->obj, sp);
      o["translate"] = w.vec3(Target::kMeshTranslate, object.mesh->translate);
      o["rotate"] = w.vec3(Target::kMeshRotate, object.mesh->rotate_deg);
      o["scale"] = w.vec3(Target::kMeshScale, object.mesh->scale);
      break;
  }
  o["material"] = material(object.material, w, sp);
  return json::value(std::move(o));
}

json::value scene_light(const Light& light, const Writer& w, const json::storage_ptr& sp) {
  json::object o(9, sp);
  o["type"] = type_name(light.type);
  o["loc"] = w.vec3(Target::kLightPosition, light.position);
  if (light.type == LightType::kSphere || light.type == LightType::kDisk) {
    o["radius"] = exact_number(light.radius, sp);
  }
  if (light.type == LightType::kDisk || light.type == LightType::kRect) o["normal"] = vec3_value(light.normal, sp);
  if (light.type == LightType::kRect) {
    o["u"] = vec3_value(light.edge_u, sp);
    o["v"] = vec3_value(light.edge_v, sp);
  }
  o["color"] = w.vec3(Target::kLightColor, light.color);
  o["intensity"] = w.number(Target::kLightIntensity, light.intensity);
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

  const Animation* animation = desc.animation.get();
  const Writer w(animation, 0, sp);
  json::object camera(4, sp);
  camera["position"] = w.vec3(Target::kCameraPosition, desc.camera.position);
  camera["look_at"] = w.vec3(Target::kCameraLookAt, desc.camera.look_at);
  camera["up"] = w.vec3(Target::kCameraUp, desc.camera.up);
  camera["fov"] = w.number(Target::kCameraFov, desc.camera.fov_deg);
  root["camera"] = std::move(camera);
  root["render"] = render_settings_object(desc.render, sp);

  json::array objects(sp);
  objects.reserve(desc.objects.size());
  for (std::uint32_t i = 0; i < desc.objects.size(); ++i) {
    const Object& object = desc.objects[i];
    const Track* box_track = object.type == ObjectType::kBox ? find_track(animation, Target::kObjectLoc, i) : nullptr;
    objects.push_back(scene_object(object, Writer(animation, i, sp), box_track, sp));
  }
  root["scene_objects"] = std::move(objects);

  json::array lights(sp);
  lights.reserve(desc.lights.size());
  for (std::uint32_t i = 0; i < desc.lights.size(); ++i) {
    lights.push_back(scene_light(desc.lights[i], Writer(animation, i, sp), sp));
  }
  root["scene_lights"] = std::move(lights);

  return json::serialize(root);
}

std::string scene_digest(const SceneDesc& desc) { return util::sha256_hex(canonical_json(desc)); }

namespace {

void put_bytes(std::string& out, const void* p, std::size_t n) { out.append(static_cast<const char*>(p), n); }
void put(std::string& out, double d) { put_bytes(out, &d, sizeof d); }
void put(std::string& out, const Vec3d& v) {
  put(out, v.x);
  put(out, v.y);
  put(out, v.z);
}
void put(std::string& out, std::uint64_t n) { put_bytes(out, &n, sizeof n); }

}  // namespace

void ObjectsDigest::reserve(std::size_t objects) {
  if (next_ != nullptr) next_->reserve(objects);
}

void ObjectsDigest::add(std::size_t index, const Object& object) {
  // Every field the canonical form writes for a static object, in a fixed order.
  chunk_.push_back(static_cast<char>(object.type));
  switch (object.type) {
    case ObjectType::kSphere:
      put(chunk_, object.sphere.center);
      put(chunk_, object.sphere.radius);
      break;
    case ObjectType::kBox:
      put(chunk_, object.box.min);
      put(chunk_, object.box.max);
      break;
    case ObjectType::kPlane:
      put(chunk_, object.plane.point);
      put(chunk_, object.plane.normal);
      break;
    case ObjectType::kMesh:
      put(chunk_, std::uint64_t{object.mesh->obj.size()});
      chunk_ += object.mesh->obj;
      put(chunk_, object.mesh->translate);
      put(chunk_, object.mesh->rotate_deg);
      put(chunk_, object.mesh->scale);
      break;
  }
  const Material& m = object.material;
  put(chunk_, m.color);
  for (const double d : {m.diffuse, m.specular, m.shininess, m.reflectivity, m.transparency, m.ior}) put(chunk_, d);
  ++count_;
  if (chunk_.size() >= kChunkBytes) flush();
  if (next_ != nullptr) next_->add(index, object);
}

void ObjectsDigest::flush() {
  const util::Sha256Digest d = util::sha256_bytes(chunk_);
  put_bytes(digests_, d.data(), d.size());
  chunk_.clear();
}

std::string ObjectsDigest::hex() const {
  std::string all = digests_;
  const util::Sha256Digest last = util::sha256_bytes(chunk_);
  put_bytes(all, last.data(), last.size());
  put(all, std::uint64_t{count_});
  return util::sha256_hex(all);
}

}  // namespace dtraced::scene
