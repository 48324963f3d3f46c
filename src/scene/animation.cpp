#include "scene/animation.h"

namespace dtraced::scene {

bool SceneDesc::operator==(const SceneDesc& o) const {
  const bool same_animation =
      animation == o.animation || (animation != nullptr && o.animation != nullptr && *animation == *o.animation);
  return objects == o.objects && lights == o.lights && camera == o.camera && render == o.render && same_animation;
}

bool is_animated(const SceneDesc& desc) { return desc.animation != nullptr; }

SceneDesc scene_at(const SceneDesc& desc, double /*t*/) {
  SceneDesc out = desc;
  out.animation = nullptr;
  return out;
}

SceneDesc scene_at_frame(const SceneDesc& desc, std::uint32_t frame) {
  SceneDesc out = scene_at(desc, frame / desc.render.fps);
  out.render.frame = frame;
  return out;
}

std::vector<bool> moving_objects(const SceneDesc& desc) { return std::vector<bool>(desc.objects.size(), false); }

}  // namespace dtraced::scene
