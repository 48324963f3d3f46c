// dtraced::http client: HTTP/1.1 over TCP or TLS, with kept-alive connections, as a coroutine
// or blocking.
//
// Owns: base URL parsing (http://host[:port] and https://host[:port]), the client side of TLS
// (an OpenSSL context built once per Client from the collector's CA: TLS 1.2 at least, ECDHE
// only, no compression, no renegotiation; SNI for DNS names; the server's certificate must chain
// to that CA and name the URL's host), a pool of kept-alive connections per Client, and one
// exchange with a deadline on each step: resolving the host and connecting (connect timeout,
// both together), the TLS handshake (handshake timeout), writing the request (write timeout),
// and reading the whole response (read timeout, counted from the end of the write), with a size
// limit on the response header and body. Expected network failures (refused, unreachable,
// reset, a deadline passed, a certificate the CA did not sign, an answer too large or not HTTP)
// come back as a ClientResult with a kind and a message naming the peer; they never throw. Any
// HTTP status is a successful exchange: interpreting 4xx/5xx is the caller's business.
//
// Keep-alive: a Client keeps up to max_idle_connections idle connections (across hosts), each
// for at most max_idle, each used for at most max_requests_per_connection requests (the last one
// says Connection: close). A request takes an idle connection to its (host, port, tls) or opens
// one, so N concurrent requests use at most N connections. A request that fails on a reused
// connection before any byte of the answer came back (the server closed it while idle) is sent
// again once on a fresh connection; nothing else is retried here: the worker and the CLI own
// their retry policies. Requests stay stateless: any may go on any connection.
// Every deadline here bounds a socket operation, so it is real time (not the daemons' injected
// util::Clock): a test's clock cannot make the kernel faster.
//
// Threading: a Client belongs to one executor (an io_context run by one thread, or a strand):
// request() and stats() only there; requests in flight at once each use their own connection.
// The Client must outlive its requests and be destroyed before its io_context. If the awaiting
// coroutine is cancelled, the exchange ends with kCancelled (or the next co_await in the caller
// throws operation_aborted, as Asio does) and its connection is closed. SyncClient blocks the
// calling thread on a private io_context: for CLI verbs, never on an event loop thread. The free
// request()/request_sync() make one exchange on a connection of their own (Connection: close).
// parse_base_url() and check_client_tls() are stateless.
#pragma once

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <boost/asio/any_io_executor.hpp>
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
  bool tls = false;  // https://

  std::string to_string() const;    // "http://host:port" ("https://[::1]:7878" for IPv6 over TLS)
  std::string host_header() const;  // "host:port", for the Host field
};

// Parses "http://HOST[:PORT][/]" and "https://HOST[:PORT][/]" (scheme case-insensitive, port
// 1-65535, default 80 for http and 443 for https). Anything else (another scheme, user info, a
// path, a query, a fragment, spaces, an empty or malformed host or port, more than kMaxUrlBytes)
// is rejected with a message that says why.
util::Result<Url> parse_base_url(std::string_view text);

struct ClientTimeouts {
  std::chrono::milliseconds connect{5'000};     // resolve and TCP connect
  std::chrono::milliseconds write{30'000};      // the whole request
  std::chrono::milliseconds read{30'000};       // from the end of the write to the end of the body
  std::chrono::milliseconds handshake{10'000};  // the TLS handshake, after the TCP connect
};

// What a client trusts for https:// URLs.
struct ClientTls {
  // The trust anchor: PEM certificate(s) of the CA that signed the server's certificate (the
  // collector's CA, tls/ca.pem in its state directory, or the operator's --tls-ca).
  std::string ca_pem;
  // Where ca_pem came from (a file name), named in errors; "" reads "the CA given".
  std::string ca_source;
  // Enrollment only, when ca_pem is empty: trust the CA certificate whose SHA-256 (of its DER
  // bytes) is this, if the server sends it in its chain; the chain must verify up to it and
  // name the host, exactly as with ca_pem.
  std::optional<std::array<std::uint8_t, 32>> ca_fingerprint;
};

// An empty Status when `tls` can make a TLS context: ca_pem parses as at least one certificate
// (or is empty with a fingerprint). Otherwise why not, naming ca_source.
util::Status check_client_tls(const ClientTls& tls);

// to_string follows this order.
enum class ClientError {
  kNone,
  kConnect,    // name not resolved, connection refused or unreachable: the server never saw it
  kTimeout,    // a deadline passed (the message says which step)
  kTooLarge,   // response header over kMaxResponseHeaderBytes or body over the caller's limit
  kProtocol,   // the answer is not valid HTTP
  kIo,         // the connection broke or closed before a complete response
  kCancelled,  // the awaiting coroutine was cancelled
  kTls,        // the TLS handshake failed: certificate not trusted, wrong name, not TLS, ...
};

std::string_view to_string(ClientError error);

struct ClientResult {
  ClientError error = ClientError::kNone;
  std::string message;  // empty when ok()
  Response response;    // the server's answer when ok(): status, header fields, body

  bool ok() const { return error == ClientError::kNone; }
};

struct ClientOptions {
  ClientTimeouts timeouts;
  std::optional<ClientTls> tls;                     // needed for https URLs (else a kConnect error saying so)
  std::size_t max_idle_connections = 8;             // kept idle at once by one Client; 0: none kept
  std::chrono::milliseconds max_idle{15'000};       // below the server's idle timeout (30 s by default)
  std::uint32_t max_requests_per_connection = 500;  // >= 1; 1: Connection: close on each
};

// Counters since construction; all read together.
struct ClientStats {
  std::uint64_t requests = 0;            // request() calls
  std::uint64_t connections_opened = 0;  // TCP connections connected (and TLS handshaken)
  std::uint64_t reuses = 0;              // exchanges sent on a kept-alive connection
  std::uint64_t retries = 0;             // sent again after a reused connection failed
  std::uint64_t tls_handshakes = 0;      // TLS handshakes completed
  std::uint64_t tls_failures = 0;        // TLS handshakes failed
  std::uint64_t idle_connections = 0;    // now
};

// A pool of kept-alive connections on one executor (see the top of this file).
class Client {
 public:
  // An https:// request fails with kTls when options.tls does not pass check_client_tls.
  Client(boost::asio::any_io_executor executor, ClientOptions options);
  ~Client();
  Client(const Client&) = delete;
  Client& operator=(const Client&) = delete;

  // Sends `req` to `url` and reads the answer. Sets Host, Connection, Content-Length and a
  // User-Agent (unless present); the caller sets the method, target, body and any other field
  // (Authorization, Content-Type). Await on the Client's executor.
  boost::asio::awaitable<ClientResult> request(Url url, Request req, std::uint64_t max_response_body);

  ClientStats stats() const;
  const ClientOptions& options() const;

  // Closes every idle connection now.
  void close_idle();

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

// Blocking: owns a private io_context and a Client, so successive calls reuse a connection. One
// thread at a time.
class SyncClient {
 public:
  explicit SyncClient(ClientOptions options);
  ~SyncClient();
  SyncClient(const SyncClient&) = delete;
  SyncClient& operator=(const SyncClient&) = delete;

  ClientResult request(const Url& url, Request req, std::uint64_t max_response_body);
  ClientStats stats() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// One exchange on a connection of its own (Connection: close), on the awaiting coroutine's
// executor; `tls` is needed for an https:// url.
boost::asio::awaitable<ClientResult> request(Url url, Request req, ClientTimeouts timeouts,
                                             std::uint64_t max_response_body,
                                             std::optional<ClientTls> tls = std::nullopt);

// The same exchange on a private io_context, blocking the calling thread until it is over.
ClientResult request_sync(const Url& url, Request req, const ClientTimeouts& timeouts, std::uint64_t max_response_body,
                          const std::optional<ClientTls>& tls = std::nullopt);

}  // namespace dtraced::http
