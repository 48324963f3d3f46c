#include "worker/config.h"

#include <limits.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cstdint>
#include <cstdlib>
#include <string>
#include <utility>
#include <vector>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "protocol/messages.h"
#include "util/cpus.h"
#include "util/file.h"

namespace dtraced::worker {
namespace {

bool is_printable(char c) { return c >= 0x20 && c <= 0x7e; }
bool is_visible(char c) { return c > 0x20 && c <= 0x7e; }

// A problem with the option `field` (util::Error::path), so that it reads "field: message".
void add_problem(util::Errors& errors, std::string_view field, std::string message) {
  errors.push_back(util::Error{std::move(message), std::string(field), /*file=*/""});
}

template <typename Duration>
void check_range(util::Errors& errors, std::string_view field, Duration value, Duration min, Duration max,
                 std::string_view unit) {
  if (value < min || value > max) {
    add_problem(errors, field,
                fmt::format("must be in [{}, {}] {} (got {})", min.count(), max.count(), unit, value.count()));
  }
}

}  // namespace

const char* process_env(const char* name) { return std::getenv(name); }

std::chrono::milliseconds start_delay(std::chrono::milliseconds max, std::mt19937_64& rng) {
  if (max.count() <= 0) return std::chrono::milliseconds{0};
  std::uniform_int_distribution<std::int64_t> pick(0, max.count());
  return std::chrono::milliseconds{pick(rng)};
}

std::string default_worker_name(const EnvLookup& env) {
  std::array<char, HOST_NAME_MAX + 1> host{};
  std::string name;
  if (::gethostname(host.data(), host.size() - 1) == 0) name = host.data();
  if (name.empty()) name = "worker";
  // A variable that is set and not empty.
  const auto var = [&env](const char* key) -> std::string {
    const char* value = env(key);
    return value != nullptr ? std::string(value) : std::string();
  };
  std::string suffix;
  if (const std::string array_job = var("SLURM_ARRAY_JOB_ID"), task = var("SLURM_ARRAY_TASK_ID");
      !array_job.empty() && !task.empty()) {
    suffix = fmt::format("-{}_{}", array_job, task);
  } else if (const std::string job = var("SLURM_JOB_ID"); !job.empty()) {
    suffix = fmt::format("-{}", job);
  }
  if (!suffix.empty()) {
    const std::string tasks = var("SLURM_NTASKS"), procid = var("SLURM_PROCID");
    if (!procid.empty() && !tasks.empty() && tasks != "1") suffix += "." + procid;
  } else {
    suffix = fmt::format("-{}", ::getpid());
  }
  suffix.resize(std::min(suffix.size(), protocol::kMaxWorkerNameBytes / 2));
  name.resize(std::min(name.size(), protocol::kMaxWorkerNameBytes - suffix.size()));
  name += suffix;
  for (char& c : name) {
    if (!is_visible(c)) c = '_';
  }
  return name;
}

util::Errors validate(const WorkerConfig& config) {
  util::Errors errors;

  if (config.collector_url.empty()) {
    add_problem(errors, "collector_url", "required (http://host[:port] or https://host[:port])");
  } else if (util::Result<http::Url> url = http::parse_base_url(config.collector_url); !url) {
    add_problem(errors, "collector_url", url.error().message);
  } else if (url->tls && config.ca_file.empty()) {
    add_problem(errors, "ca_file",
                "required for an https:// collector_url: the collector's CA certificate (tls/ca.pem in its state "
                "directory)");
  }

  if (config.token.empty()) {
    add_problem(errors, "token", "required (the collector's bearer token)");
  } else if (config.token.size() > kMaxTokenBytes) {
    add_problem(errors, "token", fmt::format("longer than {} bytes", kMaxTokenBytes));
  } else if (!std::all_of(config.token.begin(), config.token.end(), is_visible)) {
    add_problem(errors, "token", "must be visible ASCII characters without spaces or line breaks");
  }

  if (config.name.size() > protocol::kMaxWorkerNameBytes) {
    add_problem(errors, "name", fmt::format("longer than {} bytes", protocol::kMaxWorkerNameBytes));
  } else if (!std::all_of(config.name.begin(), config.name.end(), is_printable)) {
    add_problem(errors, "name", "must be printable ASCII characters");
  }

  if (config.threads > protocol::kMaxWorkerThreads) {
    add_problem(errors, "threads",
                fmt::format("at most {} (0 means every core; got {})", protocol::kMaxWorkerThreads, config.threads));
  }
  if (config.scene_cache < 1 || config.scene_cache > kMaxSceneCache) {
    add_problem(errors, "scene_cache",
                fmt::format("must be in [1, {}] scenes (got {})", kMaxSceneCache, config.scene_cache));
  }
  if (config.scene_cache_dir.size() > kMaxSceneCacheDirBytes) {
    add_problem(errors, "scene_cache_dir", fmt::format("longer than {} bytes", kMaxSceneCacheDirBytes));
  }
  if (const auto supported = accel::supported_isas();
      std::find(supported.begin(), supported.end(), config.isa) == supported.end()) {
    std::vector<std::string_view> names;
    for (const accel::Isa i : supported) names.push_back(accel::isa_name(i));
    add_problem(errors, "isa",
                fmt::format("{} is not supported by this CPU (supported: {})", accel::isa_name(config.isa),
                            fmt::join(names, ", ")));
  }
  check_range(errors, "grace", config.grace, std::chrono::seconds{0}, kMaxGrace, "s");

  using std::chrono::milliseconds;
  check_range(errors, "timeouts.connect", config.timeouts.connect, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "timeouts.write", config.timeouts.write, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "timeouts.read", config.timeouts.read, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "timeouts.handshake", config.timeouts.handshake, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "backoff_initial", config.backoff_initial, milliseconds{1}, kMaxBackoff, "ms");
  check_range(errors, "backoff_max", config.backoff_max, std::max(milliseconds{1}, config.backoff_initial), kMaxBackoff,
              "ms");

  check_range(errors, "exit_when_idle", config.exit_when_idle, std::chrono::seconds{0}, kMaxExitWhenIdle, "s");
  check_range(errors, "max_runtime", config.max_runtime, std::chrono::seconds{0}, kMaxRuntime, "s");
  check_range(errors, "start_jitter", config.start_jitter, milliseconds{0}, kMaxStartJitter, "ms");

  if (config.max_unacknowledged > kMaxUnacknowledged) {
    add_problem(errors, "max_unacknowledged",
                fmt::format("at most {} tiles (0 means {} per thread; got {})", kMaxUnacknowledged, kInHandPerThread,
                            config.max_unacknowledged));
  }
  return errors;
}

util::Result<std::optional<http::ClientTls>> load_client_tls(const WorkerConfig& config) {
  util::Result<http::Url> url = http::parse_base_url(config.collector_url);
  if (!url || !url->tls) return std::optional<http::ClientTls>();
  util::Result<std::string> pem = util::read_file_limited(config.ca_file, kMaxCaFileBytes);
  if (!pem) return util::Error{pem.error().message, "ca_file", config.ca_file};
  http::ClientTls tls;
  tls.ca_pem = std::move(pem).value();
  tls.ca_source = config.ca_file;
  if (util::Status usable = http::check_client_tls(tls); !usable) {
    return util::Error{usable.error().message, "ca_file"};  // the message names the file
  }
  return std::optional<http::ClientTls>(std::move(tls));
}

http::ClientOptions client_options(const WorkerConfig& config, std::optional<http::ClientTls> tls) {
  http::ClientOptions options;
  options.timeouts = config.timeouts;
  options.tls = std::move(tls);
  options.max_idle_connections =
      std::clamp<std::size_t>(std::size_t{2} * config.threads, kMinIdleConnections, kMaxIdleConnections);
  return options;
}

WorkerConfig resolve_defaults(WorkerConfig config) {
  if (config.name.empty()) config.name = default_worker_name();
  if (config.threads == 0) {
    config.threads = std::clamp(util::usable_cpus(), 1u, protocol::kMaxWorkerThreads);
  }
  if (config.max_unacknowledged == 0) {
    config.max_unacknowledged = std::min(kMaxUnacknowledged, kInHandPerThread * config.threads);
  }
  return config;
}

}  // namespace dtraced::worker
