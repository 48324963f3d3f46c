// dtraced::cli commands: the verbs' flags on the command line and the choice of the one to run.
//
// Owns the CLI11 set-up of every verb (render, validate, compare, generate, bench error; and the
// client verbs submit, list, status, fetch, cancel) and the dispatch from a parsed command line
// to the verb's run_* function (verbs.h, client_verbs.h, bench_error.h), so that main only picks
// between a role and a verb. The flags, help texts and exit codes are the verbs' own.
//
// Not thread-safe: CLI11 parsing happens once, on main's thread. Each struct binds its members
// to the flags, so it must stay where it is (no copy, no move) until parsing is over.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "cli/bench_error_args.h"
#include "cli/client_verbs.h"
#include "cli/enroll_verbs.h"
#include "cli/roles.h"
#include "cli/verbs.h"

namespace dtraced::cli {

// The verbs that work on this machine.
struct LocalCommands {
  LocalCommands() = default;
  LocalCommands(const LocalCommands&) = delete;
  LocalCommands& operator=(const LocalCommands&) = delete;

  RenderArgs render;
  std::vector<std::string> validate_files;
  CompareArgs compare;
  GenerateArgs generate;
  BenchErrorArgs bench_error;
  CLI::App* render_cmd = nullptr;
  CLI::App* validate_cmd = nullptr;
  CLI::App* compare_cmd = nullptr;
  CLI::App* generate_cmd = nullptr;
  CLI::App* bench_error_cmd = nullptr;

  // Whether the chosen verb renders, and so needs its kernels resolved (cli/isa_option.h).
  bool renders() const { return render_cmd->parsed() || bench_error_cmd->parsed(); }
};

// Adds render, validate, compare, generate and bench error to `app`. Their --isa flags write
// `isa_flag` (the role's, so that `dtraced --isa X render` works too).
void add_local_commands(CLI::App& app, LocalCommands& c, std::optional<std::string>& isa_flag);
// Runs the local verb that was parsed with the kernels `isa`; nullopt when none was.
std::optional<int> run_local_command(const LocalCommands& c, accel::Isa isa);

// The verbs that talk to a collector.
struct ClientCommands {
  ClientCommands() = default;
  ClientCommands(const ClientCommands&) = delete;
  ClientCommands& operator=(const ClientCommands&) = delete;

  ClientArgs client;
  SubmitArgs submit;
  ListArgs list;
  StatusArgs status;
  std::uint64_t fetch_id = 0;
  std::string fetch_output;
  std::optional<std::uint32_t> fetch_frame;
  std::uint64_t cancel_id = 0;
  CLI::App* submit_cmd = nullptr;
  CLI::App* list_cmd = nullptr;
  CLI::App* status_cmd = nullptr;
  CLI::App* fetch_cmd = nullptr;
  CLI::App* cancel_cmd = nullptr;
  std::uint64_t priority_id = 0;
  std::int32_t priority_value = 0;
  std::uint64_t requeue_id = 0;
  CLI::App* priority_cmd = nullptr;
  CLI::App* requeue_cmd = nullptr;
  bool workers_json = false;
  CLI::App* workers_cmd = nullptr;
  std::uint64_t pause_id = 0;
  std::uint64_t resume_id = 0;
  std::uint64_t delete_id = 0;
  bool delete_image = false;
  CLI::App* pause_cmd = nullptr;
  CLI::App* resume_cmd = nullptr;
  CLI::App* delete_cmd = nullptr;
  // Credentials and enrollment (enroll_verbs.h).
  EnrollCodeArgs enroll_code;
  EnrollArgs enroll;
  std::string revoke_name;
  CredentialAddArgs credential_add;
  bool credentials_json = false;
  CLI::App* enroll_code_cmd = nullptr;
  CLI::App* enroll_cmd = nullptr;
  CLI::App* revoke_cmd = nullptr;
  CLI::App* credentials_add_cmd = nullptr;
  CLI::App* credentials_list_cmd = nullptr;
};

// Adds submit, list, status, fetch, cancel, priority, requeue, workers (and workers revoke),
// pause, resume, delete, enroll-code, enroll and credentials (add, list) to `app`.
void add_client_commands(CLI::App& app, ClientCommands& c);
// Runs the client verb that was parsed; nullopt when none was.
std::optional<int> run_client_command(const ClientCommands& c);

}  // namespace dtraced::cli
