// dtraced::http over real loopback sockets: the server's limits, deadlines, connection cap and
// graceful stop, and the client's errors. Every wait is bounded (kBound) and event-driven: a test
// waits for a response, a close, or a counter, never for a guessed amount of time.
#include <array>
#include <atomic>
#include <chrono>
#include <functional>
#include <future>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <boost/asio/as_tuple.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/read.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/asio/use_future.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/json/parse.hpp>
#include <boost/json/value.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "eventually.h"
#include "http/client.h"
#include "http/server.h"
#include "http/types.h"
#include "util/clock.h"

namespace {

namespace net = boost::asio;
namespace bhttp = boost::beast::http;
using tcp = net::ip::tcp;
using boost::system::error_code;
using namespace std::chrono_literals;
using namespace dtraced::http;
using dtraced::testing::eventually;

// The longest any single wait in these tests may take before the test fails instead of hanging.
constexpr auto kBound = 10s;
constexpr std::uint64_t kMaxResponse = 1 << 20;
const ClientTimeouts kTimeouts{kBound, kBound, kBound};

std::string field_of(const Response& res, bhttp::field f) { return std::string(res[f]); }

boost::json::value json_body(const Response& res) {
  error_code ec;
  boost::json::value v = boost::json::parse(res.body(), ec);
  return ec ? boost::json::value() : v;
}

// Requests to /slow wait here until the test opens the gate. Touched only on the server's
// executor, except `entered`, a promise kept the first time a request arrives.
struct Gate {
  bool open = false;
  std::vector<net::steady_timer*> waiting;
  bool entered_set = false;
  std::promise<void> entered;
};

void open_gate(const net::any_io_executor& executor, Gate& gate) {
  net::post(executor, [&gate] {
    gate.open = true;
    for (net::steady_timer* timer : gate.waiting) timer->cancel();
  });
}

// The routes the tests talk to: /echo answers its JSON body, /throw throws, /big answers 4 KiB,
// /slow waits for the gate.
Server::Handler routes(Gate* gate = nullptr) {
  return [gate](Request req) -> net::awaitable<Response> {
    if (req.target() == "/echo") {
      error_code ec;
      boost::json::value body = boost::json::parse(req.body(), ec);
      if (ec) co_return dtraced::http::make_error(Status::bad_request, "invalid JSON", "");
      co_return dtraced::http::make_json_response(Status::ok, body);
    }
    if (req.target() == "/throw") throw std::runtime_error("handler failure on purpose");
    if (req.target() == "/big") co_return dtraced::http::make_binary_response(Status::ok, std::string(4096, 'x'));
    if (req.target() == "/slow" && gate != nullptr) {
      if (!gate->entered_set) {
        gate->entered_set = true;
        gate->entered.set_value();
      }
      if (!gate->open) {
        net::steady_timer timer(co_await net::this_coro::executor, net::steady_timer::time_point::max());
        gate->waiting.push_back(&timer);
        co_await timer.async_wait(net::as_tuple(net::use_awaitable));
        std::erase(gate->waiting, &timer);
      }
      co_return dtraced::http::make_text_response(Status::ok, "slow done");
    }
    co_return dtraced::http::make_error(Status::not_found, "no such route", "");
  };
}

ServerLimits generous_limits() {
  ServerLimits limits;
  limits.read_timeout = kBound;
  limits.write_timeout = kBound;
  limits.idle_keepalive_timeout = kBound;
  return limits;
}

// A server on 127.0.0.1, on an ephemeral port, with its io_context on a thread of its own.
class TestServer {
 public:
  TestServer(ServerLimits limits, Server::Handler handler, Server::HeaderCheck check = {},
             const dtraced::util::Clock& clock = dtraced::util::real_clock())
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), 0, limits, std::move(handler), std::move(check),
                clock) {
    REQUIRE(!server_.start());
    REQUIRE(server_.port() != 0);
    thread_ = std::thread([this] { io_.run(); });
  }

  ~TestServer() {
    if (!stop_.valid()) stop_ = begin_stop(1s);
    stop_.wait_for(kBound);
    work_.reset();
    io_.stop();
    thread_.join();
  }

  std::future<void> begin_stop(std::chrono::milliseconds grace) {
    return net::co_spawn(io_, server_.stop(grace), net::use_future);
  }
  // Starts a graceful stop that the destructor will not repeat.
  std::future<void>& stop(std::chrono::milliseconds grace) {
    stop_ = begin_stop(grace);
    return stop_;
  }

  Url url() const { return Url{"127.0.0.1", server_.port()}; }
  std::uint16_t port() const { return server_.port(); }
  dtraced::http::ServerMetrics metrics() const { return server_.metrics(); }
  net::any_io_executor executor() { return io_.get_executor(); }

 private:
  net::io_context io_;
  net::executor_work_guard<net::io_context::executor_type> work_ = net::make_work_guard(io_);
  Server server_;
  std::thread thread_;
  std::future<void> stop_;
};

// A client socket driven by hand, for bytes no well-behaved client sends. Each call runs its own
// io_context for at most kBound; on timeout it closes the socket, which ends the call.
class RawConnection {
 public:
  explicit RawConnection(std::uint16_t port) : socket_(io_) {
    socket_.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port));
  }

  bool send(std::string_view bytes) {
    error_code result = net::error::timed_out;
    run_bounded([&] {
      net::async_write(socket_, net::buffer(bytes), [&](const error_code& ec, std::size_t) { result = ec; });
    });
    return !result;
  }

  // The next response, or nullopt when the connection ended first.
  std::optional<Response> read_response() {
    Response res;
    error_code result = net::error::timed_out;
    run_bounded(
        [&] { bhttp::async_read(socket_, buffer_, res, [&](const error_code& ec, std::size_t) { result = ec; }); });
    if (result) return std::nullopt;
    return res;
  }

  // True when the server closes the connection (end of stream or reset); bytes before that are
  // discarded.
  bool wait_closed() {
    bool closed = false;
    std::array<char, 4096> scratch;
    std::function<void()> read_more = [&] {
      socket_.async_read_some(net::buffer(scratch), [&](const error_code& ec, std::size_t) {
        if (!ec) return read_more();
        closed = ec == net::error::eof || ec == net::error::connection_reset;
      });
    };
    run_bounded(read_more);
    return closed;
  }

  void close() {
    error_code ignored;
    socket_.close(ignored);
  }

 private:
  template <typename Start>
  void run_bounded(Start start) {
    io_.restart();
    start();
    io_.run_for(kBound);
    if (!io_.stopped()) {
      close();
      io_.run();
    }
  }

  net::io_context io_;
  tcp::socket socket_;
  boost::beast::flat_buffer buffer_;
};

std::string echo_request(std::string_view json, bool keep_alive = true) {
  return fmt::format(
      "POST /echo HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n{}Content-Length: {}\r\n\r\n{}",
      keep_alive ? "" : "Connection: close\r\n", json.size(), json);
}

ClientResult post_echo(const Url& url, std::string json) {
  return dtraced::http::request_sync(
      url, dtraced::http::make_request(Verb::post, "/echo", std::move(json), dtraced::http::kJsonContentType),
      kTimeouts, kMaxResponse);
}

bool connection_refused(std::uint16_t port) {
  net::io_context io;
  tcp::socket socket(io);
  error_code ec;
  socket.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port), ec);
  return ec == net::error::connection_refused;
}

// A port nobody listens on (just released by the kernel; another process grabbing it in between
// is possible but not on a test machine's loopback in practice).
std::uint16_t unused_port() {
  net::io_context io;
  tcp::acceptor acceptor(io, tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));
  return acceptor.local_endpoint().port();
}

}  // namespace

TEST_CASE("parse_base_url accepts http://host[:port] and explains every rejection", "[http]") {
  auto url = dtraced::http::parse_base_url("http://127.0.0.1:7878");
  REQUIRE(url);
  CHECK(url->host == "127.0.0.1");
  CHECK(url->port == 7878);
  CHECK(url->to_string() == "http://127.0.0.1:7878");

  url = dtraced::http::parse_base_url("HTTP://collector.example-farm.org/");
  REQUIRE(url);
  CHECK(url->host == "collector.example-farm.org");
  CHECK(url->port == 80);

  url = dtraced::http::parse_base_url("http://[::1]:9000");
  REQUIRE(url);
  CHECK(url->host == "::1");
  CHECK(url->host_header() == "[::1]:9000");

  const std::vector<std::pair<std::string, std::string>> bad = {
      {"https://127.0.0.1:7878", "https"},
      {"ftp://host", "http://"},
      {"127.0.0.1:7878", "http://"},
      {"http://", "host"},
      {"http://:7878", "host"},
      {"http://host:0", "port"},
      {"http://host:65536", "port"},
      {"http://host:78x", "port"},
      {"http://host:", "port"},
      {"http://host/v1/jobs", "path"},
      {"http://user@host", "user"},
      {"http://host?x=1", "query"},
      {"http://ho st", "space"},
      {"http://[::1", "IPv6"},
      {"http://[nonsense]:80", "IPv6"},
      {"http://" + std::string(dtraced::http::kMaxUrlBytes, 'a'), "longer"},
  };
  for (const auto& [text, why] : bad) {
    INFO(text);
    const auto refused = dtraced::http::parse_base_url(text);
    REQUIRE_FALSE(refused);
    CHECK_THAT(refused.error().message, Catch::Contains(why));
  }
  CHECK(dtraced::http::parse_base_url("http://host:1")->port == 1);
}

TEST_CASE("make_error builds the JSON error shape", "[http]") {
  const Response res = dtraced::http::make_error(Status::bad_request, "samples must be positive", "/samples");
  CHECK(res.result() == Status::bad_request);
  CHECK(field_of(res, bhttp::field::content_type) == "application/json");
  CHECK(field_of(res, bhttp::field::content_length) == std::to_string(res.body().size()));
  const boost::json::value body = json_body(res);
  REQUIRE(body.is_object());
  CHECK(body.at("error") == "samples must be positive");
  CHECK(body.at("field") == "/samples");
}

TEST_CASE("server: JSON echo, several requests on one keep-alive connection", "[http]") {
  TestServer server(generous_limits(), routes());
  RawConnection conn(server.port());
  for (int i = 0; i < 3; ++i) {
    const std::string json = fmt::format(R"({{"n":{},"text":"hello"}})", i);
    REQUIRE(conn.send(echo_request(json)));
    const auto res = conn.read_response();
    REQUIRE(res);
    CHECK(res->result() == Status::ok);
    CHECK(res->keep_alive());
    CHECK(json_body(*res) == boost::json::parse(json));
  }
  // Two requests in one write (pipelined): both answered, in order; the second one closes.
  REQUIRE(conn.send(echo_request(R"({"n":3})") + echo_request(R"({"n":4})", /*keep_alive=*/false)));
  const auto third = conn.read_response();
  const auto fourth = conn.read_response();
  REQUIRE(third);
  REQUIRE(fourth);
  CHECK(json_body(*third).at("n") == 3);
  CHECK(json_body(*fourth).at("n") == 4);
  CHECK_FALSE(fourth->keep_alive());
  CHECK(conn.wait_closed());

  // The coroutine client too.
  const ClientResult result = post_echo(server.url(), R"({"client":true})");
  REQUIRE(result.ok());
  CHECK(result.response.result() == Status::ok);
  CHECK(json_body(result.response).at("client") == true);
  CHECK(server.metrics().requests == 6);
  CHECK(server.metrics().responses_4xx == 0);
}

TEST_CASE("server: a body over the limit gets 413 and the server keeps serving", "[http]") {
  ServerLimits limits = generous_limits();
  limits.max_body_bytes = 1024;
  TestServer server(limits, routes());

  RawConnection conn(server.port());
  REQUIRE(conn.send(echo_request(fmt::format(R"({{"pad":"{}"}})", std::string(4096, 'a')))));
  const auto res = conn.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::payload_too_large);
  CHECK_THAT(json_body(*res).at("error").as_string().c_str(), Catch::Contains("1024"));
  CHECK_FALSE(res->keep_alive());
  CHECK(conn.wait_closed());

  // Through the client as well: the answer arrives although the body was refused.
  const ClientResult big = post_echo(server.url(), fmt::format(R"({{"pad":"{}"}})", std::string(4096, 'b')));
  REQUIRE(big.ok());
  CHECK(big.response.result() == Status::payload_too_large);

  const ClientResult small = post_echo(server.url(), R"({"ok":1})");
  REQUIRE(small.ok());
  CHECK(small.response.result() == Status::ok);
  CHECK(server.metrics().responses_4xx == 2);
}

TEST_CASE("server: Expect: 100-continue gets 100 before the body, or 413 instead of it", "[http]") {
  ServerLimits limits = generous_limits();
  limits.max_body_bytes = 1024;
  TestServer server(limits, routes());

  const std::string json = R"({"continued":true})";
  RawConnection conn(server.port());
  REQUIRE(conn.send(fmt::format(
      "POST /echo HTTP/1.1\r\nHost: test\r\nExpect: 100-continue\r\nContent-Length: {}\r\n\r\n", json.size())));
  const auto go_on = conn.read_response();
  REQUIRE(go_on);
  CHECK(go_on->result() == Status::continue_);
  REQUIRE(conn.send(json));
  const auto res = conn.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::ok);
  CHECK(json_body(*res) == boost::json::parse(json));

  // Over the limit: refused on the header alone, the body is never sent.
  REQUIRE(conn.send("POST /echo HTTP/1.1\r\nHost: test\r\nExpect: 100-continue\r\nContent-Length: 5000\r\n\r\n"));
  const auto refused = conn.read_response();
  REQUIRE(refused);
  CHECK(refused->result() == Status::payload_too_large);
  CHECK(conn.wait_closed());
}

TEST_CASE("server: a header over the limit gets 431", "[http]") {
  TestServer server(generous_limits(), routes());
  RawConnection conn(server.port());
  REQUIRE(conn.send("GET /echo HTTP/1.1\r\nHost: test\r\nX-Padding: " + std::string(16 * 1024, 'h') + "\r\n\r\n"));
  const auto res = conn.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::request_header_fields_too_large);
  CHECK(json_body(*res).is_object());
  CHECK(conn.wait_closed());
  CHECK(post_echo(server.url(), "{}").response.result() == Status::ok);
}

TEST_CASE("server: garbage bytes get 400", "[http]") {
  TestServer server(generous_limits(), routes());
  RawConnection conn(server.port());
  REQUIRE(conn.send(std::string("\x16\x03\x01\x02\x00 not http at all\r\n\r\n", 25)));
  const auto res = conn.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::bad_request);
  CHECK_THAT(json_body(*res).at("error").as_string().c_str(), Catch::Contains("malformed"));
  CHECK(conn.wait_closed());
  CHECK(post_echo(server.url(), "{}").response.result() == Status::ok);
}

TEST_CASE("server: a client that stalls mid-request is dropped at the read deadline", "[http]") {
  ServerLimits limits = generous_limits();
  limits.read_timeout = 500ms;  // short so the test is quick; nothing below depends on its length
  TestServer server(limits, routes());

  RawConnection stalled(server.port());
  REQUIRE(stalled.send("POST /echo HTTP/1.1\r\nHost: test\r\nContent-Length: 100\r\n\r\n{\"half\":"));
  CHECK(stalled.wait_closed());
  CHECK(eventually([&] { return server.metrics().read_timeouts == 1; }));
  CHECK(server.metrics().requests == 0);  // dropped without an answer

  const ClientResult other = post_echo(server.url(), R"({"after":"stall"})");
  REQUIRE(other.ok());
  CHECK(other.response.result() == Status::ok);
}

TEST_CASE("server: connections over max_connections get 503 and are closed", "[http]") {
  ServerLimits limits = generous_limits();
  limits.max_connections = 2;
  TestServer server(limits, routes());

  // Two sessions, each proven open by an answered keep-alive request.
  RawConnection a(server.port());
  RawConnection b(server.port());
  for (RawConnection* conn : {&a, &b}) {
    REQUIRE(conn->send(echo_request("{}")));
    const auto res = conn->read_response();
    REQUIRE(res);
    REQUIRE(res->result() == Status::ok);
  }
  CHECK(server.metrics().open_connections == 2);

  RawConnection c(server.port());
  REQUIRE(c.send(echo_request("{}")));
  const auto refused = c.read_response();
  REQUIRE(refused);
  CHECK(refused->result() == Status::service_unavailable);
  CHECK(field_of(*refused, bhttp::field::retry_after) == "1");
  CHECK(json_body(*refused).is_object());
  CHECK(c.wait_closed());
  CHECK(server.metrics().rejected_connections == 1);

  // A slot frees when a session ends.
  a.close();
  REQUIRE(eventually([&] { return server.metrics().open_connections == 1; }));
  CHECK(post_echo(server.url(), "{}").response.result() == Status::ok);
}

TEST_CASE("server: a throwing handler gives 500 with a JSON body, and serving goes on", "[http]") {
  TestServer server(generous_limits(), routes());
  const ClientResult res = dtraced::http::request_sync(server.url(), dtraced::http::make_request(Verb::get, "/throw"),
                                                       kTimeouts, kMaxResponse);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::internal_server_error);
  const boost::json::value body = json_body(res.response);
  REQUIRE(body.is_object());
  CHECK(body.at("error") == "internal error");  // the exception's text stays in the log
  CHECK(server.metrics().responses_5xx == 1);
  CHECK(post_echo(server.url(), "{}").response.result() == Status::ok);
}

TEST_CASE("server: graceful stop finishes the request in flight, closes idle connections", "[http]") {
  Gate gate;
  TestServer server(generous_limits(), routes(&gate));

  RawConnection idle(server.port());
  REQUIRE(idle.send(echo_request("{}")));
  REQUIRE(idle.read_response());

  auto slow = std::async(std::launch::async, [url = server.url()] {
    return dtraced::http::request_sync(url, dtraced::http::make_request(Verb::get, "/slow"), kTimeouts, kMaxResponse);
  });
  REQUIRE(gate.entered.get_future().wait_for(kBound) == std::future_status::ready);

  std::future<void>& stopped = server.stop(kBound);
  CHECK(idle.wait_closed());  // idle keep-alive connections close at once
  REQUIRE(eventually([&] { return connection_refused(server.port()); }));
  CHECK(stopped.wait_for(0s) == std::future_status::timeout);  // still waiting for /slow

  open_gate(server.executor(), gate);
  REQUIRE(slow.wait_for(kBound) == std::future_status::ready);
  const ClientResult res = slow.get();
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::ok);
  CHECK(res.response.body() == "slow done");
  CHECK(stopped.wait_for(kBound) == std::future_status::ready);
  CHECK(server.metrics().open_connections == 0);
}

TEST_CASE("server: stop cancels a request still running when its grace ends on the server's clock", "[http]") {
  Gate gate;  // never opened
  dtraced::util::ManualClock clock;
  TestServer server(generous_limits(), routes(&gate), {}, clock);
  auto slow = std::async(std::launch::async, [url = server.url()] {
    return dtraced::http::request_sync(url, dtraced::http::make_request(Verb::get, "/slow"), kTimeouts, kMaxResponse);
  });
  REQUIRE(gate.entered.get_future().wait_for(kBound) == std::future_status::ready);

  const auto grace = std::chrono::minutes(10);
  std::future<void>& stopped = server.stop(grace);
  // The stop sleeps on the clock until the grace ends; the request still runs meanwhile.
  REQUIRE(clock.wait_for_sleepers(1, kBound));
  CHECK(clock.next_deadline() == clock.now() + grace);
  CHECK(stopped.wait_for(0s) == std::future_status::timeout);
  clock.advance(grace);
  REQUIRE(stopped.wait_for(kBound) == std::future_status::ready);
  REQUIRE(slow.wait_for(kBound) == std::future_status::ready);
  const ClientResult res = slow.get();
  CHECK_FALSE(res.ok());
  CHECK(res.error == ClientError::kIo);
  CHECK(server.metrics().open_connections == 0);
}

TEST_CASE("client: a server that never answers is a timeout, not a hang", "[http]") {
  // The kernel completes the handshake for a listening socket nobody accepts from.
  net::io_context io;
  tcp::acceptor silent(io, tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));
  const Url url{"127.0.0.1", silent.local_endpoint().port()};
  ClientTimeouts timeouts = kTimeouts;
  timeouts.read = 300ms;
  const ClientResult res =
      dtraced::http::request_sync(url, dtraced::http::make_request(Verb::get, "/"), timeouts, kMaxResponse);
  CHECK(res.error == ClientError::kTimeout);
  CHECK_THAT(res.message, Catch::Contains("300 ms"));
}

TEST_CASE("client: connection refused is an error result", "[http]") {
  const Url url{"127.0.0.1", unused_port()};
  const ClientResult res =
      dtraced::http::request_sync(url, dtraced::http::make_request(Verb::get, "/"), kTimeouts, kMaxResponse);
  CHECK(res.error == ClientError::kConnect);
  CHECK_THAT(res.message, Catch::Contains("refused"));
  CHECK_THAT(res.message, Catch::Contains(url.to_string()));
}

TEST_CASE("client: a response body over the limit is an error result", "[http]") {
  TestServer server(generous_limits(), routes());
  const ClientResult res =
      dtraced::http::request_sync(server.url(), dtraced::http::make_request(Verb::get, "/big"), kTimeouts, 1024);
  CHECK(res.error == ClientError::kTooLarge);
  const ClientResult fits =
      dtraced::http::request_sync(server.url(), dtraced::http::make_request(Verb::get, "/big"), kTimeouts, 4096);
  REQUIRE(fits.ok());
  CHECK(fits.response.body().size() == 4096);
}

TEST_CASE("client: a host name is resolved", "[http]") {
  TestServer server(generous_limits(), routes());
  // localhost may resolve to ::1 first, where nobody listens: the client tries each address.
  const ClientResult res = post_echo(Url{"localhost", server.port()}, R"({"by":"name"})");
  REQUIRE(res.ok());
  CHECK(json_body(res.response).at("by") == "name");
}

TEST_CASE("server: a header check answers before the body is read, or lowers the body limit", "[http]") {
  std::atomic<int> handled{0};
  Server::Handler handler = [&handled](Request req) -> net::awaitable<Response> {
    ++handled;
    co_return dtraced::http::make_json_response(Status::ok, boost::json::value{{"bytes", req.body().size()}});
  };
  Server::HeaderCheck check = [](const Request& header, std::uint64_t& body_limit) -> std::optional<Response> {
    if (header.target() == "/throw") throw std::runtime_error("check failed");
    if (header[bhttp::field::authorization] != "Bearer ok") {
      return dtraced::http::make_error(Status::unauthorized, "missing or wrong bearer token");
    }
    if (header.target() == "/small") body_limit = 16;
    return std::nullopt;
  };
  TestServer server(generous_limits(), handler, check);

  // A wrong token with a 50 MB body announced: answered on the header, which is all that is sent.
  RawConnection conn(server.port());
  REQUIRE(
      conn.send("POST /big HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer no\r\nContent-Length: 50000000\r\n\r\n"));
  const auto refused = conn.read_response();
  REQUIRE(refused);
  CHECK(refused->result() == Status::unauthorized);
  CHECK_FALSE(refused->keep_alive());
  CHECK(conn.wait_closed());

  // The route's own limit: 413 naming it; under it the request reaches the handler.
  RawConnection small(server.port());
  REQUIRE(
      small.send(fmt::format("POST /small HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer ok\r\n"
                             "Content-Length: 100\r\n\r\n{}",
                             std::string(100, 'x'))));
  const auto too_big = small.read_response();
  REQUIRE(too_big);
  CHECK(too_big->result() == Status::payload_too_large);
  CHECK_THAT(json_body(*too_big).at("error").as_string().c_str(), Catch::Contains("16"));

  RawConnection fits(server.port());
  REQUIRE(fits.send(
      "POST /small HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer ok\r\nContent-Length: 10\r\n\r\n0123456789"));
  const auto ok = fits.read_response();
  REQUIRE(ok);
  CHECK(ok->result() == Status::ok);
  CHECK(json_body(*ok).at("bytes").as_int64() == 10);

  // A check that throws is a 500, and the server goes on.
  RawConnection thrower(server.port());
  REQUIRE(thrower.send("GET /throw HTTP/1.1\r\nHost: test\r\n\r\n"));
  const auto failed = thrower.read_response();
  REQUIRE(failed);
  CHECK(failed->result() == Status::internal_server_error);
  CHECK(handled == 1);
}
