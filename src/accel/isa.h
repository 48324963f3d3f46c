// dtraced::accel instruction-set choice for the traversal kernels.
//
// The binary is built for baseline x86-64 and carries the SIMD kernels once per instruction set
// (Google Highway's foreach_target); which one runs is chosen at run time from what the CPU and
// the operating system support, and can be forced lower for tests and comparisons (the CLI's
// --isa flag and DTRACED_ISA). The choice is a value handed to Geometry::build, never a global.
#pragma once

#include <cstdint>
#include <optional>
#include <string_view>
#include <vector>

namespace dtraced::accel {

enum class Isa : std::uint8_t {
  kScalar,  // the reference: scalar kernels, one ray at a time through the binary BVH
  kSse4,    // SSE4.2 (Highway target SSE4)
  kAvx2,    // AVX2 + FMA (Highway target AVX2; the kernels use no FMA, see geometry.h)
  kAvx512,  // AVX-512 F/VL/DQ/BW (Highway target AVX3)
};

// "scalar", "sse4", "avx2", "avx512".
std::string_view isa_name(Isa isa);

// The inverse of isa_name; also accepts "best" (= best_isa()). nullopt for anything else.
std::optional<Isa> parse_isa(std::string_view name);

// What this build and this CPU can run, kScalar first, in ascending order.
std::vector<Isa> supported_isas();

// The last entry of supported_isas().
Isa best_isa();

}  // namespace dtraced::accel
