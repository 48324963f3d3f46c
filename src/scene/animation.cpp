#include "scene/animation.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <tuple>

#include "math/vec.h"
#include "scene/obj_mesh.h"

namespace dtraced::scene {
namespace {

using math::Vec3f;

// `up` counts as parallel to the view direction when |up x dir| < kParallelTolerance |up| |dir|.
constexpr double kParallelTolerance = 1e-6;

int owner_rank(Target target) {
  if (target <= Target::kCameraFov) return 0;
  if (target <= Target::kMaterialColor) return 1;
  return 2;
}

auto order_key(const Track& t) { return std::tuple(owner_rank(t.target), t.index, t.target); }

// The tangent at a key between segments of slopes d0 (length h0) and d1 (length h1): zero where
// the slope changes sign or is flat, else Brodlie's weighted harmonic mean, which keeps the
// Hermite segment monotone (|m| <= 3 min(|d0|, |d1|)).
double interior_tangent(double d0, double h0, double d1, double h1) {
  if (d0 == 0 || d1 == 0 || (d0 > 0) != (d1 > 0)) return 0;
  return 3 * (h0 + h1) / ((2 * h1 + h0) / d0 + (h1 + 2 * h0) / d1);
}

// The tangent of component c at key k of a smooth track.
double tangent(const Track& track, std::size_t k, std::size_t c) {
  const std::vector<Key>& keys = track.keys;
  const std::size_t n = keys.size();
  const auto slope = [&](std::size_t i) {
    return (keys[i + 1].value[c] - keys[i].value[c]) / (keys[i + 1].t - keys[i].t);
  };
  const auto span = [&](std::size_t i) { return keys[i + 1].t - keys[i].t; };
  if (k > 0 && k + 1 < n) return interior_tangent(slope(k - 1), span(k - 1), slope(k), span(k));
  // End keys: zero (ease in and out, joining the holds), unless a repeating track closes its loop.
  if (n < 3 || !track.repeat || keys.front().value[c] != keys.back().value[c]) return 0;
  return interior_tangent(slope(n - 2), span(n - 2), slope(0), span(0));
}

// Track time `u` (offset and repeat applied) inside the keys' span, or held at an end.
double local_time(const Track& track, double t) {
  double u = t - track.offset;
  const double first = track.keys.front().t, last = track.keys.back().t;
  if (track.repeat && track.keys.size() >= 2) {
    const double period = last - first;
    double x = std::fmod(u - first, period);
    if (x < 0) x += period;
    if (x >= period) x = 0;  // -tiny + period rounds up to period
    u = first + x;
  }
  return u;
}

Camera fallback_camera(Camera camera, const Camera& at_zero) {
  if (!camera_problem(camera)) return camera;
  if (Vec3f(camera.position) == Vec3f(camera.look_at)) {
    camera.look_at = camera.position + (at_zero.look_at - at_zero.position);
    if (Vec3f(camera.position) == Vec3f(camera.look_at)) return at_zero;
  }
  if (!camera_problem(camera)) return camera;
  camera.up = at_zero.up;
  if (!camera_problem(camera)) return camera;
  // The world axis least aligned with the view is never parallel to it.
  const Vec3d d = math::abs(camera.look_at - camera.position);
  camera.up = d.x <= d.y && d.x <= d.z ? Vec3d{1, 0, 0} : d.y <= d.z ? Vec3d{0, 1, 0} : Vec3d{0, 0, 1};
  return camera_problem(camera) ? at_zero : camera;
}

// A mesh track only sets the transform of the frame's own copy of the mesh (`own`, made on first
// use); scene_at builds its triangles once all the tracks are applied.
Mesh& own_mesh(Object& object, std::shared_ptr<Mesh>& own) {
  if (own == nullptr) {
    own = std::make_shared<Mesh>(*object.mesh);
    object.mesh = own;
  }
  return *own;
}

void apply_object_track(const Track& track, const Vec3d& v, Object& object, std::shared_ptr<Mesh>& own) {
  switch (track.target) {
    case Target::kObjectLoc:
      if (object.type == ObjectType::kSphere) object.sphere.center = v;
      if (object.type == ObjectType::kPlane) object.plane.point = v;
      if (object.type == ObjectType::kBox) {
        const Vec3d half = track.box_size * 0.5;
        object.box = Box{v - half, v + half};
      }
      break;
    case Target::kSphereRadius:
      object.sphere.radius = v.x;
      break;
    case Target::kMeshTranslate:
      own_mesh(object, own).translate = v;
      break;
    case Target::kMeshRotate:
      own_mesh(object, own).rotate_deg = v;
      break;
    case Target::kMeshScale:
      own_mesh(object, own).scale = v;
      break;
    case Target::kMaterialColor:
      object.material.color = v;
      break;
    default:
      break;
  }
}

void apply_track(const Track& track, double t, SceneDesc& out, std::vector<std::shared_ptr<Mesh>>& own_meshes) {
  const Vec3d v = evaluate(track, t);
  switch (track.target) {
    case Target::kCameraPosition:
      out.camera.position = v;
      break;
    case Target::kCameraLookAt:
      out.camera.look_at = v;
      break;
    case Target::kCameraUp:
      out.camera.up = v;
      break;
    case Target::kCameraFov:
      out.camera.fov_deg = v.x;
      break;
    case Target::kLightPosition:
      out.lights[track.index].position = v;
      break;
    case Target::kLightColor:
      out.lights[track.index].color = v;
      break;
    case Target::kLightIntensity:
      out.lights[track.index].intensity = v.x;
      break;
    default:
      apply_object_track(track, v, out.objects[track.index], own_meshes[track.index]);
  }
}

}  // namespace

bool SceneDesc::operator==(const SceneDesc& o) const {
  const bool same_animation =
      animation == o.animation || (animation != nullptr && o.animation != nullptr && *animation == *o.animation);
  return objects == o.objects && lights == o.lights && camera == o.camera && render == o.render && same_animation;
}

bool is_scalar(Target target) {
  return target == Target::kCameraFov || target == Target::kSphereRadius || target == Target::kLightIntensity;
}

Vec3d evaluate(const Track& track, double t) {
  const std::vector<Key>& keys = track.keys;
  const double u = local_time(track, t);
  if (u <= keys.front().t) return keys.front().value;
  if (u >= keys.back().t) return keys.back().value;
  // The segment [k, k + 1] holding u.
  const auto next = std::upper_bound(keys.begin(), keys.end(), u, [](double x, const Key& key) { return x < key.t; });
  const std::size_t k = static_cast<std::size_t>(next - keys.begin()) - 1;
  const Key& a = keys[k];
  const Key& b = keys[k + 1];
  const double h = b.t - a.t;
  const double s = (u - a.t) / h;
  Vec3d out;
  for (std::size_t c = 0; c < 3; ++c) {
    const double p0 = a.value[c], p1 = b.value[c];
    double x = 0;
    if (track.interpolation == Interpolation::kLinear) {
      x = p0 + (p1 - p0) * s;
    } else {
      const double s2 = s * s, s3 = s2 * s;
      const double h00 = 2 * s3 - 3 * s2 + 1, h10 = s3 - 2 * s2 + s, h01 = -2 * s3 + 3 * s2, h11 = s3 - s2;
      x = h00 * p0 + h10 * h * tangent(track, k, c) + h01 * p1 + h11 * h * tangent(track, k + 1, c);
    }
    // Exact in real arithmetic; rounding must not step outside the keys' range either.
    out[c] = std::clamp(x, std::min(p0, p1), std::max(p0, p1));
  }
  return out;
}

const Track* find_track(const Animation* animation, Target target, std::uint32_t index) {
  if (animation == nullptr) return nullptr;
  Track probe;
  probe.target = target;
  probe.index = index;
  const auto it = std::lower_bound(animation->tracks.begin(), animation->tracks.end(), probe,
                                   [](const Track& a, const Track& b) { return order_key(a) < order_key(b); });
  return it != animation->tracks.end() && it->target == target && it->index == index ? &*it : nullptr;
}

void sort_tracks(Animation& animation) {
  std::stable_sort(animation.tracks.begin(), animation.tracks.end(),
                   [](const Track& a, const Track& b) { return order_key(a) < order_key(b); });
}

std::optional<CameraProblem> camera_problem(const Camera& camera) {
  // Compared as floats because the renderer builds its camera from floats.
  if (Vec3f(camera.position) == Vec3f(camera.look_at))
    return CameraProblem{"look_at", "must differ from the camera position"};
  const double up_scale = math::max_component(math::abs(camera.up));
  if (up_scale == 0) return CameraProblem{"up", "must not be the zero vector"};
  const Vec3d dir = camera.look_at - camera.position;
  const Vec3d u = camera.up / up_scale;
  const Vec3d d = dir / math::max_component(math::abs(dir));
  if (math::length(math::cross(u, d)) < kParallelTolerance * math::length(u) * math::length(d)) {
    return CameraProblem{"up", "must not be parallel to the view direction (look_at - position)"};
  }
  return std::nullopt;
}

Camera animated_camera(const SceneDesc& desc, double t) {
  SceneDesc camera_only;
  camera_only.camera = desc.camera;
  if (desc.animation == nullptr) return desc.camera;
  std::vector<std::shared_ptr<Mesh>> no_meshes;
  for (const Track& track : desc.animation->tracks) {
    if (track.target > Target::kCameraFov) break;  // sorted: the camera's tracks come first
    apply_track(track, t, camera_only, no_meshes);
  }
  return camera_only.camera;
}

bool is_animated(const SceneDesc& desc) { return desc.animation != nullptr; }

SceneDesc scene_at(const SceneDesc& desc, double t) {
  SceneDesc out = desc;
  out.animation = nullptr;
  if (desc.animation == nullptr) return out;
  std::vector<std::shared_ptr<Mesh>> own_meshes(out.objects.size());
  for (const Track& track : desc.animation->tracks) apply_track(track, t, out, own_meshes);
  for (std::size_t i = 0; i < own_meshes.size(); ++i) {
    if (own_meshes[i] == nullptr) continue;
    // The loader checked that no transform within the keys' range leaves the float range, so this
    // cannot fail; were it to, the mesh would keep its t = 0 triangles rather than vanish.
    if (!build_obj_mesh(*own_meshes[i], desc.objects[i].mesh->triangle_count())) {
      out.objects[i].mesh = desc.objects[i].mesh;
    }
  }
  out.camera = fallback_camera(out.camera, desc.camera);
  return out;
}

SceneDesc scene_at_frame(const SceneDesc& desc, std::uint32_t frame) {
  SceneDesc out = scene_at(desc, frame / desc.render.fps);
  out.render.frame = frame;
  return out;
}

std::vector<bool> moving_objects(const SceneDesc& desc) {
  std::vector<bool> moving(desc.objects.size(), false);
  if (desc.animation == nullptr) return moving;
  for (const Track& track : desc.animation->tracks) {
    if (owner_rank(track.target) == 1 && track.target != Target::kMaterialColor) moving[track.index] = true;
  }
  return moving;
}

}  // namespace dtraced::scene
