// dtraced::http under abuse, over real loopback sockets: floods of unauthenticated connections
// (idle, slowloris, keep-alive health checks) past the slot count, the short deadline of
// unauthenticated peers, and slow readers of large answers. Correctness only: every wait is bounded (kBound,
// eventually) and nothing asserts how long anything took.
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

// Byte i of large answer `n`: differs between answers and along each, so a mix-up shows.
char large_byte(std::uint64_t n, std::uint64_t i) { return static_cast<char>((i * 131 + n * 7 + (i >> 12)) & 0xff); }

std::string large_body(std::uint64_t n, std::uint64_t size) {
  std::string body(size, '\0');
  for (std::uint64_t i = 0; i < size; ++i) body[i] = large_byte(n, i);
  return body;
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

TEST_CASE("server: slow readers of large answers hold at most the cap, the rest get 503, all bytes arrive intact",
          "[http]") {
  constexpr std::uint64_t kLargeBytes = 12 << 20;  // more than loopback's socket buffers take unread
  constexpr std::size_t kSlowReaders = 8;
  ServerLimits limits = generous_limits();
  limits.write_timeout = 120s;  // the slow readers read at the end of the test: out of the way
  limits.max_held_response_bytes = 32 << 20;
  Server::Handler handler = [inner = routes()](Request req) -> net::awaitable<Response> {
    const std::string_view target(req.target().data(), req.target().size());
    if (target.starts_with("/large/")) {
      const std::uint64_t n = std::stoull(std::string(target.substr(7)));
      co_return make_binary_response(Status::ok, large_body(n, kLargeBytes));
    }
    co_return co_await inner(std::move(req));
  };
  TestServer server(limits, handler);

  std::vector<std::unique_ptr<RawConnection>> slow;
  for (std::size_t n = 0; n < kSlowReaders; ++n) {
    slow.push_back(std::make_unique<RawConnection>(server.port()));
    REQUIRE(slow.back()->send(fmt::format("GET /large/{} HTTP/1.1\r\nHost: test\r\n\r\n", n)));
  }
  // Every request has been answered (held for its reader, or refused), none read yet.
  REQUIRE(eventually([&] { return server.metrics().requests == kSlowReaders; }));
  const ServerMetrics held = server.metrics();
  CHECK(held.held_response_bytes <= limits.max_held_response_bytes);
  CHECK(held.held_response_bytes > 0);
  CHECK(held.refused_large_responses > 0);

  // Small answers are not held back by the large ones.
  for (int i = 0; i < 10; ++i) {
    const ClientResult r = post_echo(server.url(), fmt::format("{{\"i\":{}}}", i));
    REQUIRE(r.ok());
    CHECK(r.response.result() == Status::ok);
  }

  // Read at last: each answer is the whole body, bit for bit, or a 503 to retry; a retry on the
  // same connection, once the held answers are read, gets the body.
  std::vector<std::size_t> refused;
  for (std::size_t n = 0; n < kSlowReaders; ++n) {
    INFO("slow reader " << n);
    const auto res = slow[n]->read_response(kLargeBytes);
    REQUIRE(res);
    if (res->result() == Status::service_unavailable) {
      refused.push_back(n);
      CHECK(field_of(*res, bhttp::field::retry_after) == "1");
      CHECK_THAT(std::string(json_body(*res).at("error").as_string()), Catch::Contains("slow readers"));
      continue;
    }
    REQUIRE(res->result() == Status::ok);
    CHECK(res->body() == large_body(n, kLargeBytes));
  }
  for (const std::size_t n : refused) {
    INFO("slow reader " << n << ", again");
    REQUIRE(slow[n]->send(fmt::format("GET /large/{} HTTP/1.1\r\nHost: test\r\n\r\n", n)));
    const auto res = slow[n]->read_response(kLargeBytes);
    REQUIRE(res);
    REQUIRE(res->result() == Status::ok);
    CHECK(res->body() == large_body(n, kLargeBytes));
  }
  CHECK(refused.size() == held.refused_large_responses);
  CHECK(eventually([&] { return server.metrics().held_response_bytes == 0; }));
}
