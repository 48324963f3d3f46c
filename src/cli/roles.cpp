#include "cli/roles.h"

#include <charconv>
#include <filesystem>
#include <string>
#include <vector>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "cli/client_verbs.h"
#include "cli/overrides_flags.h"
#include "collector/config.h"
#include "collector/service.h"
#include "image/image_io.h"
#include "worker/config.h"
#include "worker/worker.h"

namespace dtraced::cli {

namespace {

constexpr int kExitUsage = 2;
constexpr const char* kCollectorGroup = "Collector role (--role collector)";
constexpr const char* kWorkerGroup = "Worker role (--role worker)";

// "HOST:PORT" with an IPv4 address or a bracketed IPv6 address ("[::1]:7878").
bool parse_listen(const std::string& text, std::string& host, std::uint16_t& port, std::string& error) {
  const std::size_t colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0) {
    error = fmt::format("--listen: expected ADDRESS:PORT, got \"{}\"", text);
    return false;
  }
  host = text.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  const std::string p = text.substr(colon + 1);
  unsigned value = 0;
  const auto [end, ec] = std::from_chars(p.data(), p.data() + p.size(), value);
  if (ec != std::errc() || end != p.data() + p.size() || value > 65535) {
    error = fmt::format("--listen: bad port \"{}\" (0-65535)", p);
    return false;
  }
  port = static_cast<std::uint16_t>(value);
  return true;
}

int run_collector_role(const RoleArgs& a) {
  collector::CollectorConfig c;
  std::string error;
  if (!parse_listen(a.listen, c.listen_address, c.port, error)) {
    fmt::print(stderr, "{}\n", error);
    return kExitUsage;
  }
  c.state_dir = a.state_dir;
  c.output_dir = a.output_dir;
  if (a.token_file.empty()) {
    fmt::print(stderr, "--token-file is required: every request but /healthz needs the bearer token\n");
    return kExitUsage;
  }
  auto token = read_token_file(a.token_file, error);
  if (!token) {
    fmt::print(stderr, "{}\n", error);
    return kExitUsage;
  }
  c.token = *token;
  if (a.max_connections) c.limits.max_connections = *a.max_connections;
  if (a.max_body_bytes) c.limits.max_body_bytes = *a.max_body_bytes;
  if (a.read_timeout_ms) c.limits.read_timeout = std::chrono::milliseconds(*a.read_timeout_ms);
  if (a.write_timeout_ms) c.limits.write_timeout = std::chrono::milliseconds(*a.write_timeout_ms);
  if (a.reoffer_floor_ms) c.queue.reoffer_floor = std::chrono::milliseconds(*a.reoffer_floor_ms);
  if (a.reoffer_factor) c.queue.reoffer_factor = *a.reoffer_factor;
  if (a.max_copies) c.queue.max_copies = *a.max_copies;
  if (a.shutdown_grace_ms) c.shutdown_grace = std::chrono::milliseconds(*a.shutdown_grace_ms);
  if (a.cpu_threads) c.cpu_threads = *a.cpu_threads;
  if (!a.scene.empty()) {
    if (a.output.empty()) {
      fmt::print(stderr, "--scene needs --output (the image to write)\n");
      return kExitUsage;
    }
    collector::OneShotJob job;
    job.scene_path = a.scene;
    // The image path splits into the output directory and the job's output name.
    const std::filesystem::path out(a.output);
    job.output = out.filename().string();
    if (out.has_parent_path()) {
      if (!a.output_dir.empty()) {
        fmt::print(stderr, "--output with a directory and --output-dir together: give one of them\n");
        return kExitUsage;
      }
      c.output_dir = out.parent_path().string();
    } else if (a.output_dir.empty()) {
      c.output_dir = ".";
    }
    job.overrides = a.overrides;
    c.one_shot = job;
    c.exit_when_done = a.exit_when_done;
  } else if (!a.output.empty() || a.overrides != scene::Overrides{} || a.exit_when_done) {
    std::vector<std::string> given = given_override_flags(a.overrides);
    if (!a.output.empty()) given.insert(given.begin(), "--output");
    if (a.exit_when_done) given.emplace_back("--exit-when-done");
    fmt::print(stderr, "{} {} a one-shot job's: {} --scene\n", fmt::join(given, ", "), given.size() == 1 ? "is" : "are",
               given.size() == 1 ? "it needs" : "they need");
    return kExitUsage;
  }
  if (const util::Errors errors = collector::check_collector_config(c); !errors.empty()) {
    fmt::print(stderr, "{}\n", util::to_string(errors));
    return kExitUsage;
  }
  return collector::run_collector(c);
}

int run_worker_role(const RoleArgs& a) {
  worker::WorkerConfig w;
  w.collector_url = a.collector;
  std::string error;
  if (a.token_file.empty()) {
    fmt::print(stderr, "--token-file is required: the collector answers only with the bearer token\n");
    return kExitUsage;
  }
  auto token = read_token_file(a.token_file, error);
  if (!token) {
    fmt::print(stderr, "{}\n", error);
    return kExitUsage;
  }
  w.token = *token;
  w.name = a.name;
  w.threads = a.threads;
  w.isa = a.kernels;
  if (a.scene_cache) w.scene_cache = *a.scene_cache;
  if (a.grace_seconds) w.grace = std::chrono::seconds(*a.grace_seconds);
  if (a.connect_timeout_ms) w.timeouts.connect = std::chrono::milliseconds(*a.connect_timeout_ms);
  if (a.request_timeout_ms) {
    w.timeouts.read = w.timeouts.write = std::chrono::milliseconds(*a.request_timeout_ms);
  }
  if (a.max_unacknowledged) w.max_unacknowledged = *a.max_unacknowledged;
  const auto problems = worker::validate(w);
  if (!problems.empty()) {
    for (const auto& p : problems) fmt::print(stderr, "{}\n", p.to_string());
    return kExitUsage;
  }
  return worker::run_worker(w);
}

}  // namespace

void add_role_options(CLI::App& app, RoleArgs& a) {
  app.add_option("--role", a.role, "Run as a daemon: collector or worker")
      ->check(CLI::IsMember({"collector", "worker"}));
  app.add_option("--token-file", a.token_file, "File holding the farm's bearer token (both roles)");

  app.add_option("--listen", a.listen, "Address and port to listen on (ADDRESS:PORT, [IPv6]:PORT; port 0: any)")
      ->group(kCollectorGroup)
      ->capture_default_str();
  app.add_option("--state-dir", a.state_dir, "Directory of the durable state (dtraced.db)")->group(kCollectorGroup);
  app.add_option("--output-dir", a.output_dir, "Directory for finished images (default STATE_DIR/output)")
      ->group(kCollectorGroup);
  app.add_option("--max-connections", a.max_connections, "Open connections at most")
      ->check(CLI::Range(1u, 100000u))
      ->group(kCollectorGroup);
  app.add_option("--max-body-bytes", a.max_body_bytes, "Largest request body")
      ->check(CLI::Range(std::uint64_t{1024}, std::uint64_t{1} << 32))
      ->group(kCollectorGroup);
  app.add_option("--read-timeout-ms", a.read_timeout_ms, "Time a client has to send its request")
      ->check(CLI::Range(10u, 3600000u))
      ->group(kCollectorGroup);
  app.add_option("--write-timeout-ms", a.write_timeout_ms, "Time a client has to read an answer")
      ->check(CLI::Range(10u, 3600000u))
      ->group(kCollectorGroup);
  app.add_option("--reoffer-floor-ms", a.reoffer_floor_ms, "A leased tile is not offered again before this")
      ->check(CLI::Range(1u, 86400000u))
      ->group(kCollectorGroup);
  app.add_option("--reoffer-factor", a.reoffer_factor, "Re-offer bound as a multiple of the p90 tile time")
      ->check(CLI::Range(1.0, 1000.0))
      ->group(kCollectorGroup);
  app.add_option("--max-copies", a.max_copies, "Workers rendering one tile at once, at most")
      ->check(CLI::Range(1u, 64u))
      ->group(kCollectorGroup);
  app.add_option("--shutdown-grace-ms", a.shutdown_grace_ms, "On SIGTERM, time for requests in flight")
      ->check(CLI::Range(0u, 600000u))
      ->group(kCollectorGroup);
  app.add_option("--cpu-threads", a.cpu_threads, "Threads for image encoding and payload checks")
      ->check(CLI::Range(1u, 256u))
      ->group(kCollectorGroup);
  app.add_option("--scene", a.scene, "One-shot: enqueue this scene at start (resumed after a restart)")
      ->group(kCollectorGroup);
  app.add_option("-o,--output", a.output, "One-shot: the image to write (" + image::extension_list() + ")")
      ->group(kCollectorGroup);
  OverrideFlagOptions one_shot;
  one_shot.group = kCollectorGroup;
  one_shot.help_prefix = "One-shot: ";
  add_override_flags(app, a.overrides, one_shot);
  app.add_flag("--exit-when-done", a.exit_when_done, "One-shot: exit 0 once the image is written")
      ->group(kCollectorGroup);

  app.add_option("--collector", a.collector, "Collector base URL, http://HOST:PORT")->group(kWorkerGroup);
  app.add_option("--name", a.name, "Worker name in the collector's logs (default HOST-PID)")->group(kWorkerGroup);
  app.add_option("-t,--threads", a.threads, "Render threads (0: every core)")
      ->check(CLI::Range(0u, 4096u))
      ->group(kWorkerGroup);
  app.add_option("--scene-cache", a.scene_cache, "Scenes kept built in memory")
      ->check(CLI::Range(1u, 1024u))
      ->group(kWorkerGroup);
  app.add_option("--grace-seconds", a.grace_seconds, "On SIGTERM, time to submit the tiles in hand")
      ->check(CLI::Range(0u, 3600u))
      ->group(kWorkerGroup);
  app.add_option("--connect-timeout-ms", a.connect_timeout_ms, "Connect timeout")
      ->check(CLI::Range(1u, 600000u))
      ->group(kWorkerGroup);
  app.add_option("--request-timeout-ms", a.request_timeout_ms, "Read and write timeout of each request")
      ->check(CLI::Range(1u, 600000u))
      ->group(kWorkerGroup);
  app.add_option("--max-unacknowledged", a.max_unacknowledged, "Tiles in hand at most (0: 4 per thread)")
      ->check(CLI::Range(0u, 65536u))
      ->group(kWorkerGroup);
  // Also an option of `render` (main adds it there, bound to the same value).
  app.add_option("--isa", a.isa, kIsaHelp)->group(kWorkerGroup);
}

int run_role(const CLI::App& app, const RoleArgs& a) {
  // A flag of the other role is a mistake worth stopping for, not something to ignore.
  const std::string other = a.role == "collector" ? kWorkerGroup : kCollectorGroup;
  for (const CLI::Option* opt : app.get_options()) {
    if (opt->get_group() == other && opt->count() > 0) {
      fmt::print(stderr, "{} is not an option of --role {}\n", opt->get_name(), a.role);
      return kExitUsage;
    }
  }
  return a.role == "collector" ? run_collector_role(a) : run_worker_role(a);
}

}  // namespace dtraced::cli
