#include "worker/worker.h"

#include <cassert>
#include <cstdint>
#include <exception>
#include <filesystem>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <utility>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/post.hpp>

#include "async/systemd_notifier.h"
#include "util/log.h"
#include "worker/backoff.h"
#include "worker/worker_impl.h"

namespace dtraced::worker {
namespace {

std::uint64_t seed_from(std::uint64_t configured) {
  if (configured != 0) return configured;
  std::random_device device;
  return (std::uint64_t{device()} << 32) ^ device();
}

// `text` has passed validate(): it parses.
http::Url parse_url(const std::string& text) {
  util::Result<http::Url> url = http::parse_base_url(text);
  assert(url);
  return *url;
}

}  // namespace

Worker::Impl::Impl(WorkerConfig resolved, const util::Clock& clock, std::optional<http::ClientTls> tls)
    : config(std::move(resolved)),
      clock(clock),
      url(parse_url(config.collector_url)),
      authorization("Bearer " + config.token),
      client(io.get_executor(), client_options(config, std::move(tls))),
      pool(config.threads),
      rng(seed_from(config.jitter_seed)),
      scenes(config.scene_cache),
      lease_gate(io.get_executor(), clock, Backoff(config.backoff_initial, config.backoff_max), rng),
      submit_gate(io.get_executor(), clock, Backoff(config.backoff_initial, config.backoff_max), rng),
      stop(io.get_executor()),
      abandon(io.get_executor()),
      in_hand(io.get_executor(), config.max_unacknowledged, kHeldBytesPerThread * config.threads) {}

util::Result<std::unique_ptr<Worker>, util::Errors> Worker::create(const WorkerConfig& config,
                                                                   const util::Clock& clock) {
  util::Errors problems = validate(config);
  if (!problems.empty()) return problems;
  if (!config.scene_cache_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(config.scene_cache_dir, ec);
    if (ec || !std::filesystem::is_directory(config.scene_cache_dir, ec)) {
      return util::Errors{util::Error(fmt::format("scene_cache_dir: cannot create directory {}: {}",
                                                  config.scene_cache_dir, ec ? ec.message() : "not a directory"))};
    }
  }
  util::Result<std::optional<http::ClientTls>> tls = load_client_tls(config);
  if (!tls) return util::Errors{tls.error()};
  return std::unique_ptr<Worker>(
      new Worker(std::make_unique<Impl>(resolve_defaults(config), clock, std::move(tls).value())));
}

Worker::Worker(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

Worker::~Worker() = default;

bool Worker::run(const RunOptions& options) {
  Impl& s = *impl_;
  assert(!s.ran);
  s.ran = true;
  s.notify_systemd = options.notify_systemd;
  async::net::co_spawn(s.io, s.main_loop(options), [&s](std::exception_ptr e) {
    if (!e) return;
    async::log_exception("the worker", e);
    s.failed = true;
    // Wind everything down: nothing is left to wait for it.
    s.begin_stop();
    s.abandon.set();
    if (s.signals) {
      boost::system::error_code ignored;
      s.signals->cancel(ignored);
    }
  });
  if (options.notify_systemd) {  // WATCHDOG=1 and STATUS= from this loop, under systemd only
    async::start_systemd_notifier(s.io.get_executor(), s.clock, s.stop, [&s] {
      return fmt::format("{} tiles rendered, {} submitted, {} in hand", s.tiles_rendered.get(), s.tiles_submitted.get(),
                         s.in_hand.count());
    });
  }
  s.io.run();
  s.pool.join();
  return !s.failed;
}

void Worker::request_stop() {
  Impl* impl = impl_.get();
  async::net::post(impl->io, [impl] { impl->begin_stop(); });
}

WorkerStats Worker::stats() const {
  const Impl& s = *impl_;
  WorkerStats stats;
  stats.started = s.started.load();
  stats.stopping = s.stopping.load();
  stats.collector_finished = s.collector_finished.load();
  stats.stopped_idle = s.stopped_idle.load();
  stats.stopped_runtime = s.stopped_runtime.load();
  stats.tiles_rendered = s.tiles_rendered.get();
  stats.tiles_submitted = s.tiles_submitted.get();
  stats.tiles_dropped = s.tiles_dropped.get();
  stats.tiles_rejected = s.tiles_rejected.get();
  stats.tiles_abandoned = s.tiles_abandoned.get();
  stats.submit_retries = s.submit_retries.get();
  stats.lease_failures = s.lease_failures.get();
  stats.leases_dropped = s.leases_dropped.get();
  stats.upload_leases = s.upload_leases.get();
  stats.scenes_fetched = s.scenes_fetched.get();
  stats.scenes_rejected = s.scenes_rejected.get();
  stats.tiles_held = s.tiles_held.get();
  stats.tiles_in_hand = s.in_hand.count();
  stats.tiles_in_hand_peak = s.in_hand.peak();
  stats.ack_ms = s.ack_ms.get();
  stats.in_hand_wait_ms = s.in_hand_wait_ms.get();
  return stats;
}

const WorkerConfig& Worker::config() const { return impl_->config; }

int run_worker(const WorkerConfig& config) {
  try {
    auto worker = Worker::create(config);
    if (!worker) {
      for (const util::Error& problem : worker.error()) {
        util::log_error("worker configuration: {}", problem.to_string());
      }
      return 2;
    }
    return worker.value()->run({.stop_on_signals = true, .notify_systemd = true}) ? 0 : 1;
  } catch (const std::exception& e) {
    util::log_error("worker: {}", e.what());
    return 1;
  }
}

}  // namespace dtraced::worker
