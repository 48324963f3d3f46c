#include "worker/config.h"

#include <limits.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <thread>
#include <utility>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "protocol/messages.h"

namespace dtraced::worker {
namespace {

bool is_printable(char c) { return c >= 0x20 && c <= 0x7e; }
bool is_visible(char c) { return c > 0x20 && c <= 0x7e; }

template <typename Duration>
void check_range(std::vector<std::string>& errors, std::string_view field, Duration value, Duration min, Duration max,
                 std::string_view unit) {
  if (value < min || value > max) {
    errors.push_back(
        fmt::format("{}: must be in [{}, {}] {} (got {})", field, min.count(), max.count(), unit, value.count()));
  }
}

}  // namespace

std::string default_worker_name() {
  std::array<char, HOST_NAME_MAX + 1> host{};
  std::string name;
  if (::gethostname(host.data(), host.size() - 1) == 0) name = host.data();
  for (char& c : name) {
    if (!is_visible(c)) c = '_';
  }
  if (name.empty()) name = "worker";
  const std::string pid = fmt::format("-{}", ::getpid());
  name.resize(std::min(name.size(), protocol::kMaxWorkerNameBytes - pid.size()));
  return name + pid;
}

std::vector<std::string> validate(const WorkerConfig& config) {
  std::vector<std::string> errors;

  std::string url_error;
  if (config.collector_url.empty()) {
    errors.push_back("collector_url: required (http://host[:port])");
  } else if (!http::parse_base_url(config.collector_url, url_error)) {
    errors.push_back(fmt::format("collector_url: {}", url_error));
  }

  if (config.token.empty()) {
    errors.push_back("token: required (the collector's bearer token)");
  } else if (config.token.size() > kMaxTokenBytes) {
    errors.push_back(fmt::format("token: longer than {} bytes", kMaxTokenBytes));
  } else if (!std::all_of(config.token.begin(), config.token.end(), is_visible)) {
    errors.push_back("token: must be visible ASCII characters without spaces or line breaks");
  }

  if (config.name.size() > protocol::kMaxWorkerNameBytes) {
    errors.push_back(fmt::format("name: longer than {} bytes", protocol::kMaxWorkerNameBytes));
  } else if (!std::all_of(config.name.begin(), config.name.end(), is_printable)) {
    errors.push_back("name: must be printable ASCII characters");
  }

  if (config.threads > protocol::kMaxWorkerThreads) {
    errors.push_back(
        fmt::format("threads: at most {} (0 means every core; got {})", protocol::kMaxWorkerThreads, config.threads));
  }
  if (config.scene_cache < 1 || config.scene_cache > kMaxSceneCache) {
    errors.push_back(
        fmt::format("scene_cache: must be in [1, {}] scenes (got {})", kMaxSceneCache, config.scene_cache));
  }
  if (const auto supported = accel::supported_isas();
      std::find(supported.begin(), supported.end(), config.isa) == supported.end()) {
    std::vector<std::string_view> names;
    for (const accel::Isa i : supported) names.push_back(accel::isa_name(i));
    errors.push_back(fmt::format("isa: {} is not supported by this CPU (supported: {})", accel::isa_name(config.isa),
                                 fmt::join(names, ", ")));
  }
  check_range(errors, "grace", config.grace, std::chrono::seconds{0}, kMaxGrace, "s");

  using std::chrono::milliseconds;
  check_range(errors, "timeouts.connect", config.timeouts.connect, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "timeouts.write", config.timeouts.write, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "timeouts.read", config.timeouts.read, milliseconds{1}, kMaxClientTimeout, "ms");
  check_range(errors, "backoff_initial", config.backoff_initial, milliseconds{1}, kMaxBackoff, "ms");
  check_range(errors, "backoff_max", config.backoff_max, std::max(milliseconds{1}, config.backoff_initial), kMaxBackoff,
              "ms");

  if (config.max_unacknowledged > kMaxUnacknowledged) {
    errors.push_back(fmt::format("max_unacknowledged: at most {} tiles (0 means {} per thread; got {})",
                                 kMaxUnacknowledged, kInHandPerThread, config.max_unacknowledged));
  }
  return errors;
}

WorkerConfig resolve_defaults(WorkerConfig config) {
  if (config.name.empty()) config.name = default_worker_name();
  if (config.threads == 0) {
    config.threads = std::clamp(std::thread::hardware_concurrency(), 1u, protocol::kMaxWorkerThreads);
  }
  if (config.max_unacknowledged == 0) {
    config.max_unacknowledged = std::min(kMaxUnacknowledged, kInHandPerThread * config.threads);
  }
  return config;
}

}  // namespace dtraced::worker
