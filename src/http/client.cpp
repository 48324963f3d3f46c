#include "http/client.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <exception>
#include <memory>
#include <tuple>
#include <utility>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/beast/core/error.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/error.hpp>
#include <boost/beast/http/field.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/beast/http/write.hpp>
#include <boost/system/system_error.hpp>
#include <fmt/format.h>

#include "async/async.h"
#include "http/names.h"

namespace dtraced::http {
namespace {

using namespace names;
// Every deadline here is a socket deadline (resolving, connecting, writing, reading): real time.
using RealClock = std::chrono::steady_clock;

constexpr std::string_view kScheme = "http://";
constexpr std::size_t kMaxHostBytes = 253;  // the longest DNS name
constexpr std::string_view kUserAgent = "dtraced";

ClientResult failure(ClientError error, std::string message) {
  ClientResult result;
  result.error = error;
  result.message = std::move(message);
  return result;
}

bool starts_with_icase(std::string_view text, std::string_view prefix) {
  if (text.size() < prefix.size()) return false;
  for (std::size_t i = 0; i < prefix.size(); ++i) {
    if (std::tolower(static_cast<unsigned char>(text[i])) != prefix[i]) return false;
  }
  return true;
}

bool is_host_name_char(char c) {
  return std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '.' || c == '_';
}

// A lookup that may outlive the request that started it: getaddrinfo cannot be interrupted, so on
// timeout the request abandons it and the lookup's own handler keeps this alive until it ends.
struct PendingResolve {
  explicit PendingResolve(const net::any_io_executor& executor) : resolver(executor), wake(executor) {}

  tcp::resolver resolver;
  net::steady_timer wake;  // the waiting request sleeps on it; the lookup's handler cancels it
  bool done = false;
  error_code ec;
  std::vector<tcp::endpoint> endpoints;
};

// Fills `endpoints` for `url` by `deadline`, or returns why it could not.
net::awaitable<std::optional<ClientResult>> resolve(const Url& url, RealClock::time_point deadline,
                                                    std::vector<tcp::endpoint>& endpoints) {
  error_code ec;
  const net::ip::address address = net::ip::make_address(url.host, ec);
  if (!ec) {
    endpoints.emplace_back(address, url.port);
    co_return std::nullopt;
  }
  auto pending = std::make_shared<PendingResolve>(co_await net::this_coro::executor);
  pending->wake.expires_at(deadline);
  pending->resolver.async_resolve(url.host, std::to_string(url.port),
                                  [pending](const error_code& ec, const tcp::resolver::results_type& results) {
                                    pending->done = true;
                                    pending->ec = ec;
                                    for (const auto& entry : results) pending->endpoints.push_back(entry.endpoint());
                                    pending->wake.cancel();
                                  });
  co_await pending->wake.async_wait(kAwaitTuple);
  if (!pending->done) {
    pending->resolver.cancel();
    if ((co_await net::this_coro::cancellation_state).cancelled() != net::cancellation_type::none) {
      co_return failure(ClientError::kCancelled, fmt::format("resolving {} was cancelled", url.host));
    }
    co_return failure(ClientError::kTimeout, fmt::format("resolving {} timed out", url.host));
  }
  if (pending->ec || pending->endpoints.empty()) {
    co_return failure(ClientError::kConnect, fmt::format("cannot resolve {}: {}", url.host,
                                                         pending->ec ? pending->ec.message() : "no address"));
  }
  endpoints = std::move(pending->endpoints);
  co_return std::nullopt;
}

ClientResult read_failure(const error_code& ec, const std::string& where, const ClientTimeouts& timeouts,
                          std::uint64_t max_response_body) {
  if (ec == beast::error::timeout) {
    return failure(ClientError::kTimeout,
                   fmt::format("no complete response from {} within {} ms", where, timeouts.read.count()));
  }
  if (ec == bhttp::error::body_limit) {
    return failure(ClientError::kTooLarge,
                   fmt::format("response body from {} exceeds the limit of {} bytes", where, max_response_body));
  }
  if (ec == bhttp::error::header_limit || ec == bhttp::error::buffer_overflow) {
    return failure(ClientError::kTooLarge, fmt::format("response header from {} exceeds the limit of {} bytes", where,
                                                       kMaxResponseHeaderBytes));
  }
  if (ec == net::error::operation_aborted) {
    return failure(ClientError::kCancelled, fmt::format("request to {} was cancelled", where));
  }
  if (ec == bhttp::error::end_of_stream || ec == bhttp::error::partial_message) {
    return failure(ClientError::kIo, fmt::format("{} closed the connection before a complete response", where));
  }
  if (ec.category() == bhttp::make_error_code(bhttp::error::bad_version).category()) {
    return failure(ClientError::kProtocol, fmt::format("invalid HTTP response from {}: {}", where, ec.message()));
  }
  return failure(ClientError::kIo, fmt::format("reading the response from {} failed: {}", where, ec.message()));
}

net::awaitable<ClientResult> exchange(const Url& url, Request req, const ClientTimeouts& timeouts,
                                      std::uint64_t max_response_body) {
  const std::string where = url.to_string();
  const auto connect_deadline = RealClock::now() + timeouts.connect;

  std::vector<tcp::endpoint> endpoints;
  if (std::optional<ClientResult> failed = co_await resolve(url, connect_deadline, endpoints)) co_return *failed;

  beast::tcp_stream stream(co_await net::this_coro::executor);
  stream.expires_at(connect_deadline);
  auto [connect_ec, endpoint] = co_await stream.async_connect(endpoints, kAwaitTuple);
  if (connect_ec == beast::error::timeout) {
    co_return failure(ClientError::kTimeout,
                      fmt::format("connecting to {} timed out after {} ms", where, timeouts.connect.count()));
  }
  if (connect_ec == net::error::operation_aborted) {
    co_return failure(ClientError::kCancelled, fmt::format("connecting to {} was cancelled", where));
  }
  if (connect_ec) {
    co_return failure(ClientError::kConnect, fmt::format("cannot connect to {}: {}", where, connect_ec.message()));
  }
  error_code ignored;
  stream.socket().set_option(tcp::no_delay(true), ignored);

  const bool head = req.method() == Verb::head;
  req.version(11);
  req.set(bhttp::field::host, url.host_header());
  if (req.count(bhttp::field::user_agent) == 0) req.set(bhttp::field::user_agent, kUserAgent);
  req.keep_alive(false);
  req.prepare_payload();

  stream.expires_after(timeouts.write);
  auto [write_ec, written] = co_await bhttp::async_write(stream, req, kAwaitTuple);

  // Read even after a failed write: a server may answer before taking the whole body (413) and
  // close; that answer is worth more than the write error.
  bhttp::response_parser<bhttp::string_body> parser;
  parser.header_limit(kMaxResponseHeaderBytes);
  parser.body_limit(max_response_body);
  parser.skip(head);  // the answer to HEAD announces a body it does not carry
  beast::flat_buffer buffer;
  stream.expires_after(timeouts.read);
  auto [read_ec, read] = co_await bhttp::async_read(stream, buffer, parser, kAwaitTuple);
  if (read_ec && write_ec) {
    if (write_ec == beast::error::timeout) {
      co_return failure(ClientError::kTimeout,
                        fmt::format("sending the request to {} timed out after {} ms", where, timeouts.write.count()));
    }
    if (write_ec == net::error::operation_aborted) {
      co_return failure(ClientError::kCancelled, fmt::format("request to {} was cancelled", where));
    }
    co_return failure(ClientError::kIo, fmt::format("sending the request to {} failed: {}", where, write_ec.message()));
  }
  if (read_ec) co_return read_failure(read_ec, where, timeouts, max_response_body);

  stream.socket().shutdown(tcp::socket::shutdown_both, ignored);
  ClientResult result;
  result.response = parser.release();
  co_return result;
}

}  // namespace

std::string Url::to_string() const { return fmt::format("{}{}", kScheme, host_header()); }

std::string Url::host_header() const {
  if (host.find(':') != std::string::npos) return fmt::format("[{}]:{}", host, port);
  return fmt::format("{}:{}", host, port);
}

util::Result<Url> parse_base_url(std::string_view text) {
  if (text.size() > kMaxUrlBytes) return util::Error(fmt::format("URL is longer than {} bytes", kMaxUrlBytes));
  for (const char c : text) {
    const auto u = static_cast<unsigned char>(c);
    if (u <= ' ' || u >= 0x7f) return util::Error("URL contains a space, a control character or a non-ASCII byte");
  }
  if (!starts_with_icase(text, kScheme)) {
    return util::Error(starts_with_icase(text, "https://")
                           ? "https is not supported: dtraced speaks plain HTTP (put a TLS proxy in front of it)"
                           : fmt::format("URL '{}' must start with http://", text));
  }
  std::string_view rest = text.substr(kScheme.size());
  if (!rest.empty() && rest.back() == '/') rest.remove_suffix(1);
  if (rest.find_first_of("/?#@") != std::string_view::npos) {
    return util::Error(
        fmt::format("URL '{}' must be http://host[:port], without a path, query, fragment or user name", text));
  }

  Url url;
  std::string_view port_part;
  if (!rest.empty() && rest.front() == '[') {
    const std::size_t close = rest.find(']');
    error_code ec;
    if (close != std::string_view::npos) net::ip::make_address_v6(rest.substr(1, close - 1), ec);
    if (close == std::string_view::npos || ec)
      return util::Error(fmt::format("URL '{}' has a malformed IPv6 address", text));
    url.host = std::string(rest.substr(1, close - 1));
    port_part = rest.substr(close + 1);
  } else {
    const std::size_t colon = rest.find(':');
    const std::string_view host = rest.substr(0, colon);
    if (host.empty() || host.size() > kMaxHostBytes ||
        !std::all_of(host.begin(), host.end(), [](char c) { return is_host_name_char(c); })) {
      return util::Error(fmt::format("URL '{}' has no valid host name", text));
    }
    url.host = std::string(host);
    if (colon != std::string_view::npos) port_part = rest.substr(colon);
  }

  if (!port_part.empty()) {
    const std::string_view digits = port_part.substr(1);
    unsigned value = 0;
    const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), value);
    if (port_part.front() != ':' || digits.empty() || digits.size() > 5 || ec != std::errc() ||
        end != digits.data() + digits.size() || value == 0 || value > 65535) {
      return util::Error(fmt::format("URL '{}' has no valid port (1-65535)", text));
    }
    url.port = static_cast<std::uint16_t>(value);
  }
  return url;
}

std::string_view to_string(ClientError error) {
  // The enum's order.
  constexpr std::string_view kNames[] = {"none", "connect", "timeout", "too_large", "protocol", "io", "cancelled"};
  const auto i = static_cast<std::size_t>(error);
  return i < std::size(kNames) ? kNames[i] : "unknown";
}

net::awaitable<ClientResult> request(Url url, Request req, ClientTimeouts timeouts, std::uint64_t max_response_body) {
  try {
    co_return co_await exchange(url, std::move(req), timeouts, max_response_body);
  } catch (const boost::system::system_error& e) {
    // Asio throws this from a co_await once the awaiting coroutine has been cancelled.
    if (e.code() != net::error::operation_aborted) throw;
  }
  co_return failure(ClientError::kCancelled, fmt::format("request to {} was cancelled", url.to_string()));
}

ClientResult request_sync(const Url& url, Request req, const ClientTimeouts& timeouts,
                          std::uint64_t max_response_body) {
  net::io_context io;
  ClientResult result;
  std::exception_ptr error;
  net::co_spawn(io, request(url, std::move(req), timeouts, max_response_body),
                [&](std::exception_ptr e, ClientResult r) {
                  error = e;
                  result = std::move(r);
                  io.stop();  // do not wait for an abandoned name lookup
                });
  io.run();
  if (error) std::rethrow_exception(error);
  return result;
}

}  // namespace dtraced::http
