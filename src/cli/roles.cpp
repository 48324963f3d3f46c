#include "cli/roles.h"

#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <variant>
#include <vector>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "cli/client_verbs.h"
#include "cli/config_errors.h"
#include "cli/listen_address.h"
#include "cli/overrides_flags.h"
#include "cli/tls_flags.h"
#include "collector/config.h"
#include "collector/service.h"
#include "image/image_io.h"
#include "util/file.h"
#include "util/result.h"
#include "worker/config.h"
#include "worker/worker.h"

namespace dtraced::cli {

namespace {

constexpr int kExitUsage = 2;
constexpr const char* kCollectorGroup = "Collector role (--role collector)";
constexpr const char* kWorkerGroup = "Worker role (--role worker)";

// The role's bearer token from --token-file, without which the role cannot work (`why`).
util::Result<std::string> role_token(const RoleArgs& a, std::string_view why) {
  if (a.token_file.empty()) return util::Error{fmt::format("--token-file is required: {}", why)};
  return read_token_file(a.token_file);
}

int usage_error(const util::Error& e) {
  fmt::print(stderr, "{}\n", e.to_string());
  return kExitUsage;
}

int run_collector_role(const CLI::App& app, const RoleArgs& a) {
  collector::CollectorConfig c;
  const util::Result<ListenAddress> listen = parse_listen(a.listen);
  if (!listen) return usage_error(locate_role_error(app, listen.error()));
  c.listen_address = listen->host;
  c.port = listen->port;
  util::Result<std::string> token = role_token(a, "every request but /healthz needs the bearer token");
  if (!token) return usage_error(token.error());
  c.token = std::move(token).value();
  c.state_dir = a.state_dir;
  c.output_dir = a.output_dir;
  if (a.max_connections) c.limits.max_connections = *a.max_connections;
  // Idle kept-alive connections follow --max-connections unless given: a farm raises one flag.
  c.limits.max_idle_connections = a.max_idle_connections.value_or(c.limits.max_connections);
  if (a.max_body_bytes) c.limits.max_body_bytes = *a.max_body_bytes;
  if (a.read_timeout_ms) c.limits.read_timeout = std::chrono::milliseconds(*a.read_timeout_ms);
  if (a.write_timeout_ms) c.limits.write_timeout = std::chrono::milliseconds(*a.write_timeout_ms);
  if (a.idle_timeout_ms) c.limits.idle_keepalive_timeout = std::chrono::milliseconds(*a.idle_timeout_ms);
  if (a.reoffer_floor_ms) c.queue.reoffer_floor = std::chrono::milliseconds(*a.reoffer_floor_ms);
  if (a.reoffer_factor) c.queue.reoffer_factor = *a.reoffer_factor;
  if (a.max_copies) c.queue.max_copies = *a.max_copies;
  if (a.shutdown_grace_ms) c.shutdown_grace = std::chrono::milliseconds(*a.shutdown_grace_ms);
  if (a.cpu_threads) c.cpu_threads = *a.cpu_threads;
  if (a.image_memory_mb) c.image_memory_bytes = std::uint64_t{*a.image_memory_mb} << 20;
  if (a.worker_quiet_after_s) c.workers.quiet_after = std::chrono::seconds(*a.worker_quiet_after_s);
  if (a.worker_forget_after_s) c.workers.forget_after = std::chrono::seconds(*a.worker_forget_after_s);
  if (a.max_workers) c.workers.max_workers = *a.max_workers;
  if (a.max_idle_wait_ms) c.queue.max_retry_after = std::chrono::milliseconds(*a.max_idle_wait_ms);
  c.web_ui = !a.no_web_ui;
  const util::Result<bool> tls = resolve_tls(a.tls, c.listen_address, a.allow_plain_http);
  if (!tls) return usage_error(locate_role_error(app, tls.error()));
  c.tls.enabled = *tls;
  c.tls.cert_file = a.tls_cert;
  c.tls.key_file = a.tls_key;
  c.tls.ca_file = a.tls_ca;
  c.tls.names = a.tls_names;
  if (!c.tls.enabled && (!a.tls_cert.empty() || !a.tls_key.empty() || !a.tls_ca.empty() || !a.tls_names.empty())) {
    fmt::print(stderr, "--tls-cert, --tls-key, --tls-ca and --tls-name need TLS, which is off for {} ({})\n",
               c.listen_address, a.tls == "off" ? "--tls off" : "a loopback address: add --tls on");
    return kExitUsage;
  }
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
      // A directory the user named must exist (as render's): found now, not after the render.
      if (const util::Status ok = util::check_output_path(a.output); !ok) return usage_error(ok.error());
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
    fmt::print(stderr, "{}\n", located_errors_text(app, errors));
    return kExitUsage;
  }
  return collector::run_collector(c);
}

int run_worker_role(const CLI::App& app, const RoleArgs& a) {
  worker::WorkerConfig w;
  w.collector_url = a.collector;
  util::Result<std::string> token = role_token(a, "the collector answers only with the bearer token");
  if (!token) return usage_error(token.error());
  w.token = *token;
  w.name = a.name;
  w.ca_file = a.ca_file;
  w.threads = a.threads;
  w.isa = a.kernels;
  if (a.scene_cache) w.scene_cache = *a.scene_cache;
  w.scene_cache_dir = a.scene_cache_dir;
  if (a.grace_seconds) w.grace = std::chrono::seconds(*a.grace_seconds);
  if (a.connect_timeout_ms) w.timeouts.connect = std::chrono::milliseconds(*a.connect_timeout_ms);
  if (a.request_timeout_ms) {
    w.timeouts.read = w.timeouts.write = std::chrono::milliseconds(*a.request_timeout_ms);
  }
  if (a.max_unacknowledged) w.max_unacknowledged = *a.max_unacknowledged;
  w.exit_when_done = a.exit_when_done;
  if (a.exit_when_idle) w.exit_when_idle = std::chrono::seconds(*a.exit_when_idle);
  if (a.max_runtime) w.max_runtime = std::chrono::seconds(*a.max_runtime);
  if (a.start_jitter_ms) w.start_jitter = std::chrono::milliseconds(*a.start_jitter_ms);
  const auto problems = worker::validate(w);
  if (!problems.empty()) {
    fmt::print(stderr, "{}\n", located_errors_text(app, problems));
    return kExitUsage;
  }
  return worker::run_worker(w);
}

// A numeric flag of one role: its field, range and help. The range has the field's type.
using NumberField = std::variant<std::uint32_t RoleArgs::*, std::optional<std::uint32_t> RoleArgs::*,
                                 std::optional<std::uint64_t> RoleArgs::*, std::optional<double> RoleArgs::*>;
struct NumberFlag {
  const char* group;
  const char* name;
  NumberField field;
  double lo, hi;  // exact for every bound below
  const char* help;
};

// In the order --help lists them.
const NumberFlag kNumberFlags[] = {
    {kCollectorGroup, "--max-connections", &RoleArgs::max_connections, 1, 100000,
     "Open connections at most (default 256; a farm needs one per worker)"},
    {kCollectorGroup, "--max-idle-connections", &RoleArgs::max_idle_connections, 1, 100000,
     "Kept-alive connections idle between requests at most; past it the one idle longest is closed and its "
     "client pays a new TLS handshake (default: --max-connections, so raising that is enough)"},
    {kCollectorGroup, "--max-body-bytes", &RoleArgs::max_body_bytes, 1024, 4294967296.0, "Largest request body"},
    {kCollectorGroup, "--read-timeout-ms", &RoleArgs::read_timeout_ms, 10, 3600000,
     "Time a client has to send its request"},
    {kCollectorGroup, "--write-timeout-ms", &RoleArgs::write_timeout_ms, 10, 3600000,
     "Time a client has to read an answer"},
    {kCollectorGroup, "--idle-timeout-ms", &RoleArgs::idle_timeout_ms, 10, 3600000,
     "Time an authenticated connection may idle between requests"},
    {kCollectorGroup, "--reoffer-floor-ms", &RoleArgs::reoffer_floor_ms, 1, 86400000,
     "A leased tile is not offered again before this"},
    {kCollectorGroup, "--reoffer-factor", &RoleArgs::reoffer_factor, 1, 1000,
     "Re-offer bound as a multiple of the p90 tile time"},
    {kCollectorGroup, "--max-copies", &RoleArgs::max_copies, 1, 64, "Workers rendering one tile at once, at most"},
    {kCollectorGroup, "--shutdown-grace-ms", &RoleArgs::shutdown_grace_ms, 0, 600000,
     "On SIGTERM, time for requests in flight"},
    {kCollectorGroup, "--cpu-threads", &RoleArgs::cpu_threads, 1, 256, "Threads for image encoding and payload checks"},
    {kCollectorGroup, "--image-memory-mb", &RoleArgs::image_memory_mb, 1, 1048576,
     "MiB of images assembled from the store at once, to write or serve them (12 bytes a pixel; default 3072: one "
     "16384x16384 frame); a larger frame is still assembled, alone"},
    {kCollectorGroup, "--worker-quiet-after-s", &RoleArgs::worker_quiet_after_s, 1, 86400,
     "A worker unseen this long shows as quiet (default 60)"},
    {kCollectorGroup, "--worker-forget-after-s", &RoleArgs::worker_forget_after_s, 1, 2592000,
     "A worker unseen this long leaves the worker list (default 3600)"},
    {kCollectorGroup, "--max-workers", &RoleArgs::max_workers, 1, 1000000,
     "Workers the worker list keeps at most (about 0.5 KiB each); past it a new worker evicts the one seen "
     "least recently (default 65536)"},
    {kCollectorGroup, "--max-idle-wait-ms", &RoleArgs::max_idle_wait_ms, 50, 60000,
     "Longest wait told to a worker with nothing to do; the wait is 5 ms x the workers known, at least 50 ms "
     "(default 5000: farms up to 100 workers wait at most 0.5 s, larger ones poll ~200 times/s in all up to 1,000 "
     "workers; an idle worker notices a new job within 1.5 x its wait)"},
    {kWorkerGroup, "-t,--threads", &RoleArgs::threads, 0, 4096,
     "Render threads (0: every CPU this process may use, its affinity mask)"},
    {kWorkerGroup, "--scene-cache", &RoleArgs::scene_cache, 1, 1024, "Scenes kept built in memory"},
    {kWorkerGroup, "--grace-seconds", &RoleArgs::grace_seconds, 0, 3600,
     "On SIGTERM, time to submit the tiles in hand"},
    {kWorkerGroup, "--connect-timeout-ms", &RoleArgs::connect_timeout_ms, 1, 600000, "Connect timeout"},
    {kWorkerGroup, "--request-timeout-ms", &RoleArgs::request_timeout_ms, 1, 600000,
     "Read and write timeout of each request"},
    {kWorkerGroup, "--max-unacknowledged", &RoleArgs::max_unacknowledged, 0, 65536,
     "Tiles in hand at most (0: 16 per thread)"},
    {kWorkerGroup, "--exit-when-idle", &RoleArgs::exit_when_idle, 1, 2592000,
     "Batch jobs: exit 0 once the collector has had no work for this worker for this many seconds"},
    {kWorkerGroup, "--max-runtime", &RoleArgs::max_runtime, 1, 31622400,
     "Batch jobs: stop leasing after this many seconds, submit what is in hand, exit 0"},
    {kWorkerGroup, "--start-jitter-ms", &RoleArgs::start_jitter_ms, 0, 3600000,
     "Wait a random time up to this long before the first request, so that a farm started at once does not "
     "reach the collector at once (default 0; SIGTERM during the wait exits 0 at once)"},
};

template <typename T>
struct Unoptional {
  using type = T;
};
template <typename T>
struct Unoptional<std::optional<T>> {
  using type = T;
};

// The flags of kNumberFlags in `group`.
void add_number_flags(CLI::App& app, RoleArgs& a, const char* group) {
  for (const NumberFlag& f : kNumberFlags) {
    if (std::string_view(f.group) != group) continue;
    std::visit(
        [&](auto member) {
          auto& field = a.*member;
          using T = typename Unoptional<std::remove_reference_t<decltype(field)>>::type;
          app.add_option(f.name, field, f.help)
              ->check(CLI::Range(static_cast<T>(f.lo), static_cast<T>(f.hi)))
              ->group(group);
        },
        f.field);
  }
}

}  // namespace

void add_role_options(CLI::App& app, RoleArgs& a) {
  app.add_option("--role", a.role, "Run as a daemon: collector or worker")
      ->check(CLI::IsMember({"collector", "worker"}));
  app.add_option("--token-file", a.token_file, "File holding the farm's bearer token (both roles)");

  app.add_option("--listen", a.listen,
                 "Address and port to listen on (HOST:PORT, HOST an address or a name; [IPv6]:PORT; port 0: any)")
      ->group(kCollectorGroup)
      ->capture_default_str();
  app.add_option("--state-dir", a.state_dir, "Directory of the durable state (dtraced.db)")->group(kCollectorGroup);
  app.add_option("--output-dir", a.output_dir, "Directory for finished images (default STATE_DIR/output)")
      ->group(kCollectorGroup);
  add_number_flags(app, a, kCollectorGroup);
  app.add_option("--scene", a.scene, "One-shot: enqueue this scene at start (resumed after a restart)")
      ->group(kCollectorGroup);
  app.add_option("-o,--output", a.output, "One-shot: the image to write (" + image::extension_list() + ")")
      ->group(kCollectorGroup);
  OverrideFlagOptions one_shot;
  one_shot.group = kCollectorGroup;
  one_shot.help_prefix = "One-shot: ";
  add_override_flags(app, a.overrides, one_shot);
  app.add_flag("--no-web-ui", a.no_web_ui, "Serve no web page: `/` and `/ui/...` answer 404")->group(kCollectorGroup);
  app.add_option("--tls", a.tls,
                 "auto (TLS unless the listen address is loopback), on, or off (plain HTTP; off loopback it needs "
                 "--allow-plain-http)")
      ->check(CLI::IsMember({"auto", "on", "off"}))
      ->group(kCollectorGroup)
      ->capture_default_str();
  app.add_option("--tls-cert", a.tls_cert,
                 "Your own server certificate (PEM chain) instead of the private CA's (default: "
                 "STATE_DIR/tls holds a CA created on first start)")
      ->group(kCollectorGroup);
  app.add_option("--tls-key", a.tls_key, "The private key of --tls-cert (PEM)")->group(kCollectorGroup);
  app.add_option("--tls-ca", a.tls_ca,
                 "With --tls-cert: the CA workers must trust (PEM); join codes carry its fingerprint")
      ->group(kCollectorGroup);
  app.add_option("--tls-name", a.tls_names,
                 "A DNS name or address workers use to reach this collector, added to the private CA's server "
                 "certificate (repeatable; the host name and the listen addresses are always in it)")
      ->group(kCollectorGroup);
  app.add_flag("--allow-plain-http", a.allow_plain_http,
               "Allow --tls off on an address that is not loopback (only behind a TLS proxy or on a trusted link)")
      ->group(kCollectorGroup);
  // Both roles (so in neither group): one flag name, one meaning, "exit once the one-shot job is over".
  app.add_flag("--exit-when-done", a.exit_when_done,
               "One-shot collector: exit 0 once the image is written. Worker: exit 0 when its collector says it "
               "has finished (a one-shot collector with this flag)");

  app.add_option("--collector", a.collector, "Collector base URL, https://HOST:PORT (or http:// on loopback)")
      ->group(kWorkerGroup);
  app.add_option("--ca-file", a.ca_file,
                 "The collector's CA certificate (PEM) to trust for an https:// collector (dtraced enroll writes it)")
      ->group(kWorkerGroup);
  app.add_option("--name", a.name, "Worker name in the collector's logs (default HOST-PID; under Slurm HOST-JOB_TASK)")
      ->group(kWorkerGroup);
  app.add_option("--scene-cache-dir", a.scene_cache_dir,
                 "Directory where static scenes are kept render-ready on disk by digest (default: none)")
      ->group(kWorkerGroup);
  add_number_flags(app, a, kWorkerGroup);
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
  return a.role == "collector" ? run_collector_role(app, a) : run_worker_role(app, a);
}

}  // namespace dtraced::cli
