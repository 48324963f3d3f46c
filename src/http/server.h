// dtraced::http server: HTTP/1.1 over TCP, or over TLS, with Boost.Beast and C++20 coroutines.
//
// Owns: the listening socket, one coroutine per connection, and every limit a connection is held
// to. A session waits for the first byte of a request (the idle deadline between requests, the
// read deadline on a fresh connection), reads the whole request before the read deadline with the
// header and body size limits (the body's lowered per request by an optional header check, which
// may also answer before the body is read), hands it to the handler, writes the answer before the write
// deadline, and keeps the connection for the next request when the client and the handler allow
// it. Problems the server finds itself are answered with the JSON error shape of types.h and the
// connection is closed:
//   malformed request -> 400, body over the limit -> 413, header over the limit -> 431,
//   handler threw -> 500 (logged; the message does not leak the exception),
//   max_connections sessions already open -> 503 (with Retry-After),
//   a large answer while others wait for slow readers past max_held_response_bytes -> 503.
// A request still incomplete at its read deadline is dropped without an answer: its client is
// gone or hostile. Before closing after a last response the server half-closes and drains what
// the peer still sends (bounded), so the peer reads the answer instead of a reset.
//
// TLS (a context from http/tls_server.h given to the constructor): every connection's first bytes
// decide (Beast's detect_ssl, under the deadline of a fresh connection's first byte). A TLS
// ClientHello is answered with a handshake held to handshake_timeout (and to
// unauthenticated_timeout while unauthenticated); then the same session code as for plain HTTP
// runs over the encrypted stream, with every limit, deadline, eviction, linger and stop rule
// above and below. Anything else is answered, in plain HTTP, 400 "this port speaks HTTPS: use
// https://HOST:PORT", and closed (counted plain_on_tls). A failed handshake (a client certificate
// the client CA does not vouch for or that expired, a protocol below TLS 1.2, a timeout) closes
// the connection and is logged, at most one line per kHandshakeLogInterval on the clock, with the
// peer, OpenSSL's reason and the number of failures held back since the last line. A verified
// client certificate's subject CN is stamped on each request as kClientCertHeader. Before closing
// after a last response the server sends close_notify (waiting a short bound for the peer's),
// then lingers as for plain HTTP.
// Renegotiation is refused (the context's options): a client that tries loses its connection.
//
// Keep-alive: a connection serves up to max_requests_per_connection requests (the answer to the
// last says Connection: close). A connection waiting for its next request is idle; when one goes
// idle while max_idle_connections others are, the one idle the longest is closed, and so is it
// when a new connection finds every slot taken (after the unauthenticated ones below): an idle
// client opens another connection when it needs one, so kept-alive connections never lock
// newcomers out.
//
// Unauthenticated peers cannot starve authenticated ones. With an `authenticated` predicate, a
// connection is unauthenticated from accept until a request's header satisfies it; until then it
// is held to unauthenticated_timeout (for its first request's header and between requests), and
// when every slot is taken a new connection evicts the oldest unauthenticated one that is waiting
// for bytes (idle or mid-header: a slowloris) instead of being refused. Authenticated connections
// are never evicted, so a client with a valid token always finds room unless max_connections
// authenticated connections are open. There is no per-address cap: farms behind one NAT address
// (and every test on loopback) would hit it first. Without a predicate every connection counts as
// authenticated and the cap alone applies.
//
// Large answers (kLargeResponseBytes and over) are counted from the handler's return until
// written or failed; a slow reader holds its answer up to write_timeout. One that would take the
// total past max_held_response_bytes gets 503 with Retry-After instead (unless none is held, so
// an answer over the cap alone can still be sent), which bounds the memory slow readers pin.
//
// Shutdown is graceful: stop() closes the listener and every idle connection at once, lets
// requests in flight (being read, handled or written) finish until its deadline, answering them
// with Connection: close, then cancels the handlers still running and closes their sockets.
//
// Time: the server's own decisions (stop()'s grace and the unwind bound after it, the pause after
// a failed accept) read and sleep on the injected util::Clock, so a test decides when a grace
// ends. Socket deadlines (read, write, keep-alive and linger, Beast's expires_after on each
// stream) stay in real time: they bound what the kernel and the peer do, not what the server
// decides.
//
// Threading: the server, its sessions and the handler all run on the executor given to the
// constructor, which must not run two handlers at once (an io_context run by one thread, or a
// strand); so the handler may use state owned by that executor without locks, and must not block
// it. Call start() before the executor runs or on it; await stop() on it. port() and metrics() may
// be called from any thread. The clock and the io_context must outlive the Server. Destroying the Server without
// stop() closes everything abruptly; coroutines still pending keep the internals alive until they
// end or the io_context is destroyed.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string_view>

#include <boost/asio/any_io_executor.hpp>
#include <boost/asio/awaitable.hpp>
#include <boost/asio/ip/address.hpp>
#include <boost/system/error_code.hpp>

#include "http/types.h"
#include "util/clock.h"

namespace boost::asio::ssl {
class context;
}  // namespace boost::asio::ssl

namespace dtraced::http {

// Set by the server on every request it hands to the header check and the handler: the peer's
// address (e.g. "192.0.2.7", "::1"); a value the client sent under this name is replaced.
inline constexpr std::string_view kPeerHeader = "X-Dtraced-Peer";
// Set on TLS connections whose client presented a certificate the server verified: its subject
// common name. A value the client sent under this name is always removed.
inline constexpr std::string_view kClientCertHeader = "X-Dtraced-Client-Cert";
// Failed TLS handshakes are logged at most once per this interval (on the server's clock).
inline constexpr std::chrono::seconds kHandshakeLogInterval{10};

struct ServerLimits {
  std::uint32_t max_header_bytes = 8 * 1024;  // request line and header fields together
  std::uint64_t max_body_bytes = 64ull << 20;
  std::chrono::milliseconds read_timeout{10'000};            // first byte to end of body
  std::chrono::milliseconds write_timeout{30'000};           // one whole response
  std::chrono::milliseconds idle_keepalive_timeout{30'000};  // between requests on a connection
  std::size_t max_connections = 256;                         // open sessions; more get 503
  // Until a request authenticates (see the top of this file): the first request's header
  // deadline and the idle deadline between requests, each capped by the two above.
  std::chrono::milliseconds unauthenticated_timeout{5'000};
  std::uint64_t max_held_response_bytes = 256ull << 20;  // large answers waiting to be written
  // TLS only: the handshake, from its first bytes to its end (capped by unauthenticated_timeout
  // while unauthenticated, like the header).
  std::chrono::milliseconds handshake_timeout{10'000};
  std::size_t max_idle_connections = 256;            // keep-alive connections between requests
  std::uint32_t max_requests_per_connection = 1000;  // then the answer says Connection: close
};

// Answers of this size and over count against ServerLimits::max_held_response_bytes; smaller
// ones are bounded by max_connections alone.
inline constexpr std::uint64_t kLargeResponseBytes = 64 * 1024;

// Counters since start(); a snapshot, all fields read together.
struct ServerMetrics {
  std::uint64_t requests = 0;  // responses sent, the server's own 4xx and 5xx (and 503s) included
  std::uint64_t responses_4xx = 0;
  std::uint64_t responses_5xx = 0;
  std::uint64_t read_timeouts = 0;             // connections dropped at the read deadline
  std::uint64_t rejected_connections = 0;      // connections over max_connections
  std::uint64_t open_connections = 0;          // sessions open now (a gauge)
  std::uint64_t evicted_connections = 0;       // unauthenticated connections closed to make room
  std::uint64_t held_response_bytes = 0;       // large answers not yet written (a gauge)
  std::uint64_t refused_large_responses = 0;   // large answers replaced by 503 over the cap
  std::uint64_t tls_handshakes = 0;            // completed
  std::uint64_t tls_handshake_failures = 0;    // failed or timed out (the connection was closed)
  std::uint64_t plain_on_tls = 0;              // plain bytes on a TLS server: answered 400, closed
  std::uint64_t keepalive_reuses = 0;          // requests that were not the first on their connection
  std::uint64_t evicted_idle_connections = 0;  // closed over max_idle_connections
};

class Server {
 public:
  // Called once per request on the server's executor. It may co_await; an exception becomes a
  // 500. The server sets the response's version, Connection and Content-Length.
  using Handler = std::function<boost::asio::awaitable<Response>(Request)>;

  // Optional; called on the server's executor once a request's header has been read and before
  // its body is (`header` has an empty body). It may answer at once: the connection then closes
  // without the body ever being read, so a wrong token or an unknown route costs no body buffer.
  // Or it may lower `body_limit` (which starts at ServerLimits::max_body_bytes) to the route's
  // own limit, so an oversized body is refused with 413 as it arrives. An exception becomes a 500.
  using HeaderCheck = std::function<std::optional<Response>(const Request& header, std::uint64_t& body_limit)>;

  // Optional; called on the server's executor with each request's header until one returns true
  // on a connection, which is authenticated from then on (see the top of this file). Must not
  // throw.
  using Authenticated = std::function<bool(const Request& header)>;

  // Nothing happens until start(). `port` 0 asks the kernel for a free port (see port()).
  // Limits must be positive (asserted). `tls` (make_server_tls_context) makes it an HTTPS server;
  // null: plain HTTP. The context is shared by every connection and must not change afterwards.
  Server(boost::asio::any_io_executor executor, boost::asio::ip::address address, std::uint16_t port,
         ServerLimits limits, Handler handler, HeaderCheck header_check = {}, Authenticated authenticated = {},
         const util::Clock& clock = util::real_clock(), std::shared_ptr<boost::asio::ssl::context> tls = nullptr);
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // Opens, binds and listens, then starts accepting on the executor. On error (address in use,
  // permission denied, already started, already stopped) nothing is listening and the error is
  // returned.
  [[nodiscard]] boost::system::error_code start();

  // The bound port once start() succeeded (the real one when 0 was asked for), else 0.
  std::uint16_t port() const;

  // Graceful stop (see the top of this file). Completes when every connection has ended, or
  // about a second after `grace` (on the clock) if a cancelled handler ignores its cancellation. A second call
  // returns at once. Must be awaited on the server's executor.
  boost::asio::awaitable<void> stop(std::chrono::milliseconds grace);

  ServerMetrics metrics() const;

 private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

}  // namespace dtraced::http
