// The integrator's paths for scenes with point lights (see render/integrator_paths.h).
#include <cassert>
#include <utility>

#include "render/integrator_paths.h"

namespace dtraced::render::paths {

PathFns lit_paths(unsigned features) {
  static constexpr auto kTable = path_table<kPointLights>(std::make_index_sequence<kPointLights>{});
  assert(features >= kPointLights && features <= kAllFeatures);
  return kTable[features - kPointLights];
}

}  // namespace dtraced::render::paths
