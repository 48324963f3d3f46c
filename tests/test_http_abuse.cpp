// dtraced::http under abuse, over real loopback sockets: floods of unauthenticated connections
// (idle, slowloris, keep-alive health checks) past the slot count, and the short deadline of
// unauthenticated peers. Correctness only: every wait is bounded (kBound, eventually) and nothing
// asserts how long anything took.
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "http_testing.h"

using namespace http_testing;

namespace {

constexpr std::string_view kGoodAuthorization = "Bearer good-token";

// The predicate a collector supplies: the request carries the right bearer token.
bool has_good_token(const Request& header) { return header[bhttp::field::authorization] == kGoodAuthorization; }

// /healthz answers anyone; /echo (routes()) is what authenticated clients call.
Server::Handler health_and_routes() {
  return [inner = routes()](Request req) -> net::awaitable<Response> {
    if (req.target() == "/healthz") co_return make_text_response(Status::ok, "ok");
    co_return co_await inner(std::move(req));
  };
}

std::string authenticated_echo(int n) {
  const std::string json = fmt::format("{{\"n\":{}}}", n);
  return fmt::format(
      "POST /echo HTTP/1.1\r\nHost: test\r\nAuthorization: {}\r\nContent-Type: application/json\r\n"
      "Content-Length: {}\r\n\r\n{}",
      kGoodAuthorization, json.size(), json);
}

ClientResult authenticated_post_echo(const Url& url, int n) {
  Request req = make_request(Verb::post, "/echo", fmt::format("{{\"n\":{}}}", n), kJsonContentType);
  req.set(bhttp::field::authorization, kGoodAuthorization);
  return request_sync(url, std::move(req), kTimeouts, kMaxResponse);
}

}  // namespace

TEST_CASE("server: a flood of unauthenticated connections past the slot count leaves token holders served", "[http]") {
  ServerLimits limits = generous_limits();
  limits.max_connections = 32;
  // Eviction alone must make room: no unauthenticated deadline expires during the test.
  limits.unauthenticated_timeout = kBound;
  TestServer server(limits, health_and_routes(), {}, dtraced::util::real_clock(), has_good_token);

  // Workers already connected and authenticated before the flood.
  std::vector<std::unique_ptr<RawConnection>> workers;
  for (int i = 0; i < 4; ++i) {
    workers.push_back(std::make_unique<RawConnection>(server.port()));
    REQUIRE(workers.back()->send(authenticated_echo(i)));
    const auto res = workers.back()->read_response();
    REQUIRE(res);
    CHECK(res->result() == Status::ok);
  }

  // The flood: 3 x 30 connections, far more than the 28 slots left. Idle ones say nothing,
  // slowloris ones stop mid-header, health checkers keep their connection after an answer.
  std::vector<std::unique_ptr<RawConnection>> flood;
  for (int i = 0; i < 30; ++i) {
    flood.push_back(std::make_unique<RawConnection>(server.port()));
    flood.push_back(std::make_unique<RawConnection>(server.port()));
    flood.back()->send("GET /healthz HTTP/1.1\r\nHost: test\r\nX-Slow: ");
    flood.push_back(std::make_unique<RawConnection>(server.port()));
    if (flood.back()->send("GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n")) flood.back()->read_response();
  }

  // New authenticated clients, each on a fresh connection, are all answered.
  for (int i = 0; i < 40; ++i) {
    INFO("request " << i);
    const ClientResult r = authenticated_post_echo(server.url(), i);
    REQUIRE(r.ok());
    CHECK(r.response.result() == Status::ok);
    CHECK(json_body(r.response).at("n") == i);
  }
  // The workers' connections were never evicted.
  for (std::size_t i = 0; i < workers.size(); ++i) {
    INFO("worker " << i);
    REQUIRE(workers[i]->send(authenticated_echo(100)));
    const auto res = workers[i]->read_response();
    REQUIRE(res);
    CHECK(res->result() == Status::ok);
  }
  CHECK(server.metrics().evicted_connections > 0);
  CHECK(server.metrics().rejected_connections == 0);
  CHECK(server.metrics().open_connections <= limits.max_connections);
}

TEST_CASE("server: an unauthenticated connection is closed at its short deadline, an authenticated one stays",
          "[http]") {
  ServerLimits limits = generous_limits();
  limits.unauthenticated_timeout = 200ms;  // short so the test is quick; nothing depends on its length
  TestServer server(limits, health_and_routes(), {}, dtraced::util::real_clock(), has_good_token);

  RawConnection health(server.port());
  REQUIRE(health.send("GET /healthz HTTP/1.1\r\nHost: test\r\n\r\n"));
  const auto answered = health.read_response();
  REQUIRE(answered);
  CHECK(answered->result() == Status::ok);
  RawConnection slowloris(server.port());
  REQUIRE(slowloris.send("GET /healthz HTTP/1.1\r\nHost: test\r\nX-Slow: "));
  RawConnection worker(server.port());
  REQUIRE(worker.send(authenticated_echo(1)));
  REQUIRE(worker.read_response());

  CHECK(health.wait_closed());
  CHECK(slowloris.wait_closed());
  // Idle past the unauthenticated deadline, the worker's connection still serves (its own idle
  // deadline is kBound).
  REQUIRE(worker.send(authenticated_echo(2)));
  const auto res = worker.read_response();
  REQUIRE(res);
  CHECK(res->result() == Status::ok);
}
