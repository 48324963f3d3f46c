// dtraced::accel: which instruction sets this build and this CPU can run.
#include "accel/isa.h"

#include <hwy/targets.h>

namespace dtraced::accel {

std::string_view isa_name(Isa isa) {
  switch (isa) {
    case Isa::kScalar:
      return "scalar";
    case Isa::kSse4:
      return "sse4";
    case Isa::kAvx2:
      return "avx2";
    case Isa::kAvx512:
      return "avx512";
  }
  return "unknown";
}

std::optional<Isa> parse_isa(std::string_view name) {
  if (name == "best") return best_isa();
  for (Isa isa : {Isa::kScalar, Isa::kSse4, Isa::kAvx2, Isa::kAvx512}) {
    if (name == isa_name(isa)) return isa;
  }
  return std::nullopt;
}

std::vector<Isa> supported_isas() {
  std::vector<Isa> out{Isa::kScalar};
  // hwy::SupportedTargets() checks CPUID and the OS's saved register state (XCR0), and is
  // limited to the targets this binary was compiled for.
  const std::int64_t targets = hwy::SupportedTargets();
  if (targets & HWY_SSE4) out.push_back(Isa::kSse4);
  if (targets & HWY_AVX2) out.push_back(Isa::kAvx2);
  if (targets & HWY_AVX3) out.push_back(Isa::kAvx512);
  return out;
}

Isa best_isa() { return supported_isas().back(); }

}  // namespace dtraced::accel
