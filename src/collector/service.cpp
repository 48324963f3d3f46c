#include "collector/service.h"

#include <signal.h>

#include <algorithm>
#include <exception>
#include <filesystem>
#include <optional>
#include <stdexcept>
#include <system_error>
#include <utility>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/ip/address.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/signal_set.hpp>
#include <boost/asio/ssl/context.hpp>
#include <fmt/format.h>

#include "async/systemd_notifier.h"
#include "collector/context.h"
#include "collector/restore.h"
#include "collector/router.h"
#include "collector/stop.h"
#include "collector/systemd_status.h"
#include "collector/tls_setup.h"
#include "util/log.h"
#include "util/sd_notify.h"

namespace dtraced::collector {

namespace net = async::net;

util::Result<std::unique_ptr<Collector>, util::Errors> Collector::create(CollectorConfig config,
                                                                         const util::Clock& clock) {
  util::Errors errors = check_collector_config(config);
  if (!errors.empty()) return errors;
  return std::unique_ptr<Collector>(new Collector(std::make_unique<Context>(std::move(config), clock)));
}

Collector::Collector(std::unique_ptr<Context> context) : context_(std::move(context)) {}
Collector::~Collector() = default;

util::Status Collector::open() { return open_collector(*context_); }

util::Status Collector::listen() {
  Context& c = *context_;
  if (c.stopping) return {};
  if (!c.server) {
    if (auto bound = bind(); !bound) return bound;
  }
  if (!c.opened || ready_) return {};  // bound early, for a new state directory: open() comes next
  ready_ = true;
  util::log_info("collector: listening on {} port {} ({}); images go to {}", c.config.listen_address, c.server->port(),
                 c.config.tls.enabled ? "https" : "plain http", c.output_dir);
  util::sd_notify_state("READY=1");
  // Under systemd: WATCHDOG=1 and STATUS= from this loop until the stop begins.
  async::start_systemd_notifier(c.ioc->get_executor(), c.clock, *c.stop_begun, [&c] {
    WorkerCounts workers;
    for (const WorkerView& w : c.workers.list(c.clock.now())) ++(w.quiet ? workers.quiet : workers.active);
    return systemd_status(c.metrics(), workers);
  });
  return {};
}

util::Status Collector::bind() {
  Context& c = *context_;
  http::ServerLimits limits = c.config.limits;
  // One body limit for the server: the largest of the routes' (each route checks its own).
  limits.max_body_bytes =
      std::min<std::uint64_t>(c.config.limits.max_body_bytes,
                              std::max<std::uint64_t>(protocol::kMaxJobSubmitBytes, protocol::kMaxTilePayloadBytes));
  boost::system::error_code ec;
  const auto address = net::ip::make_address(c.config.listen_address, ec);
  if (ec) return util::Error(fmt::format("listen_address '{}': {}", c.config.listen_address, ec.message()));
  // HTTPS: the private CA (or the operator's files) and this start's server certificate.
  std::shared_ptr<net::ssl::context> tls;
  if (c.config.tls.enabled) {
    auto setup = prepare_tls(c.config.tls, c.config.state_dir, c.config.listen_address, c.clock.unix_seconds());
    if (!setup) return util::Error(fmt::format("TLS: {}", setup.error().to_string()));
    tls = setup->context;
    c.ca_pem = setup->ca_pem;
    c.ca_fingerprint = setup->ca_fingerprint;
    util::log_info("collector: {}", setup->description);
  }
  c.server = std::make_unique<http::Server>(
      c.ioc->get_executor(), address, c.config.port, limits,
      [&c](http::Request req) { return handle_request(c, std::move(req)); },
      [&c](const http::Request& head, std::uint64_t& body_limit) { return check_request_header(c, head, body_limit); },
      [&c](const http::Request& head) { return is_authenticated(c, head); }, c.clock, std::move(tls));
  ec = c.server->start();
  if (ec) {
    c.server.reset();
    return util::Error(
        fmt::format("cannot listen on {} port {}: {}", c.config.listen_address, c.config.port, ec.message()));
  }
  return {};
}

int Collector::run() {
  context_->ioc->restart();
  context_->ioc->run();
  return context_->exit_code.value_or(0);
}

void Collector::stop() {
  net::post(*context_->ioc, [c = context_.get()] { begin_stop(*c, 0); });
}

std::uint16_t Collector::port() const { return context_->server ? context_->server->port() : 0; }

net::awaitable<http::Response> Collector::handle(http::Request req) {
  return handle_request(*context_, std::move(req));
}

http::Response Collector::handle_sync(http::Request req) {
  std::optional<http::Response> answer;
  std::exception_ptr failure;
  net::co_spawn(*context_->ioc, handle_request(*context_, std::move(req)),
                [&](std::exception_ptr error, http::Response res) {
                  failure = error;
                  answer = std::move(res);
                });
  run_until_idle();
  if (failure) std::rethrow_exception(failure);
  if (!answer) throw std::runtime_error("handle_sync: the request did not complete");
  answer->prepare_payload();
  return std::move(*answer);
}

void Collector::run_until_idle() {
  context_->ioc->restart();
  context_->ioc->run();
}

void Collector::set_certificate_authority(std::string ca_pem, std::optional<std::array<std::uint8_t, 32>> fingerprint) {
  context_->ca_pem = std::move(ca_pem);
  context_->ca_fingerprint = fingerprint;
}

MetricsSnapshot Collector::metrics() const { return context_->metrics(); }

net::io_context& Collector::io_context() { return *context_->ioc; }

int run_collector(const CollectorConfig& config) {
  auto created = Collector::create(config);
  if (!created) {
    util::log_error("collector: cannot start: configuration: {}", util::to_string(created.error()));
    return 1;
  }
  Collector& collector = *created.value();
  // An existing state directory is locked and opened before the port is taken, so a second
  // collector on it is refused for that, whatever its port. A new one is created only once the
  // port is bound, so a port in use leaves no empty state directory behind.
  std::error_code ec;
  if (!std::filesystem::exists(config.state_dir, ec)) {
    if (auto bound = collector.listen(); !bound) {
      util::log_error("collector: cannot start: {}", bound.error().to_string());
      return 1;
    }
  }
  if (auto opened = collector.open(); !opened) {
    util::log_error("collector: cannot start: {}", opened.error().to_string());
    return 1;
  }
  if (auto listening = collector.listen(); !listening) {
    util::log_error("collector: cannot start: {}", listening.error().to_string());
    return 1;
  }
  // Signals are caught on the loop; the first one starts the graceful stop.
  net::signal_set signals(collector.io_context(), SIGINT, SIGTERM);
  signals.async_wait([&collector](const boost::system::error_code& ec, int signal_number) {
    if (ec) return;
    util::log_info("collector: signal {} received", signal_number);
    collector.stop();
  });
  return collector.run();
}

}  // namespace dtraced::collector
