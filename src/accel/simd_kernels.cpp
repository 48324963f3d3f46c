// placeholder, replaced by the Highway kernels
#include "accel/geometry.h"
#include <cstdlib>
namespace dtraced::accel::detail {
const Kernels& kernels_for(Isa) { std::abort(); }
}
