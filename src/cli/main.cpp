// dtraced command line: parses flags, picks the role or the verb, turns results into exit codes.
//
// Exit codes: 0 success; 1 the work failed (invalid scene, unreadable or mismatching image,
// render or write error); 2 usage error (unknown flag, missing argument, bad value).
#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <string>
#include <string_view>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "cli/commands.h"
#include "cli/isa_option.h"
#include "cli/json_config.h"
#include "cli/roles.h"
#include "cli/suggest.h"
#include "cli/verbs.h"

namespace {

constexpr int kExitUsage = 2;

// The file named by --config, for error messages ("config" when none): CLI11 hands the
// formatter only a stream.
std::string config_file_argument(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string_view a = argv[i];
    if (a == "--config" && i + 1 < argc) return argv[i + 1];
    if (a.starts_with("--config=")) return std::string(a.substr(9));
  }
  return "config";
}

// CLI11's message for a failed parse, told in the user's terms: a refused value the --config
// file set is named by its file and key, and an unknown verb or flag gets the nearest known one.
std::string failure_message(const CLI::App* app, const CLI::Error& e) {
  const std::string text = dtraced::cli::failure_message_with_suggestions(app, e);
  const std::size_t eol = std::min(text.find('\n'), text.size());
  return dtraced::cli::locate_refused_value(*app, text.substr(0, eol)) + text.substr(eol);
}

}  // namespace

int main(int argc, char** argv) {
  using namespace dtraced::cli;
  CLI::App app{"dtraced: a distributed ray tracer. Renders JSON scenes locally or across a farm.", "dtraced"};
  // The environment is read here, at the edge, and handed down as values.
  const char* isa_env = std::getenv("DTRACED_ISA");
  app.set_version_flag("--version", version_line(version_string(), isa_env));
  app.require_subcommand(0, 1);
  app.failure_message(failure_message);

  RoleArgs role;
  add_role_options(app, role);
  // --config FILE: a JSON object of long flag names in snake_case; flags on the command line win.
  add_config_option(app, config_file_argument(argc, argv));
  app.fallthrough(false);
  LocalCommands local;
  add_local_commands(app, local, role.isa);
  ClientCommands client;
  add_client_commands(app, client);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitUsage;
  }
  // The kernels, for the commands that render: --isa, else $DTRACED_ISA, else the best.
  if (local.renders() || role.role == "worker") {
    const dtraced::util::Result<dtraced::accel::Isa> isa = choose_isa(role.isa, isa_env);
    if (!isa) {
      fmt::print(stderr, "{}\n", isa.error().to_string());
      return kExitUsage;
    }
    role.kernels = *isa;
  }
  if (!role.role.empty()) {
    if (!app.get_subcommands().empty()) {
      fmt::print(stderr, "--role runs a daemon; it does not combine with the verb {}\n",
                 app.get_subcommands()[0]->get_name());
      return kExitUsage;
    }
    return run_role(app, role);
  }
  if (app.get_subcommands().empty()) {
    fmt::print(stderr, "dtraced: give a verb (render, validate, submit, ...) or --role collector|worker; see --help\n");
    return kExitUsage;
  }
  if (const std::optional<int> code = run_local_command(local, role.kernels)) return *code;
  if (const std::optional<int> code = run_client_command(client)) return *code;
  return kExitUsage;
}
