#include "cli/isa_option.h"

#include <algorithm>
#include <vector>

#include <fmt/format.h>

#include "protocol/worker_messages.h"

namespace dtraced::cli {

std::string supported_isa_names(std::string_view separator) {
  std::string out;
  for (const accel::Isa isa : accel::supported_isas()) {
    if (!out.empty()) out += separator;
    out += accel::isa_name(isa);
  }
  return out;
}

util::Result<accel::Isa> choose_isa(const std::optional<std::string>& flag, const char* env) {
  if (!flag && env == nullptr) return accel::best_isa();
  const std::string value = flag ? *flag : std::string(env);
  const std::string source = flag ? fmt::format("--isa {}", value) : fmt::format("DTRACED_ISA={}", value);
  const std::optional<accel::Isa> isa = accel::parse_isa(value);
  if (!isa) return util::Error{fmt::format("{}: not an instruction set (scalar, sse4, avx2, avx512 or best)", source)};
  const std::vector<accel::Isa> supported = accel::supported_isas();
  if (std::find(supported.begin(), supported.end(), *isa) == supported.end()) {
    return util::Error{fmt::format("{}: this CPU supports {}", source, supported_isa_names(", "))};
  }
  return *isa;
}

std::string version_line(std::string_view version, const char* env) {
  const util::Result<accel::Isa> isa = choose_isa(std::nullopt, env);
  const std::string kernels = isa ? std::string(accel::isa_name(*isa)) : fmt::format("none ({})", isa.error().message);
  return fmt::format("dtraced {} (pixel version {}; kernels: {}; supported: {})", version, protocol::kPixelVersion,
                     kernels, supported_isa_names(" "));
}

}  // namespace dtraced::cli
