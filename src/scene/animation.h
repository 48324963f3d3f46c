// dtraced::scene animation: keyframed values in a scene, and the static scene at a time.
//
// Owns: the Animation a SceneDesc points at (null for a static scene), its evaluation, and which
// objects move. Every consumer (the local renderer, a worker, the collector) sees time only
// through scene_at_frame: the description of one frame is a plain static SceneDesc.
//
// Pure functions over immutable values: thread-safe.
#pragma once

#include <cstdint>
#include <vector>

#include "scene/description.h"

namespace dtraced::scene {

struct Animation {
  // Filled in by the animation loader; an empty Animation animates nothing.
  bool operator==(const Animation&) const = default;
};

// Whether anything in the scene changes with time.
bool is_animated(const SceneDesc& desc);

// The scene at time `t` seconds: every animated value evaluated, animation null.
SceneDesc scene_at(const SceneDesc& desc, double t);

// The scene of frame `frame`: scene_at(desc, frame / desc.render.fps) with render.frame = frame
// (so the frame also seeds the noise). For a static scene only render.frame changes.
SceneDesc scene_at_frame(const SceneDesc& desc, std::uint32_t frame);

// One flag per object (desc.objects order): whether its geometry (a position, a radius, a mesh's
// transform) changes with time. A material change alone does not move an object. Shapes of
// objects that do not move can be built once and shared by every frame.
std::vector<bool> moving_objects(const SceneDesc& desc);

}  // namespace dtraced::scene
