// dtraced::http client: one HTTP/1.1 exchange per TCP connection, as a coroutine or blocking.
//
// Owns: base URL parsing (http://host[:port] and nothing else), and one exchange with a deadline
// on each step: resolving the host and connecting (connect timeout, both together), writing the
// request (write timeout), and reading the whole response (read timeout, counted from the end of
// the write), with a size limit on the response header and body. Expected network failures
// (refused, unreachable, reset, a deadline passed, an answer too large or not HTTP) come back as a
// ClientResult with a kind and a message naming the peer; they never throw. Any HTTP status is a
// successful exchange: interpreting 4xx/5xx is the caller's business.
// Every request stands alone (Connection: close): no pooling and no retries here; the worker and
// the CLI own their retry policies. Every deadline here bounds a socket operation, so it is real
// time (not the daemons' injected util::Clock): a test's clock cannot make the kernel faster.
//
// Threading: request() runs entirely on the executor of the coroutine that awaits it; concurrent
// requests share nothing. If that coroutine is cancelled, the exchange ends with kCancelled (or the
// next co_await in the caller throws operation_aborted, as Asio does). request_sync() blocks the
// calling thread on a private io_context: for CLI verbs, never on an event loop thread.
// parse_base_url() is stateless.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include <boost/asio/awaitable.hpp>

#include "http/types.h"
#include "util/result.h"

namespace dtraced::http {

inline constexpr std::size_t kMaxUrlBytes = 2048;
inline constexpr std::uint32_t kMaxResponseHeaderBytes = 64 * 1024;

// Where a server listens: host is a DNS name, an IPv4 address or an IPv6 address (no brackets).
struct Url {
  std::string host;
  std::uint16_t port = 80;

  std::string to_string() const;    // "http://host:port" ("http://[::1]:7878" for IPv6)
  std::string host_header() const;  // "host:port", for the Host field
};

// Parses "http://HOST[:PORT][/]" (scheme case-insensitive, port 1-65535, default 80). Anything
// else (https, user info, a path, a query, a fragment, spaces, an empty or malformed host or port,
// more than kMaxUrlBytes) is rejected with a message that says why.
util::Result<Url> parse_base_url(std::string_view text);

struct ClientTimeouts {
  std::chrono::milliseconds connect{5'000};  // resolve and TCP connect
  std::chrono::milliseconds write{30'000};   // the whole request
  std::chrono::milliseconds read{30'000};    // from the end of the write to the end of the body
};

// to_string follows this order.
enum class ClientError {
  kNone,
  kConnect,    // name not resolved, connection refused or unreachable: the server never saw it
  kTimeout,    // a deadline passed (the message says which step)
  kTooLarge,   // response header over kMaxResponseHeaderBytes or body over the caller's limit
  kProtocol,   // the answer is not valid HTTP
  kIo,         // the connection broke or closed before a complete response
  kCancelled,  // the awaiting coroutine was cancelled
};

std::string_view to_string(ClientError error);

struct ClientResult {
  ClientError error = ClientError::kNone;
  std::string message;  // empty when ok()
  Response response;    // the server's answer when ok(): status, header fields, body

  bool ok() const { return error == ClientError::kNone; }
};

// Sends `req` to `url` and reads the answer. Sets Host, Connection: close, Content-Length and a
// User-Agent (unless present); the caller sets the method, target, body and any other field
// (Authorization, Content-Type).
boost::asio::awaitable<ClientResult> request(Url url, Request req, ClientTimeouts timeouts,
                                             std::uint64_t max_response_body);

// The same exchange on a private io_context, blocking the calling thread until it is over.
ClientResult request_sync(const Url& url, Request req, const ClientTimeouts& timeouts, std::uint64_t max_response_body);

}  // namespace dtraced::http
