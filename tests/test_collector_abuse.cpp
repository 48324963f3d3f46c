// dtraced::collector over a real socket under a flood of unauthenticated connections: the
// collector's token is what keeps a connection's slot (http::Server's authenticated predicate),
// so requests with the token are all served while idle, slowloris and /healthz keep-alive
// connections outnumber the slots. Correctness only: no timing is asserted.
#include <array>
#include <memory>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/write.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector_testing.h"
#include "http/client.h"

using namespace dtraced::testing;

namespace {

namespace net = boost::asio;
using tcp = net::ip::tcp;

// A flooding peer: connects, then sends `bytes` (maybe nothing, maybe half a request).
struct FloodConnection {
  FloodConnection(net::io_context& io, std::uint16_t port, std::string_view bytes) : socket(io) {
    boost::system::error_code ec;
    socket.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port), ec);
    if (!ec && !bytes.empty()) net::write(socket, net::buffer(bytes), ec);
  }
  tcp::socket socket;
};

}  // namespace

TEST_CASE("a flood of unauthenticated connections past the slot count leaves requests with the token served",
          "[collector][socket]") {
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.limits.max_connections = 24;
  config.limits.unauthenticated_timeout = 10min;  // eviction alone must make room
  config.limits.idle_keepalive_timeout = 10min;
  config.limits.read_timeout = 10min;
  Harness h(config);
  require_ok(h.collector.listen());
  h.start_loop();
  const auto url = dtraced::http::parse_base_url(fmt::format("http://127.0.0.1:{}", h.collector.port()));
  REQUIRE(url);
  const dtraced::http::ClientTimeouts timeouts{kBound, kBound, kBound};

  // 3 x 20 connections for 24 slots: idle, slowloris, and /healthz kept alive after its answer.
  net::io_context io;
  std::vector<std::unique_ptr<FloodConnection>> flood;
  for (int i = 0; i < 20; ++i) {
    flood.push_back(std::make_unique<FloodConnection>(io, h.collector.port(), ""));
    flood.push_back(std::make_unique<FloodConnection>(io, h.collector.port(), "GET /healthz HTTP/1.1\r\nHost: x\r\n"));
    flood.push_back(
        std::make_unique<FloodConnection>(io, h.collector.port(), "GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n"));
    std::array<char, 512> answer;
    boost::system::error_code ec;
    flood.back()->socket.read_some(net::buffer(answer), ec);  // the answer, or a 503 / close
  }

  // Clients with the token, each on a fresh connection: all answered.
  for (int i = 0; i < 30; ++i) {
    INFO("request " << i);
    const auto res = dtraced::http::request_sync(*url, make(Verb::get, "/v1/jobs"), timeouts, 1 << 20);
    REQUIRE(res.ok());
    CHECK(res.response.result() == Status::ok);
  }
  // A wrong token does not buy a slot either way, and is still refused.
  const auto wrong = dtraced::http::request_sync(*url, make(Verb::get, "/v1/jobs", "", "nope"), timeouts, 1 << 20);
  REQUIRE(wrong.ok());
  CHECK(wrong.response.result() == Status::unauthorized);
  CHECK(h.metrics().http.evicted_connections > 0);
  // A stop waits for requests mid-read (the slowloris ones) until its grace: the flood goes first.
  flood.clear();
  CHECK(h.stop_loop() == 0);
}
