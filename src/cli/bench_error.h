// dtraced::cli `dtraced bench error`: speed against error for one scene (README, "Speed against
// error"). Renders at 1, 2, 4, ... samples per pixel and adaptively at several error targets,
// measures each image against a reference and prints a table and a CSV.
#pragma once

#include <optional>
#include <string>

#include <CLI/CLI.hpp>

#include "accel/isa.h"

namespace dtraced::cli {

struct BenchErrorArgs;

// Adds `bench` with its `error` subcommand to `app`; the returned App is `bench error`, whose
// parsed() says the verb was chosen. `args` must outlive app.parse().
// Its --isa flag writes `isa_flag`, which main resolves with the render verb's rules.
CLI::App* add_bench_error_verb(CLI::App& app, BenchErrorArgs& args, std::optional<std::string>& isa_flag);

// Runs the verb with the kernels `isa` (resolved by main); returns the exit code.
int run_bench_error(const BenchErrorArgs& args, accel::Isa isa);

}  // namespace dtraced::cli
