#include "scene/overrides.h"

#include "scene/tiling.h"

namespace dtraced::scene {

RenderSettings apply(const Overrides& o, RenderSettings s) {
  if (o.width) s.width = *o.width;
  if (o.height) s.height = *o.height;
  if (o.samples) s.samples = *o.samples;
  if (o.max_depth) s.max_depth = *o.max_depth;
  if (o.seed) s.seed = *o.seed;
  if (o.frame) s.frame = *o.frame;
  if (o.background) s.background = *o.background;
  if (o.error_target) s.error_target = *o.error_target;
  if (o.min_samples) s.min_samples = *o.min_samples;
  if (o.branch_cutoff) s.branch_cutoff = *o.branch_cutoff;
  if (o.frames) s.frames = *o.frames;
  if (o.fps) s.fps = *o.fps;
  if (o.exposure) s.display.exposure = *o.exposure;
  if (o.tone) s.display.tone = *o.tone;
  if (o.frame && !o.frames) s.frames.reset();
  if (s.frames && s.frames->count() == 1) {
    s.frame = s.frames->first;
    s.frames.reset();
  }
  return s;
}

std::uint32_t tile_size_or_default(const Overrides& o) { return o.tile_size.value_or(kDefaultTileSize); }

std::uint32_t png_bit_depth_or_default(const Overrides& o) { return o.png_bit_depth.value_or(kDefaultPngBitDepth); }

}  // namespace dtraced::scene
