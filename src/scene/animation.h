// dtraced::scene animation: keyframed values in a scene, and the static scene at a time.
//
// Owns: the Animation a SceneDesc points at (null for a static scene), its evaluation, and which
// objects move. Every consumer (the local renderer, a worker, the collector) sees time only
// through scene_at_frame: the description of one frame is a plain static SceneDesc.
//
// A track animates one value (an object's "loc", a light's "intensity", the camera's "up", ...)
// through keys (t, value) sorted by strictly increasing t:
//   - before the first key the value holds the first key's, after the last the last key's;
//   - "linear" interpolates linearly, "smooth" by a cubic Hermite whose tangents are monotone
//     (Fritsch-Carlson, with the Brodlie weighting for uneven key spacing; zero at the end keys, so
//     the value eases in and out and joins the holds with zero slope). Neither overshoots: each
//     component stays within the range its two neighbouring keys span (clamped there against
//     rounding), so a check that holds at every key holds at every time;
//   - `offset` shifts the keys later in time: the track at time t is the keys evaluated at
//     t - offset;
//   - `repeat` makes the span [t_first, t_last] periodic (period t_last - t_first): the value at
//     t_first + k * period + x is the value at t_first + x, for every integer k. A smooth repeating
//     track whose first and last values are equal takes its end tangents from the wrapped
//     neighbours, so the loop has no kink.
// The SceneDesc's own field holds the track's value at time 0 (so a consumer that ignores the
// animation sees a valid scene: the scene at t = 0).
//
// Pure functions over immutable values: thread-safe.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string_view>
#include <vector>

#include "scene/description.h"

namespace dtraced::scene {

// What a track animates. The owner (camera, an object, a light) follows from the target.
enum class Target : std::uint8_t {
  kCameraPosition,
  kCameraLookAt,
  kCameraUp,
  kCameraFov,
  kObjectLoc,  // a sphere's centre, a box's centre (its size stays), a plane's point
  kSphereRadius,
  kMeshTranslate,
  kMeshRotate,
  kMeshScale,
  kMaterialColor,
  kLightPosition,
  kLightColor,
  kLightIntensity,
};

enum class Interpolation : std::uint8_t { kLinear, kSmooth };
inline constexpr std::array<std::string_view, 2> kInterpolationNames = {"linear", "smooth"};

// Limits: every track has at most kMaxKeys keys; a scene at most kMaxTracks tracks. Key times and
// offsets are within [-kMaxTrackTime, kMaxTrackTime] seconds (about 11.6 days).
inline constexpr std::size_t kMaxKeys = 10'000;
inline constexpr std::size_t kMaxTracks = 1'000'000;
inline constexpr double kMaxTrackTime = 1e6;

struct Key {
  double t = 0;  // seconds
  Vec3d value;   // a scalar track (radius, intensity, fov) uses value.x; y and z are 0
  bool operator==(const Key&) const = default;
};

struct Track {
  Target target = Target::kObjectLoc;
  std::uint32_t index = 0;  // the object's or light's index in its list; 0 for the camera
  std::vector<Key> keys;    // at least one, t strictly increasing
  Interpolation interpolation = Interpolation::kLinear;
  bool repeat = false;  // needs two keys or more
  double offset = 0;    // seconds
  // A box's full edge lengths (kObjectLoc of a box): the box at time t is loc(t) -+ size / 2.
  Vec3d box_size{0, 0, 0};
  bool operator==(const Track&) const = default;
};

struct Animation {
  // Sorted by (owner: camera, objects, lights; index; target): at most one track per value.
  std::vector<Track> tracks;
  bool operator==(const Animation&) const = default;
};

// Whether anything in the scene changes with time.
bool is_animated(const SceneDesc& desc);

// The scene at time `t` seconds: every animated value evaluated, animation null.
//
// The camera cannot be kept valid by the keys alone (position and look_at may cross, up may line
// up with the view). The loader checks it at every key time of the camera's tracks and at every
// frame of the scene's own range (render.frames, or render.frame); at any other time where the
// evaluated camera is degenerate, scene_at falls back deterministically: look_at to position +
// the t = 0 view direction, and then up to the t = 0 up (and if that too is parallel, the world
// axis least aligned with the view). So scene_at never returns a degenerate camera.
SceneDesc scene_at(const SceneDesc& desc, double t);

// The scene of frame `frame`: scene_at(desc, frame / desc.render.fps) with render.frame = frame
// (so the frame also seeds the noise). For a static scene only render.frame changes.
SceneDesc scene_at_frame(const SceneDesc& desc, std::uint32_t frame);

// One flag per object (desc.objects order): whether its geometry (a position, a radius, a mesh's
// transform) changes with time. A material change alone does not move an object. Shapes of
// objects that do not move can be built once and shared by every frame.
std::vector<bool> moving_objects(const SceneDesc& desc);

// ---- parts, for the loader and the canonical form ------------------------------------------

// The track's value at time `t` (offset and repeat applied).
Vec3d evaluate(const Track& track, double t);

// Whether the target's value is a number (value.x) rather than a vector.
bool is_scalar(Target target);

// The track of `target` of owner `index`, or nullptr (`animation` may be null).
const Track* find_track(const Animation* animation, Target target, std::uint32_t index);

// Sorts tracks into Animation's order.
void sort_tracks(Animation& animation);

// The camera with its tracks evaluated at `t`, before scene_at's fallback.
Camera animated_camera(const SceneDesc& desc, double t);

// Whether `camera` can be rendered: position != look_at as floats, up not zero and not parallel to
// the view direction (|up x dir| >= 1e-6 |up| |dir|). Empty when valid, else which key is wrong
// ("look_at" or "up") and why.
struct CameraProblem {
  std::string_view key;
  std::string_view message;
};
std::optional<CameraProblem> camera_problem(const Camera& camera);

}  // namespace dtraced::scene
