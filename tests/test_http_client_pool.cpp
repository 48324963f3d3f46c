// dtraced::http::Client: kept-alive connections (reuse, the server closing an idle one, the
// retry on a fresh connection, the per-connection request cap, concurrency, cancellation) against
// the plain http::Server and against hand-driven servers on loopback; and the client side of TLS
// (trust, host names, validity, a plain server, a handshake that never ends, a pinned CA
// fingerprint, SNI) against the HTTPS http::Server, with certificates made in memory by src/tls.
#include <ctime>
#include <mutex>
#include <variant>

#include <boost/asio/detached.hpp>
#include <boost/asio/experimental/awaitable_operators.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/beast/http/write.hpp>
#include <openssl/ssl.h>

#include "http/tls_server.h"
#include "http_testing.h"
#include "tls/material.h"

using namespace http_testing;
using dtraced::http::Client;
using dtraced::http::ClientError;
using dtraced::http::ClientOptions;
using dtraced::http::ClientTls;
using dtraced::http::SyncClient;

namespace {

namespace beast = boost::beast;
using namespace net::experimental::awaitable_operators;

Request echo(std::string json) {
  return dtraced::http::make_request(Verb::post, "/echo", std::move(json), dtraced::http::kJsonContentType);
}

ClientOptions bounded_options() {
  ClientOptions options;
  options.timeouts = ClientTimeouts{kBound, kBound, kBound, kBound};
  return options;
}

// Runs `body` (a coroutine using `client`) on a private io_context until everything it started
// is over; the Client lives on that io_context.
template <typename Body>
void run_on_client(ClientOptions options, Body body) {
  net::io_context io;
  Client client(io.get_executor(), std::move(options));
  std::exception_ptr failed;
  net::co_spawn(io, body(client), [&](std::exception_ptr e) { failed = e; });
  io.run_for(3 * kBound);
  REQUIRE(io.stopped());
  if (failed) std::rethrow_exception(failed);
}

// A server driven by a script, for what the dtraced server does not do on purpose: each accepted
// connection reads requests and, for its n-th request (from 0), does what `script(connection,
// n)` says: answer normally, close without a byte, or send half an answer and close.
enum class Act { kAnswer, kCloseSilently, kHalfAnswerThenClose };

class ScriptedServer {
 public:
  using Script = std::function<Act(int connection, int request)>;

  explicit ScriptedServer(Script script)
      : script_(std::move(script)), acceptor_(io_, tcp::endpoint(net::ip::make_address("127.0.0.1"), 0)) {
    net::co_spawn(io_, accept_loop(), net::detached);
    thread_ = std::thread([this] { io_.run(); });
  }
  ~ScriptedServer() {
    net::post(io_, [this] {
      error_code ignored;
      acceptor_.close(ignored);
    });
    io_.stop();
    thread_.join();
  }

  Url url() const { return Url{"127.0.0.1", acceptor_.local_endpoint().port()}; }
  int accepted() const { return accepted_.load(); }

 private:
  net::awaitable<void> accept_loop() {
    for (;;) {
      auto [ec, socket] = co_await acceptor_.async_accept(net::as_tuple(net::use_awaitable));
      if (ec) co_return;
      net::co_spawn(io_, session(std::move(socket), accepted_++), net::detached);
    }
  }

  net::awaitable<void> session(tcp::socket socket, int connection) {
    beast::flat_buffer buffer;
    for (int n = 0;; ++n) {
      Request req;
      auto [read_ec, read] = co_await bhttp::async_read(socket, buffer, req, net::as_tuple(net::use_awaitable));
      if (read_ec) co_return;
      const Act act = script_(connection, n);
      if (act == Act::kCloseSilently) co_return;
      if (act == Act::kHalfAnswerThenClose) {
        static constexpr std::string_view kHalf = "HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nabc";
        co_await net::async_write(socket, net::buffer(kHalf), net::as_tuple(net::use_awaitable));
        co_return;
      }
      Response res = dtraced::http::make_text_response(Status::ok, fmt::format("{}/{}", connection, n));
      res.keep_alive(req.keep_alive());
      auto [write_ec, written] = co_await bhttp::async_write(socket, res, net::as_tuple(net::use_awaitable));
      if (write_ec || !req.keep_alive()) co_return;
    }
  }

  Script script_;
  net::io_context io_;
  tcp::acceptor acceptor_;
  std::atomic<int> accepted_{0};
  std::thread thread_;
};

}  // namespace

TEST_CASE("pool: successive requests reuse one connection", "[http][pool]") {
  TestServer server(generous_limits(), routes());
  SyncClient client(bounded_options());
  for (int i = 0; i < 3; ++i) {
    const ClientResult r = client.request(server.url(), echo(fmt::format(R"({{"i":{}}})", i)), kMaxResponse);
    REQUIRE(r.ok());
    CHECK(json_body(r.response).at("i") == i);
  }
  const auto stats = client.stats();
  CHECK(stats.requests == 3);
  CHECK(stats.connections_opened == 1);
  CHECK(stats.reuses == 2);
  CHECK(stats.idle_connections == 1);
  CHECK(server.metrics().requests == 3);
  CHECK(server.metrics().open_connections == 1);  // the server keeps it too
}

TEST_CASE("pool: a connection the server closed while idle is replaced", "[http][pool]") {
  ServerLimits limits = generous_limits();
  limits.idle_keepalive_timeout = 50ms;
  TestServer server(limits, routes());
  SyncClient client(bounded_options());
  REQUIRE(client.request(server.url(), echo(R"({"n":1})"), kMaxResponse).ok());
  REQUIRE(eventually([&] { return server.metrics().open_connections == 0; }));  // closed at its idle deadline
  const ClientResult second = client.request(server.url(), echo(R"({"n":2})"), kMaxResponse);
  REQUIRE(second.ok());
  CHECK(json_body(second.response).at("n") == 2);
  CHECK(client.stats().connections_opened == 2);
  CHECK(server.metrics().requests == 2);
}

TEST_CASE("pool: a reused connection that fails before any answer is retried once, fresh", "[http][pool]") {
  // Connection 0 answers its first request, then closes on the second as if it had gone idle.
  ScriptedServer server(
      [](int connection, int request) { return connection == 0 && request == 1 ? Act::kCloseSilently : Act::kAnswer; });
  SyncClient client(bounded_options());
  ClientResult r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/a"), kMaxResponse);
  REQUIRE(r.ok());
  CHECK(r.response.body() == "0/0");
  r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/b"), kMaxResponse);
  INFO(r.message);
  REQUIRE(r.ok());
  CHECK(r.response.body() == "1/0");  // on a new connection
  CHECK(client.stats().retries == 1);
  CHECK(client.stats().connections_opened == 2);
  CHECK(server.accepted() == 2);
}

TEST_CASE("pool: no retry once the answer began, and at most one retry", "[http][pool]") {
  SECTION("half an answer") {
    ScriptedServer server([](int connection, int request) {
      return connection == 0 && request == 1 ? Act::kHalfAnswerThenClose : Act::kAnswer;
    });
    SyncClient client(bounded_options());
    REQUIRE(client.request(server.url(), dtraced::http::make_request(Verb::get, "/a"), kMaxResponse).ok());
    const ClientResult r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/b"), kMaxResponse);
    CHECK(r.error == ClientError::kIo);
    CHECK_THAT(r.message, Catch::Contains("closed the connection"));
    CHECK(client.stats().retries == 0);
    CHECK(server.accepted() == 1);
  }
  SECTION("the fresh connection fails too") {
    ScriptedServer server([](int connection, int request) {
      return connection == 0 && request == 0 ? Act::kAnswer : Act::kCloseSilently;
    });
    SyncClient client(bounded_options());
    REQUIRE(client.request(server.url(), dtraced::http::make_request(Verb::get, "/a"), kMaxResponse).ok());
    const ClientResult r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/b"), kMaxResponse);
    CHECK(r.error == ClientError::kIo);
    CHECK(client.stats().retries == 1);
    CHECK(server.accepted() == 2);
  }
  SECTION("a fresh connection is never retried") {
    ScriptedServer server([](int, int) { return Act::kCloseSilently; });
    SyncClient client(bounded_options());
    const ClientResult r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/a"), kMaxResponse);
    CHECK(r.error == ClientError::kIo);
    CHECK(client.stats().retries == 0);
    CHECK(server.accepted() == 1);
  }
}

TEST_CASE("pool: max_requests_per_connection is honoured", "[http][pool]") {
  ScriptedServer server([](int, int) { return Act::kAnswer; });
  ClientOptions options = bounded_options();
  options.max_requests_per_connection = 2;
  SyncClient client(options);
  std::vector<std::string> bodies;
  for (int i = 0; i < 5; ++i) {
    const ClientResult r = client.request(server.url(), dtraced::http::make_request(Verb::get, "/"), kMaxResponse);
    REQUIRE(r.ok());
    bodies.push_back(r.response.body());
  }
  // Two requests per connection; the second of each said Connection: close.
  CHECK(bodies == std::vector<std::string>{"0/0", "0/1", "1/0", "1/1", "2/0"});
  CHECK(client.stats().connections_opened == 3);
  CHECK(client.stats().retries == 0);
}

TEST_CASE("pool: an idle connection older than max_idle is not reused", "[http][pool]") {
  TestServer server(generous_limits(), routes());
  ClientOptions options = bounded_options();
  options.max_idle = 1ms;
  SyncClient client(options);
  REQUIRE(client.request(server.url(), echo("{}"), kMaxResponse).ok());
  std::this_thread::sleep_for(20ms);
  REQUIRE(client.request(server.url(), echo("{}"), kMaxResponse).ok());
  CHECK(client.stats().connections_opened == 2);
  CHECK(client.stats().reuses == 0);
}

TEST_CASE("pool: N concurrent requests use at most N connections, then reuse them", "[http][pool]") {
  constexpr int kConcurrent = 4;
  Gate gate;
  TestServer server(generous_limits(), routes(&gate));
  ClientOptions options = bounded_options();
  options.max_idle_connections = 3;  // one fewer than the connections: the oldest idle one is closed
  dtraced::http::ClientStats after_slow;
  dtraced::http::ClientStats after_fast;
  std::thread opener([&] {
    REQUIRE(eventually([&] { return server.metrics().open_connections == kConcurrent; }));
    open_gate(server.executor(), gate);
  });
  run_on_client(options, [&](Client& client) -> net::awaitable<void> {
    auto slow = [&]() -> net::awaitable<void> {
      const ClientResult r =
          co_await client.request(server.url(), dtraced::http::make_request(Verb::get, "/slow"), kMaxResponse);
      CHECK(r.ok());
    };
    co_await (slow() && slow() && slow() && slow());
    after_slow = client.stats();
    auto fast = [&]() -> net::awaitable<void> {
      const ClientResult r = co_await client.request(server.url(), echo("{}"), kMaxResponse);
      CHECK(r.ok());
    };
    co_await (fast() && fast() && fast());
    after_fast = client.stats();
  });
  opener.join();
  CHECK(after_slow.connections_opened == kConcurrent);
  CHECK(after_slow.idle_connections == 3);
  CHECK(after_fast.connections_opened == kConcurrent);  // three at once fit the three kept
  CHECK(after_fast.reuses == 3);
}

TEST_CASE("pool: a cancelled request ends its connection, the next one works", "[http][pool]") {
  Gate gate;
  TestServer server(generous_limits(), routes(&gate));
  dtraced::http::ClientStats stats;
  run_on_client(bounded_options(), [&](Client& client) -> net::awaitable<void> {
    const ClientResult warm = co_await client.request(server.url(), echo("{}"), kMaxResponse);
    CHECK(warm.ok());
    net::steady_timer timer(co_await net::this_coro::executor);
    timer.expires_after(50ms);
    auto raced =
        co_await (client.request(server.url(), dtraced::http::make_request(Verb::get, "/slow"), kMaxResponse) ||
                  timer.async_wait(net::use_awaitable));
    CHECK(raced.index() == 1);                    // the timer won; the request was cancelled
    CHECK(client.stats().idle_connections == 0);  // its connection was not kept
    open_gate(server.executor(), gate);
    const ClientResult after = co_await client.request(server.url(), echo(R"({"after":1})"), kMaxResponse);
    CHECK(after.ok());
    stats = client.stats();
  });
  CHECK(stats.connections_opened == 2);  // the warm one (cancelled on its second request), then a new one
  CHECK(stats.reuses == 1);
}

TEST_CASE("free request_sync still closes its connection", "[http][pool]") {
  TestServer server(generous_limits(), routes());
  REQUIRE(post_echo(server.url(), "{}").ok());
  CHECK(eventually([&] { return server.metrics().open_connections == 0; }));
}

// ---- TLS ------------------------------------------------------------------------------------

namespace {

using dtraced::tls::CertSpec;
using dtraced::tls::KeyPair;

const std::int64_t kNow = static_cast<std::int64_t>(std::time(nullptr));

// A server certificate for `dns` and `ips`, valid from an hour ago for a day unless told.
CertSpec leaf_spec(std::string cn, std::vector<std::string> dns, std::vector<std::string> ips,
                   std::int64_t from = kNow - 3600, std::int64_t to = kNow + 86'400) {
  CertSpec s;
  s.common_name = std::move(cn);
  s.dns_names = std::move(dns);
  s.ip_addresses = std::move(ips);
  s.not_before_unix = from;
  s.not_after_unix = to;
  return s;
}

CertSpec ca_spec(std::string cn) { return leaf_spec(std::move(cn), {}, {}, kNow - 3600, kNow + 30 * 86'400); }

// The certificates the tests use, made once in memory: a CA and, signed by it, a server
// certificate for localhost and 127.0.0.1, one for another name, and an expired one for
// localhost and 127.0.0.1; and another CA.
struct Pki {
  KeyPair ca = *dtraced::tls::make_self_signed_ca(ca_spec("test CA"));
  KeyPair other_ca = *dtraced::tls::make_self_signed_ca(ca_spec("other CA"));
  KeyPair server = *dtraced::tls::issue(ca, leaf_spec("server", {"localhost"}, {"127.0.0.1"}));
  KeyPair elsewhere = *dtraced::tls::issue(ca, leaf_spec("elsewhere", {"elsewhere.example"}, {}));
  KeyPair expired =
      *dtraced::tls::issue(ca, leaf_spec("expired", {"localhost"}, {"127.0.0.1"}, kNow - 7200, kNow - 3600));
};

const Pki& pki() {
  static const Pki p;
  return p;
}

// Trust in `ca`, as if read from a file called `source` (named in errors).
ClientTls trust(const KeyPair& ca, std::string source) {
  ClientTls tls;
  tls.ca_pem = ca.cert_pem;
  tls.ca_source = std::move(source);
  return tls;
}

ClientTls trust_ca() { return trust(pki().ca, "ca.pem"); }

// The HTTPS http::Server on 127.0.0.1, on an ephemeral port, with its io_context on a thread of
// its own. It presents `leaf` followed by the test CA and answers every request with its target.
// It records the SNI name of every ClientHello ("" for none) through a server-name callback on its
// context.
class HttpsServer {
 public:
  explicit HttpsServer(const KeyPair& leaf)
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), 0, generous_limits(), answer_target(), {}, {},
                dtraced::util::real_clock(), context(leaf, this)) {
    REQUIRE(!server_.start());
    REQUIRE(server_.port() != 0);
    thread_ = std::thread([this] { io_.run(); });
  }
  ~HttpsServer() {
    net::co_spawn(io_, server_.stop(1s), net::use_future).wait_for(kBound);
    work_.reset();
    io_.stop();
    thread_.join();
  }
  HttpsServer(const HttpsServer&) = delete;
  HttpsServer& operator=(const HttpsServer&) = delete;

  Url url(std::string host = "127.0.0.1") const { return Url{std::move(host), server_.port(), true}; }
  dtraced::http::ServerMetrics metrics() const { return server_.metrics(); }
  // The SNI names clients sent, in order ("" for none).
  std::vector<std::string> server_names() const {
    std::lock_guard lock(mutex_);
    return server_names_;
  }

 private:
  static Server::Handler answer_target() {
    return [](Request req) -> net::awaitable<Response> {
      co_return dtraced::http::make_text_response(Status::ok, std::string(req.target()));
    };
  }

  static std::shared_ptr<net::ssl::context> context(const KeyPair& leaf, HttpsServer* self) {
    auto made = dtraced::http::make_server_tls_context(
        dtraced::http::ServerTlsConfig{leaf.cert_pem + pki().ca.cert_pem, leaf.key_pem, ""});
    INFO((made.ok() ? std::string() : made.error().message));
    REQUIRE(made.ok());
    std::shared_ptr<net::ssl::context> ctx = *made;
    SSL_CTX_set_tlsext_servername_arg(ctx->native_handle(), self);
    SSL_CTX_set_tlsext_servername_callback(ctx->native_handle(), &HttpsServer::note_server_name);
    return ctx;
  }

  // Runs on the server's thread during each handshake.
  static int note_server_name(SSL* ssl, int*, void* arg) {
    auto* self = static_cast<HttpsServer*>(arg);
    const char* name = SSL_get_servername(ssl, TLSEXT_NAMETYPE_host_name);
    std::lock_guard lock(self->mutex_);
    self->server_names_.emplace_back(name != nullptr ? name : "");
    return SSL_TLSEXT_ERR_OK;
  }

  mutable std::mutex mutex_;
  std::vector<std::string> server_names_;  // guarded by mutex_
  net::io_context io_;
  net::executor_work_guard<net::io_context::executor_type> work_ = net::make_work_guard(io_);
  Server server_;
  std::thread thread_;
};

ClientOptions tls_options(ClientTls tls) {
  ClientOptions options = bounded_options();
  options.tls = std::move(tls);
  return options;
}

Request get(std::string_view target) { return dtraced::http::make_request(Verb::get, target); }

}  // namespace

TEST_CASE("tls: requests over TLS, kept alive: one handshake", "[http][pool][tls]") {
  HttpsServer server(pki().server);
  for (const std::string host : {"127.0.0.1", "localhost"}) {
    INFO(host);
    SyncClient client(tls_options(trust_ca()));
    for (int i = 0; i < 3; ++i) {
      const ClientResult r = client.request(server.url(host), get(fmt::format("/n{}", i)), kMaxResponse);
      INFO(r.message);
      REQUIRE(r.ok());
      CHECK(r.response.body() == fmt::format("/n{}", i));
    }
    CHECK(client.stats().tls_handshakes == 1);
    CHECK(client.stats().reuses == 2);
  }
  CHECK(server.metrics().tls_handshakes == 2);
  CHECK(server.metrics().keepalive_reuses == 4);
  // SNI names a DNS name, never an address.
  CHECK(server.server_names() == std::vector<std::string>{"", "localhost"});
  // The one-shot function speaks TLS too.
  const ClientResult once =
      dtraced::http::request_sync(server.url(), get("/once"), kTimeouts, kMaxResponse, trust_ca());
  INFO(once.message);
  CHECK(once.ok());
  CHECK(once.response.body() == "/once");
}

TEST_CASE("tls: a certificate from another CA or for another name is refused, saying why", "[http][pool][tls]") {
  HttpsServer server(pki().server);
  HttpsServer elsewhere(pki().elsewhere);

  SECTION("another CA") {
    SyncClient client(tls_options(trust(pki().other_ca, "/etc/dtraced/other-ca.pem")));
    const ClientResult r = client.request(server.url(), get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTls);
    CHECK_THAT(r.message, Catch::Contains("is not signed by the CA in /etc/dtraced/other-ca.pem"));
    CHECK(client.stats().tls_failures == 1);
  }
  SECTION("another name") {
    SyncClient client(tls_options(trust_ca()));
    const ClientResult r = client.request(elsewhere.url(), get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTls);
    CHECK_THAT(r.message, Catch::Contains("does not name 127.0.0.1") && Catch::Contains("--tls-name 127.0.0.1"));
    const ClientResult by_name = client.request(server.url("localhost"), get("/"), kMaxResponse);
    INFO(by_name.message);
    CHECK(by_name.ok());
  }
  SECTION("no CA given") {
    SyncClient client(bounded_options());
    const ClientResult r = client.request(server.url(), get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kConnect);
    CHECK_THAT(r.message, Catch::Contains("--ca-file"));
  }
  SECTION("a CA file that holds no certificate") {
    ClientTls tls;
    tls.ca_pem = "not a certificate";
    tls.ca_source = "/etc/dtraced/ca.pem";
    const auto checked = dtraced::http::check_client_tls(tls);
    REQUIRE_FALSE(checked);
    CHECK_THAT(checked.error().message, Catch::Contains("/etc/dtraced/ca.pem holds no PEM certificate"));
    SyncClient client(tls_options(tls));
    const ClientResult r = client.request(server.url(), get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTls);
    CHECK_THAT(r.message, Catch::Contains("/etc/dtraced/ca.pem"));
  }
}

TEST_CASE("tls: an expired server certificate is refused, saying so", "[http][pool][tls]") {
  HttpsServer server(pki().expired);
  SyncClient client(tls_options(trust_ca()));
  for (const std::string host : {"127.0.0.1", "localhost"}) {
    INFO(host);
    const ClientResult r = client.request(server.url(host), get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTls);
    CHECK_THAT(r.message, Catch::Contains("is not valid now") && Catch::Contains("expired") &&
                              Catch::Contains("check both clocks"));
  }
  CHECK(client.stats().tls_handshakes == 0);
  CHECK(client.stats().tls_failures == 2);
  CHECK(server.metrics().requests == 0);
}

TEST_CASE("tls: a pinned CA fingerprint is trusted when the server sends that CA", "[http][pool][tls]") {
  HttpsServer server(pki().server);
  HttpsServer elsewhere(pki().elsewhere);
  const auto fingerprint = dtraced::tls::fingerprint_of_pem(pki().ca.cert_pem);
  REQUIRE(fingerprint.ok());
  ClientTls pinned;
  pinned.ca_fingerprint = *fingerprint;
  REQUIRE(dtraced::http::check_client_tls(pinned));
  SyncClient client(tls_options(pinned));
  const ClientResult r = client.request(server.url(), get("/enroll"), kMaxResponse);
  INFO(r.message);
  CHECK(r.ok());
  CHECK(r.response.body() == "/enroll");
  // The name is still checked.
  const ClientResult wrong_name = client.request(elsewhere.url(), get("/"), kMaxResponse);
  CHECK(wrong_name.error == ClientError::kTls);
  CHECK_THAT(wrong_name.message, Catch::Contains("does not name"));
  // Another fingerprint: refused.
  ClientTls other = pinned;
  (*other.ca_fingerprint)[0] ^= 1;
  SyncClient wrong(tls_options(other));
  const ClientResult refused = wrong.request(server.url(), get("/"), kMaxResponse);
  CHECK(refused.error == ClientError::kTls);
  CHECK_THAT(refused.message, Catch::Contains("not signed by the CA of the join code's fingerprint"));
}

TEST_CASE("tls: https to a plain HTTP server, and a handshake that never ends", "[http][pool][tls]") {
  ClientTls tls;
  tls.ca_fingerprint = std::array<std::uint8_t, 32>{};  // any anchor will do: no handshake completes
  SECTION("plain server") {
    TestServer server(generous_limits(), routes());
    SyncClient client(tls_options(tls));
    const ClientResult r = client.request(Url{"127.0.0.1", server.port(), true}, get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTls);
    CHECK_THAT(r.message, Catch::Contains("TLS handshake") && Catch::Contains("plain HTTP"));
  }
  SECTION("silent server") {
    net::io_context io;
    tcp::acceptor acceptor(io, tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));  // the kernel accepts
    ClientOptions options = tls_options(tls);
    options.timeouts.handshake = 100ms;
    SyncClient client(options);
    const ClientResult r =
        client.request(Url{"127.0.0.1", acceptor.local_endpoint().port(), true}, get("/"), kMaxResponse);
    CHECK(r.error == ClientError::kTimeout);
    CHECK_THAT(r.message, Catch::Contains("TLS handshake") && Catch::Contains("timed out"));
  }
}
