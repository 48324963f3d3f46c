#include "cli/bench_error.h"

#include <fmt/format.h>

#include "cli/bench_error_args.h"
#include "cli/roles.h"

namespace dtraced::cli {

CLI::App* add_bench_error_verb(CLI::App& app, BenchErrorArgs& args, std::optional<std::string>& isa_flag) {
  CLI::App* bench = app.add_subcommand("bench", "Benchmarks that print tables");
  bench->require_subcommand(1);
  CLI::App* error = bench->add_subcommand("error", "Speed against error for one scene");
  error->add_option("scene", args.scene, "Scene file (JSON)")->required();
  error->add_option("--isa", isa_flag, kIsaHelp);
  return error;
}

int run_bench_error(const BenchErrorArgs& args, accel::Isa /*isa*/) {
  fmt::print(stderr, "dtraced bench error {}: not built yet\n", args.scene);
  return 1;
}

}  // namespace dtraced::cli
