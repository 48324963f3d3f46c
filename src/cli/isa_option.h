// dtraced::cli instruction-set choice: which traversal kernels `render` and `--role worker` run.
//
// The choice is --isa when given, else $DTRACED_ISA when set, else the best this CPU supports. It
// is resolved once in main and passed down as a value (no global): every kernel renders the same
// bits, so the choice is about speed and about comparing kernels.
//
// Pure functions (the environment is read by the caller): thread-safe.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "accel/isa.h"
#include "util/result.h"

namespace dtraced::cli {

// `flag`: the --isa value when given; `env`: $DTRACED_ISA when set. On a name that is not an
// instruction set, or one this CPU lacks, an error whose message names where the value came from
// ("--isa avx512: this CPU supports scalar, sse4, avx2").
util::Result<accel::Isa> choose_isa(const std::optional<std::string>& flag, const char* env);

// "scalar sse4 avx2": accel::supported_isas(), by name.
std::string supported_isa_names(std::string_view separator);

// "dtraced 0.1.0 (kernels: avx2; supported: scalar sse4 avx2)": the kernels that run by default
// (from `env`, $DTRACED_ISA, when it names a supported set).
std::string version_line(std::string_view version, const char* env);

}  // namespace dtraced::cli
