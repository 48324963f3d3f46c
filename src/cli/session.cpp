#include "cli/session.h"

#include <random>
#include <thread>
#include <utility>

#include <boost/beast/http/field.hpp>

#include "util/file.h"
#include "util/token_file.h"

namespace dtraced::cli {

std::string format_seconds(double s) {
  if (s < 60) return fmt::format("{:.1f}s", s);
  if (s < 3600) return fmt::format("{}m{:02}s", int(s) / 60, int(s) % 60);
  return fmt::format("{}h{:02}m", int(s) / 3600, (int(s) % 3600) / 60);
}

// The CA certificate(s) in `path`, checked to be usable; errors name the file.
util::Result<http::ClientTls> read_ca_file(const std::string& path) {
  constexpr std::uint64_t kMaxCaFileBytes = 1 << 20;
  util::Result<std::string> pem = util::read_file_limited(path, kMaxCaFileBytes);
  if (!pem) return pem.error();
  http::ClientTls tls;
  tls.ca_pem = std::move(pem).value();
  tls.ca_source = path;
  if (util::Status usable = http::check_client_tls(tls); !usable) return usable.error();
  return tls;
}

bool Session::init(const ClientArgs& args) {
  auto url = http::parse_base_url(args.collector);
  if (!url) {
    fmt::print(stderr, "--collector: {}\n", url.error().message);
    return false;
  }
  url_ = *url;
  http::ClientOptions options;
  if (url_.tls) {
    if (args.ca_file.empty()) {
      fmt::print(stderr,
                 "--ca-file: required for an https:// collector (its CA certificate: tls/ca.pem in the "
                 "collector's state directory)\n");
      return false;
    }
    auto tls = read_ca_file(args.ca_file);
    if (!tls) {
      fmt::print(stderr, "--ca-file: {}\n", tls.error().to_string());
      return false;
    }
    options.tls = std::move(tls).value();
  }
  if (!args.token_file.empty()) {
    auto token = read_token_file(args.token_file);
    if (!token) {
      fmt::print(stderr, "{}\n", token.error().to_string());
      return false;
    }
    token_ = std::move(token).value();
  }
  options.timeouts.read = options.timeouts.write = std::chrono::milliseconds(args.timeout_ms);
  // One verb's requests follow each other closely (a --wait polls every half second): one
  // kept-alive connection carries them all.
  options.max_idle_connections = 1;
  client_ = std::make_unique<http::SyncClient>(std::move(options));
  retry_for(std::chrono::milliseconds(args.timeout_ms), fmt::format("--timeout-ms {}", args.timeout_ms));
  return true;
}

void Session::retry_for(std::chrono::milliseconds budget, std::string flag) {
  retry_ = RetryPolicy(budget, std::random_device{}());
  retry_flag_ = std::move(flag);
}

std::optional<http::Response> Session::call(http::Verb verb, const std::string& target, const std::string& body,
                                            std::uint64_t max_body) {
  while (true) {
    http::Request req =
        http::make_request(verb, target, body, verb == http::Verb::post ? http::kJsonContentType : std::string_view{});
    if (!token_.empty()) req.set(boost::beast::http::field::authorization, "Bearer " + token_);
    http::ClientResult r = client_->request(url_, std::move(req), max_body);
    if (r.ok() && r.response.result_int() >= 200 && r.response.result_int() < 300) {
      retry_.succeeded();
      return std::move(r.response);
    }
    const Failure failure = classify(r, verb, target);
    const auto now = std::chrono::steady_clock::now();
    const std::optional<std::chrono::milliseconds> wait = retry_.next_wait(failure, now);
    if (!wait) {
      fmt::print(stderr, "{}\n", failure.reason);
      if (failure.retryable && retry_.failures() > 1) {
        fmt::print(stderr, "giving up on {} after {} of retries ({})\n", target,
                   format_seconds(retry_.spent(now).count() / 1000.0), retry_flag_);
      }
      return std::nullopt;
    }
    fmt::print(stderr, "{}, retrying in {} ms\n", failure.reason, wait->count());
    std::this_thread::sleep_for(*wait);
  }
}

}  // namespace dtraced::cli
