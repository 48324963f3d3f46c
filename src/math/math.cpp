// The math layer is header-only today; this unit keeps it a real library target so the layer
// arrows in CMake hold and later non-inline code (sampling warps, SIMD wrappers) has a home.
#include "math/float_util.h"
#include "math/ray.h"
#include "math/rng.h"
#include "math/vec.h"

namespace dtraced::math {
static_assert(gamma(1) > 0.0f);
static_assert(to_unit_float(~0ULL) < 1.0f);
}  // namespace dtraced::math
