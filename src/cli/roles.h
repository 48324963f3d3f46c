// dtraced::cli daemon roles: `dtraced --role collector` and `dtraced --role worker`.
//
// Adds the roles' flags to the top-level command line (each also settable from the JSON file
// given by --config; flags win), turns them into the collector's or the worker's configuration,
// and runs the daemon. Flags of the other role are usage errors.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "accel/isa.h"
#include "scene/overrides.h"

namespace dtraced::cli {

struct RoleArgs {
  std::string role;  // "collector", "worker" or empty (a verb runs instead)
  std::string token_file;
  // collector
  std::string listen = "127.0.0.1:7878";
  std::string state_dir;
  std::string scene_cache_dir;
  std::string output_dir;
  std::optional<std::uint32_t> max_connections, read_timeout_ms, write_timeout_ms, idle_timeout_ms, reoffer_floor_ms,
      max_copies, shutdown_grace_ms, cpu_threads, worker_quiet_after_s, worker_forget_after_s, max_idle_connections,
      max_workers, max_idle_wait_ms, image_memory_mb;
  bool no_web_ui = false;  // --no-web-ui: `/` and `/ui/...` are 404
  // TLS (cli/tls_flags.h): --tls auto|on|off, the operator's files, extra names, plain HTTP off
  // loopback only with --allow-plain-http.
  std::string tls = "auto";
  std::string tls_cert, tls_key, tls_ca;
  std::vector<std::string> tls_names;
  bool allow_plain_http = false;
  std::optional<std::uint64_t> max_body_bytes;
  std::optional<double> reoffer_factor;
  std::string scene;           // one-shot job
  std::string output;          // one-shot job's image path
  scene::Overrides overrides;  // one-shot job's overrides (the flags of cli/overrides_flags.h)
  // Both roles: the one-shot collector exits when its job is over, and so do its workers.
  bool exit_when_done = false;
  // worker
  std::string collector;
  std::string name;
  std::string ca_file;  // the collector's CA (PEM) for an https:// collector
  std::uint32_t threads = 0;
  std::optional<std::uint32_t> scene_cache, grace_seconds, connect_timeout_ms, request_timeout_ms, max_unacknowledged,
      exit_when_idle, max_runtime, start_jitter_ms;
  // worker and `render`: --isa as given (main resolves it with $DTRACED_ISA into `kernels`)
  std::optional<std::string> isa;
  accel::Isa kernels = accel::Isa::kScalar;
};

inline constexpr const char* kIsaHelp =
    "Traversal kernels: scalar, sse4, avx2, avx512 or best (default: $DTRACED_ISA if set, else best; "
    "worker and render)";

// Adds --role, the role flags and --config to `app`. Call before parsing.
void add_role_options(CLI::App& app, RoleArgs& args);

// Runs the chosen role; returns the exit code (2 for a usage or configuration error).
int run_role(const CLI::App& app, const RoleArgs& args);

}  // namespace dtraced::cli
