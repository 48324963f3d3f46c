// dtraced::http server: HTTP/1.1 over TCP with Boost.Beast and C++20 coroutines.
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
//   max_connections sessions already open -> 503 (with Retry-After).
// A request still incomplete at its read deadline is dropped without an answer: its client is
// gone or hostile. Before closing after a last response the server half-closes and drains what
// the peer still sends (bounded), so the peer reads the answer instead of a reset.
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

namespace dtraced::http {

// Set by the server on every request it hands to the header check and the handler: the peer's
// address (e.g. "192.0.2.7", "::1"); a value the client sent under this name is replaced.
inline constexpr std::string_view kPeerHeader = "X-Dtraced-Peer";

struct ServerLimits {
  std::uint32_t max_header_bytes = 8 * 1024;  // request line and header fields together
  std::uint64_t max_body_bytes = 64ull << 20;
  std::chrono::milliseconds read_timeout{10'000};            // first byte to end of body
  std::chrono::milliseconds write_timeout{30'000};           // one whole response
  std::chrono::milliseconds idle_keepalive_timeout{30'000};  // between requests on a connection
  std::size_t max_connections = 256;                         // open sessions; more get 503
};

// Counters since start(); a snapshot, all fields read together.
struct ServerMetrics {
  std::uint64_t requests = 0;  // responses sent, the server's own 4xx and 5xx (and 503s) included
  std::uint64_t responses_4xx = 0;
  std::uint64_t responses_5xx = 0;
  std::uint64_t read_timeouts = 0;         // connections dropped at the read deadline
  std::uint64_t rejected_connections = 0;  // connections over max_connections
  std::uint64_t open_connections = 0;      // sessions open now (a gauge)
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

  // Nothing happens until start(). `port` 0 asks the kernel for a free port (see port()).
  // Limits must be positive (asserted).
  Server(boost::asio::any_io_executor executor, boost::asio::ip::address address, std::uint16_t port,
         ServerLimits limits, Handler handler, HeaderCheck header_check = {},
         const util::Clock& clock = util::real_clock());
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
