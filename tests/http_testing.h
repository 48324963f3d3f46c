// Helpers for the dtraced::http tests over real loopback sockets: a server on an ephemeral port
// with its io_context on a thread of its own, a hand-driven client socket for bytes no
// well-behaved client sends, and a few routes. Every wait is bounded (kBound).
//
// Thread safety: a TestServer's handler state (Gate) is touched on the server's thread only;
// RawConnection is used by one test thread.
#pragma once

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
#include <boost/beast/http/parser.hpp>
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

namespace http_testing {

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

inline std::string field_of(const Response& res, bhttp::field f) { return std::string(res[f]); }

inline boost::json::value json_body(const Response& res) {
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

inline void open_gate(const net::any_io_executor& executor, Gate& gate) {
  net::post(executor, [&gate] {
    gate.open = true;
    for (net::steady_timer* timer : gate.waiting) timer->cancel();
  });
}

// The routes the tests talk to: /echo answers its JSON body, /throw throws, /big answers 4 KiB,
// /slow waits for the gate.
inline Server::Handler routes(Gate* gate = nullptr) {
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

inline ServerLimits generous_limits() {
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
             const dtraced::util::Clock& clock = dtraced::util::real_clock(), Server::Authenticated authenticated = {})
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), 0, limits, std::move(handler), std::move(check),
                std::move(authenticated), clock) {
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

  // The next response, or nullopt when the connection ended first (or its body is over
  // `body_limit`).
  std::optional<Response> read_response(std::uint64_t body_limit = 8 << 20) {
    bhttp::response_parser<bhttp::string_body> parser;
    parser.body_limit(body_limit);
    error_code result = net::error::timed_out;
    run_bounded(
        [&] { bhttp::async_read(socket_, buffer_, parser, [&](const error_code& ec, std::size_t) { result = ec; }); });
    if (result) return std::nullopt;
    return parser.release();
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

inline std::string echo_request(std::string_view json, bool keep_alive = true) {
  return fmt::format(
      "POST /echo HTTP/1.1\r\nHost: test\r\nContent-Type: application/json\r\n{}Content-Length: {}\r\n\r\n{}",
      keep_alive ? "" : "Connection: close\r\n", json.size(), json);
}

inline ClientResult post_echo(const Url& url, std::string json) {
  return dtraced::http::request_sync(
      url, dtraced::http::make_request(Verb::post, "/echo", std::move(json), dtraced::http::kJsonContentType),
      kTimeouts, kMaxResponse);
}

inline bool connection_refused(std::uint16_t port) {
  net::io_context io;
  tcp::socket socket(io);
  error_code ec;
  socket.connect(tcp::endpoint(net::ip::make_address("127.0.0.1"), port), ec);
  return ec == net::error::connection_refused;
}

// A port nobody listens on (just released by the kernel; another process grabbing it in between
// is possible but not on a test machine's loopback in practice).
inline std::uint16_t unused_port() {
  net::io_context io;
  tcp::acceptor acceptor(io, tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));
  return acceptor.local_endpoint().port();
}

}  // namespace http_testing
