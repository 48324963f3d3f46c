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
#include <sstream>
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
#include <boost/beast/http/write.hpp>
#include <boost/json/parse.hpp>
#include <boost/json/value.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "eventually.h"
#include "http/client.h"
#include "http/server.h"
#include "http/types.h"
#include "http_testing.h"
#include "util/clock.h"

using namespace http_testing;

TEST_CASE("parse_base_url accepts http(s)://host[:port] and explains every rejection", "[http]") {
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
  CHECK_FALSE(url->tls);

  url = dtraced::http::parse_base_url("HTTPS://collector.example-farm.org");
  REQUIRE(url);
  CHECK(url->tls);
  CHECK(url->port == 443);
  CHECK(url->to_string() == "https://collector.example-farm.org:443");

  url = dtraced::http::parse_base_url("https://[::1]:7878/");
  REQUIRE(url);
  CHECK(url->tls);
  CHECK(url->host == "::1");
  CHECK(url->to_string() == "https://[::1]:7878");

  const std::vector<std::pair<std::string, std::string>> bad = {
      {"https://host:0", "port"},
      {"https://host/v1/jobs", "path"},
      {"ftp://host", "https://"},
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
  limits.max_connections = 1;
  Gate gate;
  TestServer server(limits, routes(&gate));

  // The one slot is busy: its request is in the handler.
  RawConnection a(server.port());
  REQUIRE(a.send("GET /slow HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n"));
  REQUIRE(gate.entered.get_future().wait_for(kBound) == std::future_status::ready);
  CHECK(server.metrics().open_connections == 1);

  RawConnection c(server.port());
  REQUIRE(c.send(echo_request("{}")));
  const auto refused = c.read_response();
  REQUIRE(refused);
  CHECK(refused->result() == Status::service_unavailable);
  CHECK(field_of(*refused, bhttp::field::retry_after) == "1");
  CHECK(json_body(*refused).is_object());
  CHECK(c.wait_closed());
  CHECK(server.metrics().rejected_connections == 1);

  // The busy one is answered; a slot frees when its session ends.
  open_gate(server.executor(), gate);
  const auto slow = a.read_response();
  REQUIRE(slow);
  CHECK(slow->result() == Status::ok);
  a.close();
  REQUIRE(eventually([&] { return server.metrics().open_connections == 0; }));
  CHECK(post_echo(server.url(), "{}").response.result() == Status::ok);
}

TEST_CASE("server: at max_connections the connection idle longest makes room", "[http]") {
  ServerLimits limits = generous_limits();
  limits.max_connections = 2;
  TestServer server(limits, routes());

  // Two kept-alive connections, idle after their answers.
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
  const auto served = c.read_response();
  REQUIRE(served);
  CHECK(served->result() == Status::ok);
  CHECK(a.wait_closed());  // idle the longest
  REQUIRE(b.send(echo_request("{}")));
  CHECK(b.read_response().has_value());
  CHECK(server.metrics().evicted_idle_connections == 1);
  CHECK(server.metrics().rejected_connections == 0);
}

TEST_CASE("server: with max_idle_connections N, N idle connections are kept and the (N+1)th closes the oldest",
          "[http][limits]") {
  constexpr std::size_t kIdle = 40;
  ServerLimits limits = generous_limits();
  limits.max_connections = 100;
  limits.max_idle_connections = kIdle;
  TestServer server(limits, routes());

  std::vector<std::unique_ptr<RawConnection>> conns;
  const auto ask = [](RawConnection& conn) {
    if (!conn.send(echo_request("{}"))) return false;
    const auto res = conn.read_response();
    return res && res->result() == Status::ok && res->keep_alive();
  };
  for (std::size_t i = 0; i < kIdle; ++i) {
    conns.push_back(std::make_unique<RawConnection>(server.port()));
    REQUIRE(ask(*conns.back()));
  }
  // All N are idle and kept: each serves a second request on the same connection.
  CHECK(eventually([&] { return server.metrics().open_connections == kIdle; }));
  CHECK(server.metrics().evicted_idle_connections == 0);
  for (auto& conn : conns) CHECK(ask(*conn));
  CHECK(server.metrics().keepalive_reuses == kIdle);
  CHECK(server.metrics().evicted_idle_connections == 0);

  // One more idle connection: the one idle the longest (conns[0], answered first above) is closed.
  conns.push_back(std::make_unique<RawConnection>(server.port()));
  REQUIRE(ask(*conns.back()));
  CHECK(conns[0]->wait_closed());
  CHECK(eventually([&] { return server.metrics().evicted_idle_connections == 1; }));
  // The other N are still kept, and going idle again among N idle ones closes nothing.
  for (std::size_t i = 1; i < conns.size(); ++i) CHECK(ask(*conns[i]));
  CHECK(server.metrics().evicted_idle_connections == 1);
  CHECK(server.metrics().rejected_connections == 0);
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

namespace {

// Every byte the server sends back for `request` (which asks for Connection: close), up to its
// close; "" when it does not close within kBound.
std::string raw_exchange(std::uint16_t port, const std::string& request) {
  net::io_context io;
  tcp::socket socket(io);
  socket.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port));
  net::write(socket, net::buffer(request));
  std::string got;
  error_code result = net::error::timed_out;
  net::async_read(socket, net::dynamic_buffer(got), [&](const error_code& ec, std::size_t) { result = ec; });
  io.run_for(kBound);
  return result == net::error::eof ? got : std::string();
}

// The answers of the test below, before the server adds its own fields.
Response wire_answer(std::string_view target) {
  if (target == "/small") {
    Response res = dtraced::http::make_text_response(Status::ok, R"({"result":"stored"})", "application/json");
    res.set("X-Dtraced-Test", "one, two");
    return res;
  }
  if (target == "/reason") {
    Response res = dtraced::http::make_text_response(Status::accepted, "later");
    res.reason("Taken For Later");
    return res;
  }
  if (target == "/large") return dtraced::http::make_binary_response(Status::ok, std::string(20'000, 'L'));
  return dtraced::http::make_error(Status::not_found, "no such route", "");
}

}  // namespace

TEST_CASE("server: an answer's bytes are what Beast's serializer writes, small or large", "[http]") {
  // Small answers are serialised by the server itself (one buffer, one write); larger ones by
  // Beast. Either way the wire carries the same bytes as Beast's serializer makes of the message.
  TestServer server(generous_limits(),
                    [](Request req) -> net::awaitable<Response> { co_return wire_answer(req.target()); });
  for (const std::string_view target : {"/small", "/reason", "/large", "/missing"}) {
    INFO(target);
    Response expected = wire_answer(target);
    expected.prepare_payload();
    expected.version(11);
    expected.keep_alive(false);
    std::ostringstream text;
    text << expected;
    const std::string got =
        raw_exchange(server.port(), fmt::format("GET {} HTTP/1.1\r\nHost: test\r\nConnection: close\r\n\r\n", target));
    CHECK(got == text.str());
  }
}
