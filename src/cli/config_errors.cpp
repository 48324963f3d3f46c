#include "cli/config_errors.h"

#include <string_view>
#include <utility>

#include "cli/json_config.h"

namespace dtraced::cli {

namespace {

struct FieldFlag {
  std::string_view field;  // as collector::check_collector_config and worker::validate name it
  std::string_view flag;
};

// Both roles' fields that a flag sets (cli/roles.cpp turns the flags into these fields).
constexpr FieldFlag kFieldFlags[] = {
    // collector
    {"listen_address", "--listen"},
    {"state_dir", "--state-dir"},
    {"limits.max_connections", "--max-connections"},
    {"limits.max_idle_connections", "--max-idle-connections"},
    {"workers.max_workers", "--max-workers"},
    {"queue.max_retry_after", "--max-idle-wait-ms"},
    {"limits.max_body_bytes", "--max-body-bytes"},
    {"limits.read_timeout", "--read-timeout-ms"},
    {"limits.write_timeout", "--write-timeout-ms"},
    {"queue.reoffer_floor", "--reoffer-floor-ms"},
    {"queue.reoffer_factor", "--reoffer-factor"},
    {"queue.max_copies", "--max-copies"},
    {"shutdown_grace", "--shutdown-grace-ms"},
    {"cpu_threads", "--cpu-threads"},
    {"image_memory_bytes", "--image-memory-mb"},
    {"scene", "--scene"},
    {"output", "--output"},
    {"exit_when_done", "--exit-when-done"},
    // worker
    {"collector_url", "--collector"},
    {"name", "--name"},
    {"threads", "--threads"},
    {"scene_cache", "--scene-cache"},
    {"isa", "--isa"},
    {"grace", "--grace-seconds"},
    {"timeouts.connect", "--connect-timeout-ms"},
    {"timeouts.read", "--request-timeout-ms"},
    {"timeouts.write", "--request-timeout-ms"},
    {"max_unacknowledged", "--max-unacknowledged"},
    {"exit_when_idle", "--exit-when-idle"},
    {"max_runtime", "--max-runtime"},
    {"start_jitter", "--start-jitter-ms"},
    // both: the field holds the token, the flag names the file that holds it
    {"token", "--token-file"},
};

}  // namespace

std::string flag_of_field(const std::string& field) {
  for (const FieldFlag& f : kFieldFlags) {
    if (f.field == field) return std::string(f.flag);
  }
  return {};
}

util::Error locate_role_error(const CLI::App& app, util::Error e) {
  if (!e.file.empty()) return e;  // already located (a token file, a scene)
  std::string flag = e.path.starts_with("--") ? e.path : flag_of_field(e.path);
  if (flag.empty()) return e;
  // The token's own problems are about what the token file holds.
  std::string message = e.path == "token" ? "the token it holds: " + e.message : std::move(e.message);
  return option_error(app, flag, std::move(message));
}

std::string located_errors_text(const CLI::App& app, const util::Errors& errors) {
  util::Errors located;
  located.reserve(errors.size());
  for (const util::Error& e : errors) located.push_back(locate_role_error(app, e));
  return util::to_string(located);
}

}  // namespace dtraced::cli
