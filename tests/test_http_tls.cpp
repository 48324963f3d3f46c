// dtraced::http's TLS server over real loopback sockets, with certificates from src/tls and a
// client written here on OpenSSL directly (blocking sockets with kBound receive and send
// timeouts), so a test can do what no well-behaved client does: speak plain HTTP or garbage to
// the TLS port, stop after its ClientHello, present a foreign or expired certificate, try to
// renegotiate. Every wait is bounded (kBound, eventually); nothing asserts how long anything took.
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sys/socket.h>
#include <sys/time.h>
#include <unistd.h>

#include <ctime>
#include <fstream>
#include <iterator>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/ssl/context.hpp>
#include <boost/beast/http/parser.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>
#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include "http/tls_server.h"
#include "http_testing.h"
#include "temp_dir.h"
#include "tls/material.h"

using namespace http_testing;
using dtraced::tls::CertSpec;
using dtraced::tls::KeyPair;

namespace {

const std::int64_t kNow = static_cast<std::int64_t>(std::time(nullptr));

CertSpec spec(std::string cn, bool server, std::int64_t from = kNow - 3600, std::int64_t to = kNow + 86'400) {
  CertSpec s;
  s.common_name = std::move(cn);
  s.server = server;
  s.not_before_unix = from;
  s.not_after_unix = to;
  if (server) {
    s.dns_names = {"localhost"};
    s.ip_addresses = {"127.0.0.1"};
  }
  return s;
}

// The certificates the tests use, made once.
struct Pki {
  KeyPair ca = *dtraced::tls::make_self_signed_ca(spec("test CA", false));
  KeyPair server = *dtraced::tls::issue(ca, spec("localhost", true));
  KeyPair worker = *dtraced::tls::issue(ca, spec("worker-7", false));
  KeyPair expired_worker = *dtraced::tls::issue(ca, spec("old-worker", false, kNow - 7200, kNow - 3600));
  KeyPair foreign_ca = *dtraced::tls::make_self_signed_ca(spec("foreign CA", false));
  KeyPair intruder = *dtraced::tls::issue(foreign_ca, spec("intruder", false));
};

const Pki& pki() {
  static const Pki p;
  return p;
}

std::shared_ptr<net::ssl::context> server_context(bool ask_client_certs = true) {
  auto ctx = make_server_tls_context(
      ServerTlsConfig{pki().server.cert_pem, pki().server.key_pem, ask_client_certs ? pki().ca.cert_pem : ""});
  REQUIRE(ctx.ok());
  return *ctx;
}

// /whoami answers the client certificate name the server stamped ("" when none); the rest is
// http_testing's routes() (/slow waits for `gate`).
Server::Handler tls_routes(Gate* gate) {
  return [inner = routes(gate)](Request req) -> net::awaitable<Response> {
    if (req.target() == "/whoami") {
      co_return make_text_response(Status::ok, std::string(req[std::string(kClientCertHeader)]));
    }
    co_return co_await inner(std::move(req));
  };
}

// A TLS server on 127.0.0.1, on an ephemeral port, with its io_context on a thread of its own.
class TlsTestServer {
 public:
  explicit TlsTestServer(ServerLimits limits, std::shared_ptr<net::ssl::context> ctx = server_context(),
                         const dtraced::util::Clock& clock = dtraced::util::real_clock(),
                         Server::Authenticated authenticated = {})
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), 0, limits, tls_routes(&gate_), {},
                std::move(authenticated), clock, std::move(ctx)) {
    REQUIRE(!server_.start());
    thread_ = std::thread([this] { io_.run(); });
  }
  ~TlsTestServer() {
    net::co_spawn(io_, server_.stop(1s), net::use_future).wait_for(kBound);
    work_.reset();
    io_.stop();
    thread_.join();
  }
  std::uint16_t port() const { return server_.port(); }
  ServerMetrics metrics() const { return server_.metrics(); }
  Gate& gate() { return gate_; }
  net::any_io_executor executor() { return io_.get_executor(); }
  std::future<void> begin_stop(std::chrono::milliseconds grace) {
    return net::co_spawn(io_, server_.stop(grace), net::use_future);
  }

 private:
  net::io_context io_;
  net::executor_work_guard<net::io_context::executor_type> work_ = net::make_work_guard(io_);
  Gate gate_;
  Server server_;
  std::thread thread_;
};

template <typename T, void (*Free)(T*)>
struct Deleter {
  void operator()(T* p) const { Free(p); }
};
using SslCtxPtr = std::unique_ptr<SSL_CTX, Deleter<SSL_CTX, SSL_CTX_free>>;
using SslPtr = std::unique_ptr<SSL, Deleter<SSL, SSL_free>>;
using X509Ptr = std::unique_ptr<X509, Deleter<X509, X509_free>>;
using PkeyPtr = std::unique_ptr<EVP_PKEY, Deleter<EVP_PKEY, EVP_PKEY_free>>;

X509Ptr read_cert(const std::string& pem) {
  BIO* bio = BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size()));
  X509Ptr cert(PEM_read_bio_X509(bio, nullptr, nullptr, nullptr));
  BIO_free(bio);
  REQUIRE(cert);
  return cert;
}

PkeyPtr read_key(const std::string& pem) {
  BIO* bio = BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size()));
  PkeyPtr key(PEM_read_bio_PrivateKey(bio, nullptr, nullptr, nullptr));
  BIO_free(bio);
  REQUIRE(key);
  return key;
}

struct ClientOptions {
  const KeyPair* certificate = nullptr;  // a client certificate to present
  int max_version = 0;                   // e.g. TLS1_2_VERSION; 0: OpenSSL's highest
};

// A TLS client on a blocking socket whose every read and write gives up after kBound. It trusts
// the test CA and checks the server's certificate names 127.0.0.1.
class TlsClient {
 public:
  explicit TlsClient(std::uint16_t port, ClientOptions options = {}) {
    fd_ = ::socket(AF_INET, SOCK_STREAM, 0);
    REQUIRE(fd_ >= 0);
    timeval bound{static_cast<time_t>(std::chrono::duration_cast<std::chrono::seconds>(kBound).count()), 0};
    ::setsockopt(fd_, SOL_SOCKET, SO_RCVTIMEO, &bound, sizeof bound);
    ::setsockopt(fd_, SOL_SOCKET, SO_SNDTIMEO, &bound, sizeof bound);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::connect(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) == 0);

    ctx_.reset(SSL_CTX_new(TLS_client_method()));
    REQUIRE(ctx_);
    X509Ptr ca = read_cert(pki().ca.cert_pem);
    REQUIRE(X509_STORE_add_cert(SSL_CTX_get_cert_store(ctx_.get()), ca.get()) == 1);
    SSL_CTX_set_verify(ctx_.get(), SSL_VERIFY_PEER, nullptr);
    if (options.max_version != 0) SSL_CTX_set_max_proto_version(ctx_.get(), options.max_version);
    if (options.certificate != nullptr) {
      X509Ptr cert = read_cert(options.certificate->cert_pem);
      PkeyPtr key = read_key(options.certificate->key_pem);
      REQUIRE(SSL_CTX_use_certificate(ctx_.get(), cert.get()) == 1);
      REQUIRE(SSL_CTX_use_PrivateKey(ctx_.get(), key.get()) == 1);
    }
    ssl_.reset(SSL_new(ctx_.get()));
    REQUIRE(ssl_);
    REQUIRE(X509_VERIFY_PARAM_set1_ip_asc(SSL_get0_param(ssl_.get()), "127.0.0.1") == 1);
    SSL_set_fd(ssl_.get(), fd_);
  }
  ~TlsClient() {
    ssl_.reset();
    ::close(fd_);
  }
  TlsClient(const TlsClient&) = delete;
  TlsClient& operator=(const TlsClient&) = delete;

  // True when the handshake completed (on TLS 1.3 the server may still refuse the client's
  // certificate after this: the next read shows it).
  bool handshake() {
    ERR_clear_error();
    return SSL_connect(ssl_.get()) == 1;
  }

  bool write(std::string_view bytes) {
    std::size_t off = 0;
    while (off < bytes.size()) {
      const int n = SSL_write(ssl_.get(), bytes.data() + off, static_cast<int>(bytes.size() - off));
      if (n <= 0) return false;
      off += static_cast<std::size_t>(n);
    }
    return true;
  }

  // The next response, or nullopt when the connection failed or ended first.
  std::optional<Response> read_response() {
    bhttp::response_parser<bhttp::string_body> parser;
    for (;;) {
      while (!pending_.empty() && !parser.is_done()) {
        error_code ec;
        const std::size_t used = parser.put(net::buffer(pending_), ec);
        if (ec == bhttp::error::need_more) break;
        if (ec) return std::nullopt;
        pending_.erase(0, used);
        if (used == 0) break;
      }
      if (parser.is_done()) return parser.release();
      std::array<char, 4096> chunk;
      const int n = SSL_read(ssl_.get(), chunk.data(), static_cast<int>(chunk.size()));
      if (n <= 0) return std::nullopt;
      pending_.append(chunk.data(), static_cast<std::size_t>(n));
    }
  }

  std::optional<Response> get(std::string_view target, std::string_view extra_headers = "") {
    if (!write(fmt::format("GET {} HTTP/1.1\r\nHost: 127.0.0.1\r\n{}\r\n", target, extra_headers))) {
      return std::nullopt;
    }
    return read_response();
  }

  // True when the server ends the connection (close_notify, end of stream, reset, alert); false
  // when kBound passes with the connection still open.
  bool wait_closed() {
    std::array<char, 4096> chunk;
    for (;;) {
      errno = 0;
      const int n = SSL_read(ssl_.get(), chunk.data(), static_cast<int>(chunk.size()));
      if (n > 0) continue;
      const int error = SSL_get_error(ssl_.get(), n);
      return !(error == SSL_ERROR_SYSCALL && (errno == EAGAIN || errno == EWOULDBLOCK));
    }
  }

  SSL* ssl() { return ssl_.get(); }
  int fd() const { return fd_; }

 private:
  int fd_ = -1;
  SslCtxPtr ctx_;
  SslPtr ssl_;
  std::string pending_;
};

// One request on a fresh connection: the body of a 200 answer to /whoami, or nullopt.
std::optional<std::string> whoami(std::uint16_t port, ClientOptions options = {}) {
  TlsClient client(port, options);
  if (!client.handshake()) return std::nullopt;
  auto res = client.get("/whoami");
  if (!res || res->result() != Status::ok) return std::nullopt;
  return res->body();
}

ServerLimits tls_limits() {
  ServerLimits limits = generous_limits();
  limits.handshake_timeout = kBound;
  return limits;
}

// The first flight of a real TLS client, made on memory BIOs: a ClientHello.
std::string client_hello() {
  SslCtxPtr ctx(SSL_CTX_new(TLS_client_method()));
  SslPtr ssl(SSL_new(ctx.get()));
  BIO* in = BIO_new(BIO_s_mem());
  BIO* out = BIO_new(BIO_s_mem());
  SSL_set_bio(ssl.get(), in, out);
  REQUIRE(SSL_connect(ssl.get()) == -1);  // wants to read the ServerHello
  char* data = nullptr;
  const long n = BIO_get_mem_data(out, &data);
  REQUIRE(n > 0);
  REQUIRE(static_cast<unsigned char>(data[0]) == 0x16);  // a handshake record
  return std::string(data, static_cast<std::size_t>(n));
}

}  // namespace

TEST_CASE("tls server: a request over TLS, and two on one kept-alive connection", "[http][tls]") {
  TlsTestServer server(tls_limits());
  {
    TlsClient client(server.port());
    REQUIRE(client.handshake());
    REQUIRE(client.write(echo_request(R"({"n":1})")));
    auto first = client.read_response();
    REQUIRE(first);
    CHECK(first->result() == Status::ok);
    CHECK(json_body(*first).at("n").as_int64() == 1);
    CHECK(first->keep_alive());
    REQUIRE(client.write(echo_request(R"({"n":2})")));
    auto second = client.read_response();
    REQUIRE(second);
    CHECK(json_body(*second).at("n").as_int64() == 2);
  }
  const ServerMetrics m = server.metrics();
  CHECK(m.tls_handshakes == 1);
  CHECK(m.keepalive_reuses == 1);
  CHECK(m.requests == 2);
  CHECK(m.tls_handshake_failures == 0);
  CHECK(m.plain_on_tls == 0);
}

TEST_CASE("tls server: plain HTTP on the TLS port gets 400 naming https, and the port stays TLS", "[http][tls]") {
  TlsTestServer server(tls_limits());
  RawConnection raw(server.port());
  REQUIRE(raw.send(echo_request(R"({"n":1})")));
  auto res = raw.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::bad_request);
  CHECK_THAT(json_body(*res).at("error").as_string().c_str(),
             Catch::Contains(fmt::format("this port speaks HTTPS: use https://test:{}", server.port())));
  CHECK_FALSE(res->keep_alive());
  CHECK(raw.wait_closed());
  CHECK(server.metrics().plain_on_tls == 1);
  // Without a Host header the answer names the address the client reached.
  RawConnection bare(server.port());
  REQUIRE(bare.send("GET / HTTP/1.0\r\n\r\n"));
  auto named = bare.read_response();
  REQUIRE(named);
  CHECK_THAT(std::string(named->body()), Catch::Contains(fmt::format("https://127.0.0.1:{}", server.port())));
  CHECK(whoami(server.port()) == std::optional<std::string>(""));
}

TEST_CASE("tls server: garbage bytes close the connection and the next client is served", "[http][tls]") {
  TlsTestServer server(tls_limits());
  {
    RawConnection raw(server.port());
    // Bytes that are neither a TLS record (which starts 0x16) nor an HTTP method.
    std::string garbage;
    for (int i = 0; i < 512; ++i) garbage += static_cast<char>(1 + (i * 73) % 200);
    REQUIRE(raw.send(garbage));
    CHECK(raw.wait_closed());
  }
  CHECK(server.metrics().plain_on_tls == 1);
  {
    // A TLS record holding a ClientHello of 44 bytes of nonsense.
    RawConnection raw(server.port());
    REQUIRE(raw.send(std::string("\x16\x03\x01\x00\x30\x01\x00\x00\x2c", 9) + std::string(44, '\xee')));
    CHECK(raw.wait_closed());
  }
  CHECK(server.metrics().plain_on_tls == 1);
  CHECK(eventually([&] { return server.metrics().tls_handshake_failures == 1; }));
  CHECK(whoami(server.port()) == std::optional<std::string>(""));
  CHECK(eventually([&] { return server.metrics().open_connections == 0; }));
}

TEST_CASE("tls server: a ClientHello then silence is dropped at the handshake deadline", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.handshake_timeout = 300ms;
  TlsTestServer server(limits);
  RawConnection raw(server.port());
  REQUIRE(raw.send(client_hello()));
  // The server answers its flight, waits for ours, gives up and closes.
  CHECK(raw.wait_closed());
  CHECK(eventually([&] { return server.metrics().tls_handshake_failures == 1; }));
  CHECK(server.metrics().tls_handshakes == 0);
  CHECK(whoami(server.port()) == std::optional<std::string>(""));
  CHECK(server.metrics().tls_handshakes == 1);
}

TEST_CASE("tls server: client certificates are verified against the client CA", "[http][tls]") {
  TlsTestServer server(tls_limits());

  SECTION("a valid one: its CN is stamped, and a forged header is replaced") {
    CHECK(whoami(server.port(), {&pki().worker}) == std::optional<std::string>("worker-7"));
    TlsClient forged(server.port(), {&pki().worker});
    REQUIRE(forged.handshake());
    auto res = forged.get("/whoami", "X-Dtraced-Client-Cert: admin\r\n");
    REQUIRE(res);
    CHECK(res->body() == "worker-7");
    // Without a certificate, a forged header is removed.
    TlsClient anonymous(server.port());
    REQUIRE(anonymous.handshake());
    auto none = anonymous.get("/whoami", "X-Dtraced-Client-Cert: admin\r\n");
    REQUIRE(none);
    CHECK(none->body() == "");
    CHECK(server.metrics().tls_handshake_failures == 0);
  }
  SECTION("one from a foreign CA fails the handshake") {
    CHECK_FALSE(whoami(server.port(), {&pki().intruder}).has_value());
    CHECK(eventually([&] { return server.metrics().tls_handshake_failures == 1; }));
    CHECK(whoami(server.port()) == std::optional<std::string>(""));
  }
  SECTION("an expired one signed by the right CA fails the handshake") {
    CHECK_FALSE(whoami(server.port(), {&pki().expired_worker}).has_value());
    CHECK(eventually([&] { return server.metrics().tls_handshake_failures == 1; }));
    CHECK(whoami(server.port(), {&pki().worker}) == std::optional<std::string>("worker-7"));
  }
  SECTION("also over TLS 1.2, where the failure shows in the client's handshake") {
    TlsClient client(server.port(), {&pki().intruder, TLS1_2_VERSION});
    CHECK_FALSE(client.handshake());
    CHECK(eventually([&] { return server.metrics().tls_handshake_failures == 1; }));
  }
}

TEST_CASE("tls server: without a client CA no certificate is asked for or stamped", "[http][tls]") {
  TlsTestServer server(tls_limits(), server_context(/*ask_client_certs=*/false));
  CHECK(whoami(server.port(), {&pki().worker}) == std::optional<std::string>(""));
}

TEST_CASE("tls server: a renegotiation is refused and the server keeps serving", "[http][tls]") {
  TlsTestServer server(tls_limits());
  {
    TlsClient client(server.port(), {nullptr, TLS1_2_VERSION});
    REQUIRE(client.handshake());
    REQUIRE(SSL_version(client.ssl()) == TLS1_2_VERSION);
    REQUIRE(client.get("/whoami"));
    REQUIRE(SSL_renegotiate(client.ssl()) == 1);
    // The new ClientHello goes out; the server's refusal ends the handshake and the connection.
    CHECK(SSL_do_handshake(client.ssl()) != 1);
    CHECK_FALSE(client.get("/whoami").has_value());
    CHECK(SSL_num_renegotiations(client.ssl()) <= 1);
  }
  CHECK(eventually([&] { return server.metrics().open_connections == 0; }));
  CHECK(server.metrics().requests == 1);
  CHECK(whoami(server.port()) == std::optional<std::string>(""));
}

TEST_CASE("tls server: over max_idle_connections the connection idle longest is closed", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.max_idle_connections = 2;
  TlsTestServer server(limits);
  std::vector<std::unique_ptr<TlsClient>> clients;
  for (int i = 0; i < 3; ++i) {
    clients.push_back(std::make_unique<TlsClient>(server.port()));
    REQUIRE(clients.back()->handshake());
    auto res = clients.back()->get("/whoami");
    REQUIRE(res);
    REQUIRE(res->keep_alive());
  }
  CHECK(eventually([&] { return server.metrics().evicted_idle_connections == 1; }));
  CHECK(clients[0]->wait_closed());
  // The two younger ones are still kept alive.
  CHECK(clients[1]->get("/whoami").has_value());
  CHECK(clients[2]->get("/whoami").has_value());
  CHECK(server.metrics().keepalive_reuses == 2);
  CHECK(server.metrics().evicted_idle_connections == 1);
}

TEST_CASE("tls server: with every slot taken a newcomer closes the connection idle longest", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.max_connections = 2;
  TlsTestServer server(limits);
  std::vector<std::unique_ptr<TlsClient>> clients;
  for (int i = 0; i < 2; ++i) {
    clients.push_back(std::make_unique<TlsClient>(server.port()));
    REQUIRE(clients.back()->handshake());
    auto res = clients.back()->get("/whoami");
    REQUIRE(res);
    REQUIRE(res->keep_alive());
  }
  // Both slots hold idle kept-alive connections: the third is served, not refused.
  TlsClient newcomer(server.port());
  REQUIRE(newcomer.handshake());
  auto res = newcomer.get("/whoami");
  REQUIRE(res);
  CHECK(res->result() == Status::ok);
  CHECK(clients[0]->wait_closed());
  CHECK(clients[1]->get("/whoami").has_value());
  CHECK(server.metrics().evicted_idle_connections == 1);
  CHECK(server.metrics().rejected_connections == 0);
}

TEST_CASE("tls server: the last request a connection may make is answered Connection: close", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.max_requests_per_connection = 2;
  TlsTestServer server(limits);
  TlsClient client(server.port());
  REQUIRE(client.handshake());
  auto first = client.get("/whoami");
  REQUIRE(first);
  CHECK(first->keep_alive());
  auto second = client.get("/whoami");
  REQUIRE(second);
  CHECK_FALSE(second->keep_alive());
  CHECK(client.wait_closed());
}

TEST_CASE("tls server: make_server_tls_context says which PEM is wrong", "[http][tls]") {
  const KeyPair& server = pki().server;
  auto no_cert = make_server_tls_context(ServerTlsConfig{"garbage", server.key_pem, ""});
  REQUIRE_FALSE(no_cert.ok());
  CHECK_THAT(no_cert.error().message, Catch::Contains("server certificate"));
  auto wrong_key = make_server_tls_context(ServerTlsConfig{server.cert_pem, pki().worker.key_pem, ""});
  REQUIRE_FALSE(wrong_key.ok());
  CHECK_THAT(wrong_key.error().message, Catch::Contains("does not match"));
  auto bad_ca = make_server_tls_context(ServerTlsConfig{server.cert_pem, server.key_pem, "not a CA"});
  REQUIRE_FALSE(bad_ca.ok());
  CHECK_THAT(bad_ca.error().message, Catch::Contains("client CA"));
  // TLS 1.1 is refused.
  TlsTestServer running(tls_limits());
  TlsClient old(running.port(), {nullptr, TLS1_1_VERSION});
  CHECK_FALSE(old.handshake());
  CHECK(eventually([&] { return running.metrics().tls_handshake_failures == 1; }));
}

TEST_CASE("tls server: failed handshakes are logged at most once per interval, with a count", "[http][tls]") {
  dtraced::util::ManualClock clock;
  std::string log;
  {
    TlsTestServer server(tls_limits(), server_context(), clock);
    auto fail_once = [&](std::uint64_t total) {
      TlsClient old(server.port(), {nullptr, TLS1_1_VERSION});
      CHECK_FALSE(old.handshake());
      CHECK(eventually([&] { return server.metrics().tls_handshake_failures == total; }));
    };
    dtraced::testing::TempDir dir("dtraced-tls-log");
    const std::string path = (dir.path() / "stderr").string();
    const int file = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
    REQUIRE(file >= 0);
    const int saved = ::dup(STDERR_FILENO);
    REQUIRE(::dup2(file, STDERR_FILENO) == STDERR_FILENO);
    fail_once(1);
    fail_once(2);
    fail_once(3);
    clock.advance(kHandshakeLogInterval);
    fail_once(4);
    ::dup2(saved, STDERR_FILENO);
    ::close(saved);
    ::close(file);
    std::ifstream in(path);
    log.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  }
  INFO(log);
  std::vector<std::string> lines;
  for (std::size_t at = 0, end; (end = log.find('\n', at)) != std::string::npos; at = end + 1) {
    const std::string line = log.substr(at, end - at);
    if (line.find("TLS handshake with 127.0.0.1 failed") != std::string::npos) lines.push_back(line);
  }
  REQUIRE(lines.size() == 2);
  CHECK_THAT(lines[0], Catch::Contains("unsupported protocol"));
  CHECK_THAT(lines[1], Catch::Contains("2 more failed handshake(s) not logged"));
}

TEST_CASE("tls server: a connection stuck in its handshake is evicted for an authenticated client", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.max_connections = 2;
  auto authenticated = [](const Request& header) { return header[bhttp::field::authorization] == "Bearer good"; };
  TlsTestServer server(limits, server_context(), dtraced::util::real_clock(), authenticated);
  // Two peers that send the start of a ClientHello and stall inside the handshake.
  const std::string hello = client_hello();
  RawConnection first(server.port());
  RawConnection second(server.port());
  REQUIRE(first.send(hello.substr(0, hello.size() / 2)));
  REQUIRE(second.send(hello.substr(0, hello.size() / 2)));
  CHECK(eventually([&] { return server.metrics().open_connections == 2; }));
  TlsClient client(server.port());
  REQUIRE(client.handshake());
  auto res = client.get("/whoami", "Authorization: Bearer good\r\n");
  REQUIRE(res);
  CHECK(res->result() == Status::ok);
  CHECK(server.metrics().evicted_connections == 1);
  CHECK(first.wait_closed());
  // Evicted by the server: not a failure of the peer's handshake.
  CHECK(server.metrics().tls_handshake_failures == 0);
}

TEST_CASE("tls server: stop closes idle TLS connections and lets a request in flight finish", "[http][tls]") {
  TlsTestServer server(tls_limits());
  TlsClient idle(server.port());
  REQUIRE(idle.handshake());
  REQUIRE(idle.get("/whoami"));
  TlsClient busy(server.port());
  REQUIRE(busy.handshake());
  // A request in its handler when stop() begins.
  REQUIRE(busy.write("GET /slow HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"));
  REQUIRE(server.gate().entered.get_future().wait_for(kBound) == std::future_status::ready);
  auto stopped = server.begin_stop(kBound);
  CHECK(idle.wait_closed());
  open_gate(server.executor(), server.gate());
  auto res = busy.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::ok);
  CHECK(res->body() == "slow done");
  CHECK_FALSE(res->keep_alive());
  CHECK(stopped.wait_for(kBound) == std::future_status::ready);
}

TEST_CASE("tls server: over max_connections a TLS client is answered 503 over TLS", "[http][tls]") {
  ServerLimits limits = tls_limits();
  limits.max_connections = 1;
  TlsTestServer server(limits);
  TlsClient holder(server.port());
  REQUIRE(holder.handshake());
  // The slot's connection is busy (its request in the handler), so there is nothing to evict.
  REQUIRE(holder.write("GET /slow HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"));
  REQUIRE(server.gate().entered.get_future().wait_for(kBound) == std::future_status::ready);
  TlsClient late(server.port());
  REQUIRE(late.handshake());
  auto res = late.get("/whoami");
  REQUIRE(res);
  CHECK(res->result() == Status::service_unavailable);
  CHECK(std::string(res->at(bhttp::field::retry_after)) == "1");
  CHECK(late.wait_closed());
  CHECK(server.metrics().rejected_connections == 1);
  // The connection holding the slot is still served.
  open_gate(server.executor(), server.gate());
  auto slow = holder.read_response();
  REQUIRE(slow);
  CHECK(slow->body() == "slow done");
}
