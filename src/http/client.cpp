#include "http/client.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <deque>
#include <exception>
#include <memory>
#include <tuple>
#include <utility>
#include <variant>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/asio/ssl/error.hpp>
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
#include <boost/beast/ssl/ssl_stream.hpp>
#include <boost/system/system_error.hpp>
#include <fmt/format.h>
#include <openssl/err.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include "async/async.h"
#include "http/names.h"

namespace dtraced::http {
namespace {

using namespace names;
namespace ssl = net::ssl;
// Every deadline here is a socket deadline (resolving, connecting, writing, reading): real time.
using RealClock = std::chrono::steady_clock;
using TlsStream = beast::ssl_stream<beast::tcp_stream>;
using Fingerprint = std::array<std::uint8_t, 32>;

constexpr std::string_view kScheme = "http://";
constexpr std::string_view kTlsScheme = "https://";
constexpr std::uint16_t kDefaultTlsPort = 443;
constexpr std::size_t kMaxHostBytes = 253;  // the longest DNS name
constexpr std::string_view kUserAgent = "dtraced";
// TLS 1.2 suites: forward secret (ECDHE) and AEAD only. TLS 1.3's are all both: OpenSSL's list.
constexpr const char* kTls12Ciphers = "ECDHE+AESGCM:ECDHE+CHACHA20";

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

bool is_ip_address(const std::string& host) {
  error_code ec;
  net::ip::make_address(host, ec);
  return !ec;
}

// OpenSSL's latest queued error as text (and the queue emptied), or `otherwise`.
std::string openssl_reason(std::string_view otherwise) {
  const unsigned long code = ERR_peek_last_error();
  ERR_clear_error();
  if (code == 0) return std::string(otherwise);
  const char* reason = ERR_reason_error_string(code);
  return reason != nullptr ? std::string(reason) : std::string(otherwise);
}

std::string ca_name(const ClientTls& tls) {
  return tls.ca_source.empty() ? std::string("the CA given") : fmt::format("the CA in {}", tls.ca_source);
}

// ---- TLS context ---------------------------------------------------------------------------

std::optional<Fingerprint> sha256_of(X509* cert) {
  Fingerprint digest{};
  unsigned int size = 0;
  if (X509_digest(cert, EVP_sha256(), digest.data(), &size) != 1 || size != digest.size()) return std::nullopt;
  return digest;
}

// Verification of a peer chain against a pinned CA fingerprint: the certificate of the chain the
// server sent whose SHA-256 is `arg` becomes the only trust anchor, then the chain is verified as
// usual (signatures, validity, the host name set on the connection).
int verify_pinned(X509_STORE_CTX* store, void* arg) {
  const auto& wanted = *static_cast<const Fingerprint*>(arg);
  STACK_OF(X509)* sent = X509_STORE_CTX_get0_untrusted(store);
  X509* anchor = nullptr;
  for (int i = 0; sent != nullptr && i < sk_X509_num(sent); ++i) {
    X509* cert = sk_X509_value(sent, i);
    if (sha256_of(cert) == wanted) anchor = cert;
  }
  if (anchor == nullptr) {
    X509_STORE_CTX_set_error(store, X509_V_ERR_UNABLE_TO_GET_ISSUER_CERT_LOCALLY);
    return 0;
  }
  STACK_OF(X509)* trusted = sk_X509_new_null();
  if (trusted == nullptr || sk_X509_push(trusted, anchor) == 0) {
    sk_X509_free(trusted);
    X509_STORE_CTX_set_error(store, X509_V_ERR_OUT_OF_MEM);
    return 0;
  }
  X509_STORE_CTX_set0_trusted_stack(store, trusted);
  const int verified = X509_verify_cert(store);
  X509_STORE_CTX_set0_trusted_stack(store, nullptr);
  sk_X509_free(trusted);  // the certificate itself belongs to the sent chain
  return verified;
}

// Adds every certificate of `pem` to the context's trust store; how many, or why none.
util::Result<int> add_trust_anchors(ssl::context& context, const ClientTls& tls) {
  ERR_clear_error();
  std::unique_ptr<BIO, decltype(&BIO_free)> bio(BIO_new_mem_buf(tls.ca_pem.data(), static_cast<int>(tls.ca_pem.size())),
                                                &BIO_free);
  if (!bio) return util::Error(fmt::format("{}: {}", ca_name(tls), openssl_reason("out of memory")));
  X509_STORE* store = SSL_CTX_get_cert_store(context.native_handle());
  int added = 0;
  for (;;) {
    std::unique_ptr<X509, decltype(&X509_free)> cert(PEM_read_bio_X509(bio.get(), nullptr, nullptr, nullptr),
                                                     &X509_free);
    if (!cert) break;
    if (X509_STORE_add_cert(store, cert.get()) != 1) {
      return util::Error(fmt::format("{}: cannot use a certificate: {}", ca_name(tls), openssl_reason("unknown")));
    }
    ++added;
  }
  const std::string reason = openssl_reason("");
  if (added == 0) {
    return util::Error(fmt::format("{} holds no PEM certificate{}", ca_name(tls),
                                   reason.empty() || reason == "no start line" ? "" : fmt::format(" ({})", reason)));
  }
  return added;
}

// The context every TLS connection of one Client shares. `pinned` must outlive it.
util::Result<std::unique_ptr<ssl::context>> make_context(const ClientTls& tls, const Fingerprint* pinned) {
  auto context = std::make_unique<ssl::context>(ssl::context::tls_client);
  SSL_CTX* handle = context->native_handle();
  if (SSL_CTX_set_min_proto_version(handle, TLS1_2_VERSION) != 1 ||
      SSL_CTX_set_cipher_list(handle, kTls12Ciphers) != 1) {
    return util::Error(fmt::format("cannot set up TLS: {}", openssl_reason("unknown")));
  }
  SSL_CTX_set_options(handle, SSL_OP_NO_COMPRESSION | SSL_OP_NO_RENEGOTIATION);
  SSL_CTX_set_verify(handle, SSL_VERIFY_PEER, nullptr);
  if (!tls.ca_pem.empty()) {
    if (util::Result<int> added = add_trust_anchors(*context, tls); !added) return added.error();
  } else if (tls.ca_fingerprint && pinned != nullptr) {
    SSL_CTX_set_cert_verify_callback(handle, verify_pinned, const_cast<Fingerprint*>(pinned));
  } else {
    return util::Error(fmt::format("{} is empty: a CA certificate is needed to trust the collector", ca_name(tls)));
  }
  return context;
}

// Why a TLS handshake with `where` failed, for someone who has to fix it.
ClientResult handshake_failure(const error_code& ec, SSL* ssl, const Url& url, const std::string& where,
                               const ClientTls& tls, const ClientTimeouts& timeouts) {
  if (ec == beast::error::timeout) {
    ERR_clear_error();
    return failure(ClientError::kTimeout,
                   fmt::format("the TLS handshake with {} timed out after {} ms", where, timeouts.handshake.count()));
  }
  if (ec == net::error::operation_aborted) {
    ERR_clear_error();
    return failure(ClientError::kCancelled, fmt::format("the TLS handshake with {} was cancelled", where));
  }
  const long verified = SSL_get_verify_result(ssl);
  const std::string anchor = tls.ca_pem.empty() ? "the CA of the join code's fingerprint" : ca_name(tls);
  if (verified != X509_V_OK) {
    ERR_clear_error();
    const std::string reason = X509_verify_cert_error_string(verified);
    switch (verified) {
      case X509_V_ERR_HOSTNAME_MISMATCH:
      case X509_V_ERR_IP_ADDRESS_MISMATCH:
        return failure(ClientError::kTls,
                       fmt::format("the certificate of {} does not name {}: connect by a name it has, or start the "
                                   "collector with --tls-name {}",
                                   where, url.host, url.host));
      case X509_V_ERR_CERT_HAS_EXPIRED:
      case X509_V_ERR_CERT_NOT_YET_VALID:
        return failure(ClientError::kTls,
                       fmt::format("the certificate of {} is not valid now ({}): check both clocks", where, reason));
      case X509_V_ERR_UNABLE_TO_GET_ISSUER_CERT_LOCALLY:
      case X509_V_ERR_UNABLE_TO_GET_ISSUER_CERT:
      case X509_V_ERR_UNABLE_TO_VERIFY_LEAF_SIGNATURE:
      case X509_V_ERR_DEPTH_ZERO_SELF_SIGNED_CERT:
      case X509_V_ERR_SELF_SIGNED_CERT_IN_CHAIN:
      case X509_V_ERR_CERT_UNTRUSTED:
      case X509_V_ERR_CERT_SIGNATURE_FAILURE:
        return failure(ClientError::kTls,
                       fmt::format("the certificate of {} is not signed by {} ({})", where, anchor, reason));
      default:
        return failure(ClientError::kTls,
                       fmt::format("the certificate of {} was refused: {} (trusting {})", where, reason, anchor));
    }
  }
  if (ec.category() == net::error::get_ssl_category() || ec.category() == ssl::error::get_stream_category()) {
    ERR_clear_error();
    const std::string reason = ec.message();
    const bool plain = reason.find("wrong version number") != std::string::npos ||
                       reason.find("packet length too long") != std::string::npos ||
                       reason.find("http request") != std::string::npos;
    return failure(ClientError::kTls, fmt::format("the TLS handshake with {} failed: {}{}", where, reason,
                                                  plain ? " (does it speak plain HTTP? then use http://)" : ""));
  }
  ERR_clear_error();
  if (ec == net::error::eof || ec == net::error::connection_reset) {
    return failure(ClientError::kTls, fmt::format("{} closed the connection during the TLS handshake ({}): does it "
                                                  "speak TLS?",
                                                  where, ec.message()));
  }
  return failure(ClientError::kIo, fmt::format("the TLS handshake with {} failed: {}", where, ec.message()));
}

// ---- one connection --------------------------------------------------------------------------

struct Connection {
  explicit Connection(beast::tcp_stream tcp) : stream(std::in_place_type<beast::tcp_stream>, std::move(tcp)) {}
  Connection(beast::tcp_stream tcp, ssl::context& context)
      : stream(std::in_place_type<TlsStream>, std::move(tcp), context) {}

  beast::tcp_stream& tcp() {
    return std::visit([](auto& s) -> beast::tcp_stream& { return beast::get_lowest_layer(s); }, stream);
  }

  std::variant<beast::tcp_stream, TlsStream> stream;
  beast::flat_buffer buffer;  // kept across the responses of the connection, as Beast requires
  std::string key;            // (host, port, tls): which requests may use it
  std::uint32_t requests = 0;
  RealClock::time_point idle_since;
};

std::string pool_key(const Url& url) { return fmt::format("{}|{}|{}", url.tls ? 's' : 'p', url.port, url.host); }

// False when an idle connection cannot carry another request: the peer closed it (or reset it),
// or sent something unasked (an alert before its close, say).
bool still_usable(Connection& connection) {
  tcp::socket& socket = connection.tcp().socket();
  if (!socket.is_open()) return false;
  error_code ec;
  socket.non_blocking(true, ec);
  if (ec) return false;
  char byte = 0;
  socket.receive(net::buffer(&byte, 1), tcp::socket::message_peek, ec);
  error_code ignored;
  socket.non_blocking(false, ignored);
  return ec == net::error::would_block || ec == net::error::try_again;
}

void close_connection(Connection& connection) {
  error_code ignored;
  tcp::socket& socket = connection.tcp().socket();
  socket.shutdown(tcp::socket::shutdown_both, ignored);
  socket.close(ignored);
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
  if (ec == bhttp::error::end_of_stream || ec == bhttp::error::partial_message || ec == ssl::error::stream_truncated) {
    return failure(ClientError::kIo, fmt::format("{} closed the connection before a complete response", where));
  }
  if (ec.category() == bhttp::make_error_code(bhttp::error::bad_version).category()) {
    return failure(ClientError::kProtocol, fmt::format("invalid HTTP response from {}: {}", where, ec.message()));
  }
  return failure(ClientError::kIo, fmt::format("reading the response from {} failed: {}", where, ec.message()));
}

struct Outcome {
  ClientResult result;
  bool answer_started = false;  // some byte of the answer arrived
  bool keep_alive = false;      // the answer lets the connection carry another request
};

// Writes `req` and reads the whole answer on a connected (and handshaken) stream.
template <typename Stream>
net::awaitable<Outcome> exchange_on(Stream& stream, beast::tcp_stream& tcp, beast::flat_buffer& buffer,
                                    const Request& req, const std::string& where, const ClientTimeouts& timeouts,
                                    std::uint64_t max_response_body) {
  Outcome out;
  tcp.expires_after(timeouts.write);
  auto [write_ec, written] = co_await bhttp::async_write(stream, req, kAwaitTuple);

  // Read even after a failed write: a server may answer before taking the whole body (413) and
  // close; that answer is worth more than the write error.
  bhttp::response_parser<bhttp::string_body> parser;
  parser.header_limit(kMaxResponseHeaderBytes);
  parser.body_limit(max_response_body);
  parser.skip(req.method() == Verb::head);  // the answer to HEAD announces a body it does not carry
  tcp.expires_after(timeouts.read);
  auto [read_ec, read] = co_await bhttp::async_read(stream, buffer, parser, kAwaitTuple);
  out.answer_started = parser.got_some() || buffer.size() > 0;
  if (read_ec && write_ec) {
    if (write_ec == beast::error::timeout) {
      out.result = failure(ClientError::kTimeout, fmt::format("sending the request to {} timed out after {} ms", where,
                                                              timeouts.write.count()));
    } else if (write_ec == net::error::operation_aborted) {
      out.result = failure(ClientError::kCancelled, fmt::format("request to {} was cancelled", where));
    } else {
      out.result =
          failure(ClientError::kIo, fmt::format("sending the request to {} failed: {}", where, write_ec.message()));
    }
    co_return out;
  }
  if (read_ec) {
    out.result = read_failure(read_ec, where, timeouts, max_response_body);
    co_return out;
  }
  out.keep_alive = !write_ec && parser.keep_alive();
  out.result.response = parser.release();
  co_return out;
}

// Runs `exchange` on `io` from the calling thread until it is over; rethrows what it threw.
ClientResult run_blocking(net::io_context& io, net::awaitable<ClientResult> exchange) {
  ClientResult result;
  std::exception_ptr error;
  net::co_spawn(io, std::move(exchange), [&](std::exception_ptr e, ClientResult r) {
    error = e;
    result = std::move(r);
    io.stop();  // do not wait for an abandoned name lookup
  });
  io.run();
  if (error) std::rethrow_exception(error);
  return result;
}

}  // namespace

// ---- Client ------------------------------------------------------------------------------------

struct Client::Impl {
  Impl(net::any_io_executor executor, ClientOptions options)
      : executor(std::move(executor)), options(std::move(options)) {
    if (this->options.tls) {
      if (this->options.tls->ca_fingerprint) pinned = *this->options.tls->ca_fingerprint;
      auto made = make_context(*this->options.tls, &pinned);
      if (made) {
        context = std::move(made).value();
      } else {
        context_problem = made.error().message;
      }
    }
    if (this->options.max_requests_per_connection == 0) this->options.max_requests_per_connection = 1;
  }

  net::awaitable<ClientResult> request(Url url, Request req, std::uint64_t max_response_body);
  net::awaitable<std::unique_ptr<Connection>> open(const Url& url, const std::string& where, ClientResult& failed);
  std::unique_ptr<Connection> take_idle(const std::string& key);
  void give_back(std::unique_ptr<Connection> connection);

  net::any_io_executor executor;
  ClientOptions options;
  Fingerprint pinned{};                          // the verify callback's argument: lives as long as context
  std::unique_ptr<ssl::context> context;         // null without options.tls or when it is unusable
  std::string context_problem;                   // why there is no context although options.tls is set
  std::deque<std::unique_ptr<Connection>> idle;  // oldest first
  ClientStats counters;
};

std::unique_ptr<Connection> Client::Impl::take_idle(const std::string& key) {
  const auto now = RealClock::now();
  // Too old to trust the server still keeps them: closed.
  std::erase_if(idle, [&](const std::unique_ptr<Connection>& c) { return now - c->idle_since >= options.max_idle; });
  for (auto it = idle.end(); it != idle.begin();) {
    --it;
    if ((*it)->key != key) continue;
    std::unique_ptr<Connection> connection = std::move(*it);
    it = idle.erase(it);
    if (still_usable(*connection)) return connection;
  }
  return nullptr;
}

void Client::Impl::give_back(std::unique_ptr<Connection> connection) {
  const auto now = RealClock::now();
  std::erase_if(idle, [&](const std::unique_ptr<Connection>& c) { return now - c->idle_since >= options.max_idle; });
  connection->idle_since = now;
  idle.push_back(std::move(connection));
  while (idle.size() > options.max_idle_connections) idle.pop_front();
}

net::awaitable<std::unique_ptr<Connection>> Client::Impl::open(const Url& url, const std::string& where,
                                                               ClientResult& failed) {
  const ClientTimeouts& timeouts = options.timeouts;
  const auto connect_deadline = RealClock::now() + timeouts.connect;
  std::vector<tcp::endpoint> endpoints;
  if (std::optional<ClientResult> unresolved = co_await resolve(url, connect_deadline, endpoints)) {
    failed = std::move(*unresolved);
    co_return nullptr;
  }

  beast::tcp_stream tcp_stream(executor);
  tcp_stream.expires_at(connect_deadline);
  auto [connect_ec, endpoint] = co_await tcp_stream.async_connect(endpoints, kAwaitTuple);
  if (connect_ec == beast::error::timeout) {
    failed = failure(ClientError::kTimeout,
                     fmt::format("connecting to {} timed out after {} ms", where, timeouts.connect.count()));
    co_return nullptr;
  }
  if (connect_ec == net::error::operation_aborted) {
    failed = failure(ClientError::kCancelled, fmt::format("connecting to {} was cancelled", where));
    co_return nullptr;
  }
  if (connect_ec) {
    failed = failure(ClientError::kConnect, fmt::format("cannot connect to {}: {}", where, connect_ec.message()));
    co_return nullptr;
  }
  error_code ignored;
  tcp_stream.socket().set_option(tcp::no_delay(true), ignored);
  ++counters.connections_opened;

  std::unique_ptr<Connection> connection;
  if (!url.tls) {
    connection = std::make_unique<Connection>(std::move(tcp_stream));
  } else {
    connection = std::make_unique<Connection>(std::move(tcp_stream), *context);
    TlsStream& stream = std::get<TlsStream>(connection->stream);
    SSL* handle = stream.native_handle();
    X509_VERIFY_PARAM* param = SSL_get0_param(handle);
    X509_VERIFY_PARAM_set_hostflags(param, X509_CHECK_FLAG_NO_PARTIAL_WILDCARDS);
    const bool set = is_ip_address(url.host) ? X509_VERIFY_PARAM_set1_ip_asc(param, url.host.c_str()) == 1
                                             : SSL_set_tlsext_host_name(handle, url.host.c_str()) == 1 &&
                                                   SSL_set1_host(handle, url.host.c_str()) == 1;
    if (!set) {
      failed = failure(ClientError::kTls,
                       fmt::format("cannot set up TLS for {}: {}", where, openssl_reason("invalid host name")));
      co_return nullptr;
    }
    connection->tcp().expires_after(timeouts.handshake);
    auto [handshake_ec] = co_await stream.async_handshake(ssl::stream_base::client, kAwaitTuple);
    if (handshake_ec) {
      ++counters.tls_failures;
      failed = handshake_failure(handshake_ec, handle, url, where, *options.tls, timeouts);
      co_return nullptr;
    }
    ++counters.tls_handshakes;
  }
  connection->key = pool_key(url);
  co_return connection;
}

net::awaitable<ClientResult> Client::Impl::request(Url url, Request req, std::uint64_t max_response_body) {
  ++counters.requests;
  const std::string where = url.to_string();
  if (url.tls && !options.tls) {
    co_return failure(ClientError::kConnect,
                      fmt::format("{} is an https:// URL, but no CA to trust was given (--ca-file)", where));
  }
  if (url.tls && !context) co_return failure(ClientError::kTls, context_problem);

  req.version(11);
  req.set(bhttp::field::host, url.host_header());
  if (req.count(bhttp::field::user_agent) == 0) req.set(bhttp::field::user_agent, kUserAgent);
  req.prepare_payload();
  const std::string key = pool_key(url);

  for (int attempt = 0;; ++attempt) {
    std::unique_ptr<Connection> connection = attempt == 0 ? take_idle(key) : nullptr;
    const bool reused = connection != nullptr;
    if (reused) {
      ++counters.reuses;
    } else {
      ClientResult failed;
      connection = co_await open(url, where, failed);
      if (!connection) co_return failed;
    }
    ++connection->requests;
    const bool last = connection->requests >= options.max_requests_per_connection || options.max_idle_connections == 0;
    req.keep_alive(!last);

    Outcome out = co_await std::visit(
        [&](auto& stream) {
          return exchange_on(stream, connection->tcp(), connection->buffer, req, where, options.timeouts,
                             max_response_body);
        },
        connection->stream);
    if (out.result.ok()) {
      if (out.keep_alive && !last) {
        give_back(std::move(connection));
      } else {
        close_connection(*connection);
      }
      co_return std::move(out.result);
    }
    close_connection(*connection);
    // The server closed the kept connection while it was idle (or just then): the request did not
    // reach it, or it did not answer; once more on a new connection.
    const bool cancelled = (co_await net::this_coro::cancellation_state).cancelled() != net::cancellation_type::none;
    if (reused && attempt == 0 && !out.answer_started && out.result.error == ClientError::kIo && !cancelled) {
      ++counters.retries;
      continue;
    }
    co_return std::move(out.result);
  }
}

Client::Client(net::any_io_executor executor, ClientOptions options)
    : impl_(std::make_shared<Impl>(std::move(executor), std::move(options))) {}

Client::~Client() = default;

net::awaitable<ClientResult> Client::request(Url url, Request req, std::uint64_t max_response_body) {
  const std::shared_ptr<Impl> impl = impl_;  // alive until the exchange is over
  const std::string where = url.to_string();
  try {
    co_return co_await impl->request(std::move(url), std::move(req), max_response_body);
  } catch (const boost::system::system_error& e) {
    // Asio throws this from a co_await once the awaiting coroutine has been cancelled.
    if (e.code() != net::error::operation_aborted) throw;
  }
  co_return failure(ClientError::kCancelled, fmt::format("request to {} was cancelled", where));
}

ClientStats Client::stats() const {
  ClientStats stats = impl_->counters;
  stats.idle_connections = impl_->idle.size();
  return stats;
}

const ClientOptions& Client::options() const { return impl_->options; }

void Client::close_idle() { impl_->idle.clear(); }

// ---- SyncClient --------------------------------------------------------------------------------

struct SyncClient::Impl {
  explicit Impl(ClientOptions options) : client(io.get_executor(), std::move(options)) {}
  net::io_context io{1};
  Client client;  // after io: destroyed (its sockets closed) before it
};

SyncClient::SyncClient(ClientOptions options) : impl_(std::make_unique<Impl>(std::move(options))) {}

SyncClient::~SyncClient() = default;

ClientResult SyncClient::request(const Url& url, Request req, std::uint64_t max_response_body) {
  impl_->io.restart();
  return run_blocking(impl_->io, impl_->client.request(url, std::move(req), max_response_body));
}

ClientStats SyncClient::stats() const { return impl_->client.stats(); }

// ---- the rest ----------------------------------------------------------------------------------

std::string Url::to_string() const { return fmt::format("{}{}", tls ? kTlsScheme : kScheme, host_header()); }

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
  Url url;
  std::string_view rest;
  if (starts_with_icase(text, kScheme)) {
    rest = text.substr(kScheme.size());
  } else if (starts_with_icase(text, kTlsScheme)) {
    rest = text.substr(kTlsScheme.size());
    url.tls = true;
    url.port = kDefaultTlsPort;
  } else {
    return util::Error(fmt::format("URL '{}' must start with http:// or https://", text));
  }
  if (!rest.empty() && rest.back() == '/') rest.remove_suffix(1);
  if (rest.find_first_of("/?#@") != std::string_view::npos) {
    return util::Error(
        fmt::format("URL '{}' must be http(s)://host[:port], without a path, query, fragment or user name", text));
  }

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

util::Status check_client_tls(const ClientTls& tls) {
  const Fingerprint pinned = tls.ca_fingerprint.value_or(Fingerprint{});
  auto context = make_context(tls, &pinned);
  if (!context) return context.error();
  return util::Status();
}

std::string_view to_string(ClientError error) {
  // The enum's order.
  constexpr std::string_view kNames[] = {"none",     "connect", "timeout",   "too_large",
                                         "protocol", "io",      "cancelled", "tls"};
  const auto i = static_cast<std::size_t>(error);
  return i < std::size(kNames) ? kNames[i] : "unknown";
}

net::awaitable<ClientResult> request(Url url, Request req, ClientTimeouts timeouts, std::uint64_t max_response_body,
                                     std::optional<ClientTls> tls) {
  ClientOptions options;
  options.timeouts = timeouts;
  options.tls = std::move(tls);
  options.max_idle_connections = 0;
  options.max_requests_per_connection = 1;
  Client client(co_await net::this_coro::executor, std::move(options));
  co_return co_await client.request(std::move(url), std::move(req), max_response_body);
}

ClientResult request_sync(const Url& url, Request req, const ClientTimeouts& timeouts, std::uint64_t max_response_body,
                          const std::optional<ClientTls>& tls) {
  net::io_context io;
  return run_blocking(io, request(url, std::move(req), timeouts, max_response_body, tls));
}

}  // namespace dtraced::http
