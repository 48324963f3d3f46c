#include "http/server.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <cctype>
#include <exception>
#include <list>
#include <mutex>
#include <optional>
#include <string>
#include <tuple>
#include <type_traits>
#include <utility>

#include <boost/asio/bind_cancellation_slot.hpp>
#include <boost/asio/cancellation_signal.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/asio/ssl/stream_base.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/core/detect_ssl.hpp>
#include <boost/beast/core/error.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/string.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/empty_body.hpp>
#include <boost/beast/http/error.hpp>
#include <boost/beast/http/field.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/beast/http/write.hpp>
#include <boost/beast/ssl/ssl_stream.hpp>
#include <openssl/ssl.h>
#include <openssl/x509.h>

#include "async/async.h"
#include "http/names.h"
#include "http/serialise.h"
#include "util/log.h"

namespace dtraced::http {
namespace {

using namespace names;

// Socket deadlines are beast::tcp_stream's expires_at/after, in real time: one timer per
// connection, re-armed per phase, that closes the socket when it fires. Racing each operation
// against a timer with awaitable_operators' || would spawn two coroutines per read or write for
// the same effect.
//
// One completion token for every awaited operation (async::kAwaitTuple): errors come back as
// values, so a peer's misbehaviour is handled where it happens instead of unwinding the session.

// Bytes asked of the kernel per read while waiting for the start of a request.
constexpr std::size_t kReadChunkBytes = 16 * 1024;
// After a connection's last response the server half-closes and reads what the peer still sends
// (the rest of a refused body, a pipelined request) before closing: closing with unread input
// makes the kernel send a reset, and the peer may then lose the response it has not read yet.
constexpr std::chrono::milliseconds kLingerTimeout{1000};
constexpr std::size_t kLingerMaxBytes = 1 << 20;
constexpr std::size_t kLingerChunkBytes = 4096;
// Connections over max_connections are answered 503 by a short coroutine each; past this many
// such answers at once, further ones are closed without a word.
constexpr std::size_t kMaxRejectingConnections = 64;
// Pause after a failed accept (EMFILE, ENFILE, ENOBUFS) so the loop does not spin on it.
constexpr std::chrono::milliseconds kAcceptErrorBackoff{100};
// How long a TLS connection's close_notify exchange may take before the socket is closed anyway.
constexpr std::chrono::milliseconds kTlsShutdownTimeout{1000};
// A client certificate's common name stamped on requests is cut to this length.
constexpr std::size_t kMaxClientNameBytes = 256;
// How long stop() waits for cancelled sessions to unwind after its grace period.
constexpr std::chrono::milliseconds kCutUnwindTimeout{1000};
// Request targets quoted in log lines are cut to this length.
constexpr std::size_t kMaxLoggedTargetBytes = 200;

bool is_http_parse_error(const error_code& ec) {
  return ec.category() == bhttp::make_error_code(bhttp::error::bad_method).category();
}

// The answer to a request that could not be read, or nullopt to drop the connection silently
// (the peer closed, reset, or ran out of time: nobody is there to read an answer).
std::optional<Response> answer_read_error(const error_code& ec, const ServerLimits& limits) {
  if (ec == bhttp::error::body_limit) {
    return make_error(Status::payload_too_large,
                      fmt::format("request body exceeds the limit of {} bytes", limits.max_body_bytes));
  }
  if (ec == bhttp::error::header_limit || ec == bhttp::error::buffer_overflow) {
    return make_error(Status::request_header_fields_too_large,
                      fmt::format("request header exceeds the limit of {} bytes", limits.max_header_bytes));
  }
  if (ec == bhttp::error::end_of_stream || ec == bhttp::error::partial_message) return std::nullopt;
  if (is_http_parse_error(ec)) {
    return make_error(Status::bad_request, fmt::format("malformed HTTP request: {}", ec.message()));
  }
  return std::nullopt;
}

bool expects_continue(const Request& req) { return beast::iequals(req[bhttp::field::expect], "100-continue"); }

// Answers whose body is at most this are written as one buffer, which Beast's serializer fills
// synchronously: on TLS one SSL_write, one record and one sendmsg, without the four layers of
// composed operations of bhttp::async_write (serializer, write_op, write_some_op and flat_stream's
// write_op), which cost more than the copy of a small body (most answers: a tile's verdict with
// the next lease is under 1 KB). Header and body stay within one 16 KiB TLS record. Larger
// answers (images) are written by bhttp::async_write, without a copy of the body.
constexpr std::size_t kOneBufferBodyBytes = 8 * 1024;

// `res` as bhttp::async_write puts it on the wire, serialised by Beast into one string; nullopt
// when the body is over kOneBufferBodyBytes or chunked, or the serializer fails.
std::optional<std::string> one_buffer(Response& res) {
  if (res.body().size() > kOneBufferBodyBytes || res.chunked()) return std::nullopt;
  std::string out;
  out.reserve(256 + res.body().size());
  if (!append_serialised(res, out)) return std::nullopt;
  return out;
}

std::string loggable_target(const Request& req) {
  const auto target = req.target();
  return std::string(target.data(), std::min(target.size(), kMaxLoggedTargetBytes));
}

using TlsStream = beast::ssl_stream<beast::tcp_stream>;

// One accepted socket. Lives in Impl::connections from accept until its coroutine has ended.
struct Connection {
  Connection(tcp::socket socket, bool rejecting, bool authenticated)
      : stream(std::move(socket)), rejecting(rejecting), authenticated(authenticated) {}

  // The TCP layer, under TLS or not: its deadlines govern both, and closing it ends either.
  beast::tcp_stream& lowest() { return tls ? tls->next_layer() : stream; }

  beast::tcp_stream stream;         // moved into `tls` when a handshake starts; use lowest() instead
  std::optional<TlsStream> tls;     // a TLS connection's stream, from its handshake on
  std::string peer;                 // the peer's address, as stamped on requests ("" if unknown)
  std::string client_name;          // a verified client certificate's CN ("" when none)
  const bool rejecting;             // over the cap: answered 503 and closed
  bool authenticated;               // a request's header passed the predicate (or there is none)
  bool reading = false;             // waiting for or reading a request: an unauthenticated one may be evicted
  bool holds_slot = false;          // counted in sessions (and unauthenticated) until released
  bool busy = false;                // a request is being read, handled or written: stop() lets it finish
  bool finished = false;            // its coroutine has completed; erased soon after
  bool idle = false;                // waiting for a request after answering one (Impl::idle_count)
  std::uint64_t idle_order = 0;     // when it went idle: the lowest goes first over the cap
  std::uint32_t requests = 0;       // requests read on this connection
  net::cancellation_signal cancel;  // cancels the coroutine (and the handler) when stop() gives up
};

// Replaces any kPeerHeader the client sent with the connection's real source address, so the
// header check and the handler can name the peer (logs, the collector's worker registry), and
// any kClientCertHeader with the verified client certificate's name (or nothing).
void stamp_peer(Request& req, const Connection& conn) {
  const beast::string_view peer(kPeerHeader.data(), kPeerHeader.size());
  req.erase(peer);
  if (!conn.peer.empty()) req.set(peer, conn.peer);
  const beast::string_view client(kClientCertHeader.data(), kClientCertHeader.size());
  req.erase(client);
  if (!conn.client_name.empty()) req.set(client, conn.client_name);
}

std::string peer_address(const tcp::socket& socket) {
  error_code ec;
  const tcp::endpoint peer = socket.remote_endpoint(ec);
  return ec ? std::string() : peer.address().to_string();
}

// The subject CN of the client certificate OpenSSL verified on `ssl`, made safe for a header
// value (control characters become '?'), or "" when no certificate was asked for or given.
std::string verified_client_name(SSL* ssl) {
  if ((SSL_get_verify_mode(ssl) & SSL_VERIFY_PEER) == 0) return {};
  X509* cert = SSL_get0_peer_certificate(ssl);
  if (cert == nullptr || SSL_get_verify_result(ssl) != X509_V_OK) return {};
  X509_NAME* subject = X509_get_subject_name(cert);
  const int index = X509_NAME_get_index_by_NID(subject, NID_commonName, -1);
  if (index < 0) return {};
  unsigned char* utf8 = nullptr;
  const int n = ASN1_STRING_to_UTF8(&utf8, X509_NAME_ENTRY_get_data(X509_NAME_get_entry(subject, index)));
  if (n <= 0) return {};
  std::string name(reinterpret_cast<const char*>(utf8), std::min<std::size_t>(n, kMaxClientNameBytes));
  OPENSSL_free(utf8);
  for (char& c : name) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 || u == 0x7f) c = '?';
  }
  return name;
}

// What a client that spoke plain HTTP to the TLS port should have asked for: https:// and the
// host it named (Host header, when it is a plain host[:port]), else the address it reached.
std::string https_origin(const bhttp::fields* header, const tcp::socket& socket) {
  error_code ec;
  const tcp::endpoint local = socket.local_endpoint(ec);
  const std::string port = ec ? std::string() : fmt::format(":{}", local.port());
  if (header != nullptr) {
    const auto host = (*header)[bhttp::field::host];
    const bool plain = !host.empty() && host.size() <= 255 && std::all_of(host.begin(), host.end(), [](char c) {
      return std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '-' || c == ':' || c == '[' || c == ']';
    });
    if (plain) {
      const std::string name(host);
      const auto bracket = name.rfind(']');
      const auto colon = name.rfind(':');
      const bool has_port = colon != std::string::npos && (bracket == std::string::npos || colon > bracket) &&
                            (name.front() == '[' || name.find(':') == colon);
      return "https://" + name + (has_port ? "" : port);
    }
  }
  if (ec) return "https://HOST:PORT";
  const auto address = local.address();
  return address.is_v6() ? fmt::format("https://[{}]{}", address.to_string(), port)
                         : fmt::format("https://{}{}", address.to_string(), port);
}

}  // namespace

struct Server::Impl {
  Impl(net::any_io_executor executor, net::ip::address address, std::uint16_t port, ServerLimits limits,
       Handler handler, HeaderCheck header_check, Authenticated authenticated, const util::Clock& clock,
       std::shared_ptr<net::ssl::context> tls)
      : executor(executor),
        endpoint(address, port),
        limits(limits),
        handler(std::move(handler)),
        header_check(std::move(header_check)),
        authenticated(std::move(authenticated)),
        clock(clock),
        tls(std::move(tls)),
        acceptor(executor) {}

  static net::awaitable<void> accept_loop(std::shared_ptr<Impl> self);
  static void spawn(const std::shared_ptr<Impl>& self, tcp::socket socket, bool rejecting);
  bool evict_oldest_unauthenticated();
  void release_slot(Connection& conn);
  void authenticate(Connection& conn, const Request& header);
  // The 503 a large answer gets over max_held_response_bytes, or nullopt with its bytes counted
  // as held (in `held`, to give back with release_held once written).
  std::optional<Response> hold_large_response(const Response& res, std::uint64_t& held);
  void release_held(std::uint64_t held);
  static void on_finished(const std::shared_ptr<Impl>& self, std::list<Connection>::iterator it,
                          std::exception_ptr error);
  void set_idle(Connection& conn, bool idle);
  // Over max_idle_connections: closes the connection idle the longest.
  void close_excess_idle();
  // The connection idle the longest, or null.
  Connection* oldest_idle();
  void close_idle(Connection& conn);
  void log_handshake_failure(const std::string& peer, const std::string& reason);
  // A connection's coroutine: on a TLS server, detection and handshake first; then session() or
  // reject() on the stream that resulted.
  static net::awaitable<void> run(std::shared_ptr<Impl> self, Connection& conn);
  static net::awaitable<bool> handshake(Impl& self, Connection& conn, beast::flat_buffer& buffer);
  static net::awaitable<void> refuse_plain(Impl& self, Connection& conn, beast::flat_buffer& buffer);
  template <typename Stream>
  static net::awaitable<void> session(std::shared_ptr<Impl> self, Connection& conn, Stream& stream,
                                      beast::flat_buffer& buffer);
  template <typename Stream>
  static net::awaitable<void> reject(Impl& self, Connection& conn, Stream& stream);
  static net::awaitable<Response> call_handler(Impl& self, Request req);
  template <typename Stream>
  static net::awaitable<void> respond_and_close(Impl& self, Connection& conn, Stream& stream, Response res);
  template <typename Stream>
  static net::awaitable<void> linger_and_close(Connection& conn, Stream& stream);
  static net::awaitable<void> stop(std::shared_ptr<Impl> self, std::chrono::milliseconds grace);
  static net::awaitable<void> wait_until_drained(Impl& self, util::TimePoint deadline);
  void cut_all();
  void count_response(unsigned status);
  // Adds `n` to a counter (a negative n to a gauge).
  void count(std::uint64_t ServerMetrics::*counter, std::int64_t n = 1) {
    std::lock_guard lock(metrics_mu);
    counts.*counter += static_cast<std::uint64_t>(n);
  }

  // Immutable after construction.
  const net::any_io_executor executor;
  const tcp::endpoint endpoint;
  const ServerLimits limits;
  const Handler handler;
  const HeaderCheck header_check;     // may be empty
  const Authenticated authenticated;  // may be empty: every connection is authenticated
  const util::Clock& clock;
  const std::shared_ptr<net::ssl::context> tls;  // null: plain HTTP

  // Owned by the executor.
  tcp::acceptor acceptor;
  std::list<Connection> connections;  // stable addresses: sessions hold a reference to theirs
  std::size_t sessions = 0;           // connections holding a slot (not rejecting, not evicted)
  std::uint64_t held_bytes = 0;       // large answers handed back by the handler, not yet written
  std::size_t rejecting = 0;
  std::size_t idle_count = 0;                          // connections with `idle` set
  std::uint64_t idle_sequence = 0;                     // source of Connection::idle_order
  std::optional<util::TimePoint> handshake_logged_at;  // the last handshake failure logged
  std::uint64_t handshake_failures_held = 0;           // failures not logged since
  bool started = false;
  bool stopping = false;                 // no new connections; answers say Connection: close
  bool cutting = false;                  // the grace period is over: cancellations and errors are expected
  async::Event* erased_event = nullptr;  // set when a connection is erased while stop() waits

  // Read from any thread.
  std::atomic<std::uint16_t> bound_port{0};
  mutable std::mutex metrics_mu;
  ServerMetrics counts;  // guarded by metrics_mu
};

net::awaitable<void> Server::Impl::accept_loop(std::shared_ptr<Impl> self) {
  for (;;) {
    auto [ec, socket] = co_await self->acceptor.async_accept(kAwaitTuple);
    if (self->stopping) co_return;  // an accepted socket closes with `socket`
    if (ec) {
      if (ec == net::error::operation_aborted || !self->acceptor.is_open()) co_return;
      util::log_warn("http: accept failed: {}", ec.message());
      co_await async::sleep_for(self->clock, kAcceptErrorBackoff);
      continue;
    }
    // Room for the newcomer: the oldest unauthenticated connection waiting for bytes goes first,
    // then the connection idle the longest (its client opens another when it needs one).
    if (self->sessions >= self->limits.max_connections) self->evict_oldest_unauthenticated();
    if (self->sessions >= self->limits.max_connections) {
      if (Connection* idle = self->oldest_idle()) {
        self->release_slot(*idle);
        self->close_idle(*idle);
      }
    }
    if (self->sessions >= self->limits.max_connections) {
      self->count(&ServerMetrics::rejected_connections);
      if (self->rejecting < kMaxRejectingConnections) spawn(self, std::move(socket), /*rejecting=*/true);
      continue;
    }
    spawn(self, std::move(socket), /*rejecting=*/false);
  }
}

void Server::Impl::spawn(const std::shared_ptr<Impl>& self, tcp::socket socket, bool rejecting) {
  // Requests and answers are small and written whole: Nagle would only add latency.
  error_code ignored;
  socket.set_option(tcp::no_delay(true), ignored);
  std::string peer = peer_address(socket);
  const auto it = self->connections.emplace(self->connections.end(), std::move(socket), rejecting,
                                            /*authenticated=*/!self->authenticated);
  it->peer = std::move(peer);
  if (rejecting) {
    ++self->rejecting;
  } else {
    it->holds_slot = true;
    ++self->sessions;
    self->count(&ServerMetrics::open_connections);
  }
  net::co_spawn(self->executor, run(self, *it),
                net::bind_cancellation_slot(it->cancel.slot(), [self, it](std::exception_ptr error) {
                  on_finished(self, it, std::move(error));
                }));
}

void Server::Impl::on_finished(const std::shared_ptr<Impl>& self, std::list<Connection>::iterator it,
                               std::exception_ptr error) {
  if (!self->cutting) async::log_exception("http: a connection", error);
  it->finished = true;
  self->set_idle(*it, false);
  if (it->rejecting) {
    --self->rejecting;
  } else {
    self->release_slot(*it);
  }
  // Erase later: this completion handler runs inside co_spawn's machinery, which still holds the
  // cancellation slot that lives in *it.
  net::post(self->executor, [self, it] {
    self->connections.erase(it);
    if (self->stopping && self->erased_event != nullptr) self->erased_event->set();
  });
}

net::awaitable<void> Server::Impl::run(std::shared_ptr<Impl> self, Connection& conn) {
  beast::flat_buffer buffer;
  conn.reading = !conn.rejecting;  // a connection that has not yet spoken may be evicted
  if (!self->tls) {
    if (conn.rejecting) {
      co_await reject(*self, conn, conn.stream);
    } else {
      co_await session(self, conn, conn.stream, buffer);
    }
    co_return;
  }
  // The first bytes say whether the peer speaks TLS, under the deadline of a first byte.
  const ServerLimits& limits = self->limits;
  auto wait = limits.read_timeout;
  if (!conn.authenticated) wait = std::min(wait, limits.unauthenticated_timeout);
  conn.stream.expires_after(wait);
  auto [ec, is_tls] = co_await beast::async_detect_ssl(conn.stream, buffer, kAwaitTuple);
  if (ec) {
    if (ec == beast::error::timeout) self->count(&ServerMetrics::read_timeouts);
    co_return;
  }
  if (!is_tls) {
    co_await refuse_plain(*self, conn, buffer);
    co_return;
  }
  if (!co_await handshake(*self, conn, buffer)) co_return;
  if (conn.rejecting) {
    co_await reject(*self, conn, *conn.tls);
  } else {
    co_await session(self, conn, *conn.tls, buffer);
  }
}

net::awaitable<bool> Server::Impl::handshake(Impl& self, Connection& conn, beast::flat_buffer& buffer) {
  conn.tls.emplace(std::move(conn.stream), *self.tls);
  auto limit = self.limits.handshake_timeout;
  if (!conn.authenticated) limit = std::min(limit, self.limits.unauthenticated_timeout);
  conn.lowest().expires_after(limit);
  // The bytes detect_ssl read are the start of the ClientHello.
  auto [ec, used] = co_await conn.tls->async_handshake(net::ssl::stream_base::server, buffer.data(), kAwaitTuple);
  if (ec) {
    conn.lowest().close();
    // Closed by the server itself (eviction, stop) is no failure of the peer's.
    if (ec == net::error::operation_aborted) co_return false;
    std::string reason =
        ec == beast::error::timeout ? fmt::format("no handshake within {} ms", limit.count()) : ec.message();
    const long verify = SSL_get_verify_result(conn.tls->native_handle());
    if (verify != X509_V_OK) reason += fmt::format(" (client certificate: {})", X509_verify_cert_error_string(verify));
    if (!self.cutting) self.log_handshake_failure(conn.peer, reason);
    self.count(&ServerMetrics::tls_handshake_failures);  // after the log line: tests wait for it
    co_return false;
  }
  buffer.consume(used);
  self.count(&ServerMetrics::tls_handshakes);
  conn.client_name = verified_client_name(conn.tls->native_handle());
  co_return true;
}

net::awaitable<void> Server::Impl::refuse_plain(Impl& self, Connection& conn, beast::flat_buffer& buffer) {
  self.count(&ServerMetrics::plain_on_tls);
  conn.busy = true;
  // The request's header, if it is one, names the host the client meant; garbage ends the read
  // at once with a parse error and gets the same answer.
  auto wait = self.limits.read_timeout;
  if (!conn.authenticated) wait = std::min(wait, self.limits.unauthenticated_timeout);
  conn.stream.expires_after(wait);
  bhttp::request_parser<bhttp::empty_body> parser;
  parser.header_limit(self.limits.max_header_bytes);
  auto [ec, n] = co_await bhttp::async_read_header(conn.stream, buffer, parser, kAwaitTuple);
  if (ec == beast::error::timeout) {
    self.count(&ServerMetrics::read_timeouts);
    co_return;
  }
  const std::string origin = https_origin(ec ? nullptr : &parser.get().base(), conn.stream.socket());
  co_await respond_and_close(self, conn, conn.stream,
                             make_error(Status::bad_request, fmt::format("this port speaks HTTPS: use {}", origin)));
}

template <typename Stream>
net::awaitable<void> Server::Impl::session(std::shared_ptr<Impl> self, Connection& conn, Stream& stream,
                                           beast::flat_buffer& buffer) {
  const ServerLimits& limits = self->limits;
  bool first = true;
  for (;;) {
    // Between requests. A pipelined request may already be in the buffer; otherwise wait for the
    // first byte of the next one.
    conn.busy = false;
    conn.reading = true;
    if (buffer.size() == 0) {
      auto wait = first ? limits.read_timeout : limits.idle_keepalive_timeout;
      if (!conn.authenticated) wait = std::min(wait, limits.unauthenticated_timeout);
      conn.lowest().expires_after(wait);
      if (!first) self->set_idle(conn, true);
      auto [ec, n] = co_await stream.async_read_some(buffer.prepare(kReadChunkBytes), kAwaitTuple);
      self->set_idle(conn, false);
      if (ec) {
        // A fresh connection that never speaks counts as a stalled request; an idle keep-alive
        // connection timing out is ordinary.
        if (ec == beast::error::timeout && first) self->count(&ServerMetrics::read_timeouts);
        co_return;
      }
      buffer.commit(n);
    }
    if (!first) self->count(&ServerMetrics::keepalive_reuses);
    first = false;
    conn.busy = true;
    ++conn.requests;

    // One whole request before its deadline, within the size limits.
    // Socket deadlines; an unauthenticated peer has less time for the header.
    const auto now = std::chrono::steady_clock::now();
    const auto read_deadline = now + limits.read_timeout;
    const auto header_deadline =
        conn.authenticated ? read_deadline : std::min(read_deadline, now + limits.unauthenticated_timeout);
    conn.lowest().expires_at(header_deadline);
    bhttp::request_parser<bhttp::string_body> parser;
    parser.header_limit(limits.max_header_bytes);
    // No body limit while the header is read: Beast would refuse a Content-Length over it when the
    // header ends, before the header check could answer (a wrong token must get 401, not 413).
    parser.body_limit(boost::none);
    error_code ec;
    std::size_t n = 0;
    std::tie(ec, n) = co_await bhttp::async_read_header(stream, buffer, parser, kAwaitTuple);
    ServerLimits request_limits = limits;  // the body limit as the header check leaves it
    if (!ec) {
      stamp_peer(parser.get(), conn);
      self->authenticate(conn, parser.get());
      if (conn.authenticated) conn.lowest().expires_at(read_deadline);
      std::optional<Response> early;
      try {
        std::uint64_t body_limit = limits.max_body_bytes;
        if (self->header_check) early = self->header_check(parser.get(), body_limit);
        request_limits.max_body_bytes = std::min(body_limit, limits.max_body_bytes);
      } catch (const std::exception& e) {
        util::log_error("http: header check threw: {}", e.what());
        early = make_error(Status::internal_server_error, "internal error");
      }
      if (!early) {
        // A chunked body is held to the limit chunk by chunk; a Content-Length is checked here.
        parser.body_limit(request_limits.max_body_bytes);
        const auto length = parser.content_length();
        if (length && *length > request_limits.max_body_bytes) {
          early = answer_read_error(bhttp::error::body_limit, request_limits);
        }
      }
      if (early) {
        // Answered on the header alone; the body, if any, is never read (at most drained).
        co_await respond_and_close(*self, conn, stream, std::move(*early));
        co_return;
      }
    }
    if (!ec && !parser.is_done()) {
      if (expects_continue(parser.get())) {
        // The client waits for this before it sends the body (curl does for large bodies).
        conn.lowest().expires_after(limits.write_timeout);
        bhttp::response<bhttp::empty_body> go_on{Status::continue_, parser.get().version()};
        std::tie(ec, n) = co_await bhttp::async_write(stream, go_on, kAwaitTuple);
        conn.lowest().expires_at(conn.authenticated ? read_deadline : header_deadline);
      }
      if (!ec) std::tie(ec, n) = co_await bhttp::async_read(stream, buffer, parser, kAwaitTuple);
    }
    if (ec) {
      if (ec == beast::error::timeout) {
        self->count(&ServerMetrics::read_timeouts);
        co_return;
      }
      std::optional<Response> answer = answer_read_error(ec, request_limits);
      if (answer) co_await respond_and_close(*self, conn, stream, std::move(*answer));
      co_return;
    }

    conn.reading = false;
    Request req = parser.release();
    const bool client_keep_alive = req.keep_alive();
    const unsigned version = req.version();
    conn.lowest().expires_never();
    Response res = co_await call_handler(*self, std::move(req));

    const bool keep_alive =
        client_keep_alive && res.keep_alive() && !self->stopping && conn.requests < limits.max_requests_per_connection;
    std::uint64_t held = 0;
    if (std::optional<Response> refused = self->hold_large_response(res, held)) res = std::move(*refused);
    res.version(version);
    res.keep_alive(keep_alive);
    self->count_response(res.result_int());
    conn.lowest().expires_after(limits.write_timeout);
    if (const std::optional<std::string> text = one_buffer(res)) {
      std::tie(ec, n) = co_await net::async_write(stream, net::buffer(*text), kAwaitTuple);
    } else {
      std::tie(ec, n) = co_await bhttp::async_write(stream, res, kAwaitTuple);
    }
    res = Response();  // the body is written (or never will be): free it before lingering
    self->release_held(held);
    if (ec) co_return;
    if (!keep_alive) {
      co_await linger_and_close(conn, stream);
      co_return;
    }
  }
}

bool Server::Impl::evict_oldest_unauthenticated() {
  for (Connection& conn : connections) {
    if (conn.holds_slot && conn.reading && !conn.authenticated && !conn.finished) {
      release_slot(conn);
      count(&ServerMetrics::evicted_connections);
      conn.lowest().close();  // its read ends with an error and the session returns
      return true;
    }
  }
  return false;
}

void Server::Impl::release_slot(Connection& conn) {
  if (!conn.holds_slot) return;
  conn.holds_slot = false;
  --sessions;
  count(&ServerMetrics::open_connections, -1);
}

void Server::Impl::set_idle(Connection& conn, bool idle) {
  if (conn.idle == idle) return;
  conn.idle = idle;
  if (!idle) {
    --idle_count;
    return;
  }
  ++idle_count;
  conn.idle_order = ++idle_sequence;
  close_excess_idle();
}

void Server::Impl::close_excess_idle() {
  while (idle_count > limits.max_idle_connections) {
    Connection* oldest = oldest_idle();
    if (oldest == nullptr) return;
    close_idle(*oldest);
  }
}

Connection* Server::Impl::oldest_idle() {
  Connection* oldest = nullptr;
  for (Connection& conn : connections) {
    if (conn.idle && !conn.finished && (oldest == nullptr || conn.idle_order < oldest->idle_order)) oldest = &conn;
  }
  return oldest;
}

void Server::Impl::close_idle(Connection& conn) {
  set_idle(conn, false);
  count(&ServerMetrics::evicted_idle_connections);
  conn.lowest().close();  // its read ends with an error and the session returns
}

void Server::Impl::log_handshake_failure(const std::string& peer, const std::string& reason) {
  const util::TimePoint now = clock.now();
  if (handshake_logged_at && now - *handshake_logged_at < kHandshakeLogInterval) {
    ++handshake_failures_held;
    return;
  }
  handshake_logged_at = now;
  const std::string who = peer.empty() ? std::string("a peer") : peer;
  if (handshake_failures_held > 0) {
    util::log_warn(
        "http: TLS handshake with {} failed: {} ({} more failed handshake(s) not logged since the last line)", who,
        reason, handshake_failures_held);
  } else {
    util::log_warn("http: TLS handshake with {} failed: {}", who, reason);
  }
  handshake_failures_held = 0;
}

void Server::Impl::authenticate(Connection& conn, const Request& header) {
  if (!conn.authenticated && authenticated(header)) conn.authenticated = true;
}

std::optional<Response> Server::Impl::hold_large_response(const Response& res, std::uint64_t& held) {
  held = 0;
  const std::uint64_t size = res.body().size();
  if (size < kLargeResponseBytes) return std::nullopt;
  if (held_bytes > 0 && held_bytes + size > limits.max_held_response_bytes) {
    count(&ServerMetrics::refused_large_responses);
    Response busy = make_error(Status::service_unavailable,
                               fmt::format("{} bytes of answers are waiting for slow readers (limit {}); retry later",
                                           held_bytes, limits.max_held_response_bytes));
    busy.set(bhttp::field::retry_after, "1");
    return busy;
  }
  held_bytes += size;
  held = size;
  count(&ServerMetrics::held_response_bytes, static_cast<std::int64_t>(size));
  return std::nullopt;
}

void Server::Impl::release_held(std::uint64_t held) {
  if (held == 0) return;
  held_bytes -= held;
  count(&ServerMetrics::held_response_bytes, -static_cast<std::int64_t>(held));
}

template <typename Stream>
net::awaitable<void> Server::Impl::reject(Impl& self, Connection& conn, Stream& stream) {
  conn.busy = true;
  Response res =
      make_error(Status::service_unavailable,
                 fmt::format("too many open connections (limit {}); retry later", self.limits.max_connections));
  res.set(bhttp::field::retry_after, "1");
  co_await respond_and_close(self, conn, stream, std::move(res));
}

net::awaitable<Response> Server::Impl::call_handler(Impl& self, Request req) {
  const std::string method(req.method_string());
  const std::string target = loggable_target(req);
  std::string failure;
  try {
    Response res = co_await self.handler(std::move(req));
    res.prepare_payload();  // throws for a body where none is allowed (204, 304)
    co_return res;
  } catch (const std::exception& e) {
    failure = e.what();
  } catch (...) {
    failure = "unknown exception";
  }
  if (!self.cutting) util::log_error("http: handler for {} {} threw: {}", method, target, failure);
  co_return make_error(Status::internal_server_error, "internal error");
}

template <typename Stream>
net::awaitable<void> Server::Impl::respond_and_close(Impl& self, Connection& conn, Stream& stream, Response res) {
  res.keep_alive(false);
  self.count_response(res.result_int());
  conn.lowest().expires_after(self.limits.write_timeout);
  auto [ec, n] = co_await bhttp::async_write(stream, res, kAwaitTuple);
  if (ec) co_return;
  co_await linger_and_close(conn, stream);
}

template <typename Stream>
net::awaitable<void> Server::Impl::linger_and_close(Connection& conn, Stream& stream) {
  conn.busy = false;  // the answer is out: stop() may close this at once
  beast::tcp_stream& lowest = conn.lowest();
  if constexpr (std::is_same_v<Stream, TlsStream>) {
    // close_notify, so the peer knows the answer is complete; its own close_notify (or its end
    // of stream) ends the exchange, a silent peer the deadline (which closes the socket).
    lowest.expires_after(kTlsShutdownTimeout);
    auto [sec] = co_await stream.async_shutdown(kAwaitTuple);
    std::ignore = sec;
  }
  error_code ec;
  lowest.socket().shutdown(tcp::socket::shutdown_send, ec);
  if (!ec) {
    lowest.expires_after(kLingerTimeout);
    std::array<char, kLingerChunkBytes> scratch;
    std::size_t drained = 0;
    while (drained < kLingerMaxBytes) {
      auto [rec, n] = co_await lowest.async_read_some(net::buffer(scratch), kAwaitTuple);
      if (rec) break;  // end of stream (the usual way out), reset, or the linger deadline
      drained += n;
    }
  }
  lowest.close();
}

net::awaitable<void> Server::Impl::stop(std::shared_ptr<Impl> self, std::chrono::milliseconds grace) {
  if (self->stopping) co_return;
  self->stopping = true;
  error_code ignored;
  self->acceptor.close(ignored);
  for (Connection& conn : self->connections) {
    if (!conn.busy && !conn.finished) conn.lowest().close();
  }
  co_await wait_until_drained(*self, self->clock.now() + grace);
  if (self->connections.empty()) co_return;

  const auto busy = std::count_if(self->connections.begin(), self->connections.end(),
                                  [](const Connection& conn) { return !conn.finished; });
  util::log_warn("http: {} connection(s) still busy {} ms after stop; cancelling them", busy, grace.count());
  self->cut_all();
  co_await wait_until_drained(*self, self->clock.now() + kCutUnwindTimeout);
  if (!self->connections.empty()) {
    util::log_warn("http: {} connection(s) did not unwind after cancellation", self->connections.size());
  }
}

net::awaitable<void> Server::Impl::wait_until_drained(Impl& self, util::TimePoint deadline) {
  // Woken by the deadline on the clock, or by each connection erased, to look again.
  while (!self.connections.empty() && self.clock.now() < deadline) {
    async::Event erased(self.executor);
    self.erased_event = &erased;
    co_await async::sleep_until(self.clock, deadline, &erased);
    self.erased_event = nullptr;
  }
}

void Server::Impl::cut_all() {
  stopping = true;
  cutting = true;
  error_code ignored;
  acceptor.close(ignored);
  for (Connection& conn : connections) {
    if (conn.finished) continue;
    conn.cancel.emit(net::cancellation_type::terminal);
    conn.lowest().close();
  }
}

void Server::Impl::count_response(unsigned status) {
  std::lock_guard lock(metrics_mu);
  ++counts.requests;
  if (status >= 400 && status < 500) ++counts.responses_4xx;
  if (status >= 500 && status < 600) ++counts.responses_5xx;
}

Server::Server(net::any_io_executor executor, net::ip::address address, std::uint16_t port, ServerLimits limits,
               Handler handler, HeaderCheck header_check, Authenticated authenticated, const util::Clock& clock,
               std::shared_ptr<net::ssl::context> tls)
    : impl_(std::make_shared<Impl>(std::move(executor), address, port, limits, std::move(handler),
                                   std::move(header_check), std::move(authenticated), clock, std::move(tls))) {
  assert(limits.max_header_bytes > 0 && limits.max_body_bytes > 0 && limits.max_connections > 0);
  assert(limits.read_timeout.count() > 0 && limits.write_timeout.count() > 0 &&
         limits.idle_keepalive_timeout.count() > 0 && limits.unauthenticated_timeout.count() > 0 &&
         limits.max_held_response_bytes > 0 && limits.handshake_timeout.count() > 0 &&
         limits.max_idle_connections > 0 && limits.max_requests_per_connection > 0);
}

Server::~Server() {
  // The executor may be running on another thread: close everything from there. If it never runs
  // again, the io_context's destruction frees the internals instead.
  net::post(impl_->executor, [impl = impl_] { impl->cut_all(); });
}

error_code Server::start() {
  Impl& s = *impl_;
  if (s.started) return net::error::already_started;
  if (s.stopping) return net::error::shut_down;
  error_code ec;
  s.acceptor.open(s.endpoint.protocol(), ec);
  if (!ec) s.acceptor.set_option(net::socket_base::reuse_address(true), ec);
  if (!ec) s.acceptor.bind(s.endpoint, ec);
  if (!ec) s.acceptor.listen(net::socket_base::max_listen_connections, ec);
  tcp::endpoint bound;
  if (!ec) bound = s.acceptor.local_endpoint(ec);
  if (ec) {
    error_code ignored;
    s.acceptor.close(ignored);
    return ec;
  }
  s.started = true;
  s.bound_port.store(bound.port());
  net::co_spawn(s.executor, Impl::accept_loop(impl_), async::log_failure("http: the accept loop"));
  return {};
}

std::uint16_t Server::port() const { return impl_->bound_port.load(); }

net::awaitable<void> Server::stop(std::chrono::milliseconds grace) { return Impl::stop(impl_, grace); }

ServerMetrics Server::metrics() const {
  std::lock_guard lock(impl_->metrics_mu);
  return impl_->counts;
}

}  // namespace dtraced::http
