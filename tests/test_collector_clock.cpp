// The collector in time, on a ManualClock: the ETA, a lease offered again once its bound has
// passed, a failed image write tried again after its delay, and a stop's grace; and the collector
// over a real socket. Where the collector sleeps on its clock, the loop runs on a thread of its
// own (Harness::start_loop) and the test moves the clock once the collector waits on it
// (ManualClock::wait_for_sleepers): no test waits for real time to pass.
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <functional>
#include <future>
#include <string>
#include <thread>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/lifecycle.h"
#include "collector_testing.h"
#include "eventually.h"
#include "http/client.h"

using namespace dtraced::testing;

namespace {

// A client socket to 127.0.0.1 driven by hand, every read bounded by kBound.
class RawSocket {
 public:
  explicit RawSocket(std::uint16_t port) : fd_(::socket(AF_INET, SOCK_STREAM, 0)) {
    REQUIRE(fd_ >= 0);
    sockaddr_in addr{};
    addr.sin_family = AF_INET;
    addr.sin_port = htons(port);
    addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    REQUIRE(::connect(fd_, reinterpret_cast<const sockaddr*>(&addr), sizeof addr) == 0);
  }
  ~RawSocket() { ::close(fd_); }
  RawSocket(const RawSocket&) = delete;
  RawSocket& operator=(const RawSocket&) = delete;

  void send(std::string_view bytes) {
    REQUIRE(::send(fd_, bytes.data(), bytes.size(), MSG_NOSIGNAL) == static_cast<ssize_t>(bytes.size()));
  }
  // Reads until `until` is in what was read, or the peer closes (""), or kBound passes (REQUIRE).
  std::string read_until(std::string_view until) {
    std::string got;
    char buf[1024];
    const auto deadline = std::chrono::steady_clock::now() + kBound;
    while (got.find(until) == std::string::npos) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      pollfd p{fd_, POLLIN, 0};
      REQUIRE(left.count() > 0);
      REQUIRE(::poll(&p, 1, static_cast<int>(left.count())) > 0);
      const ssize_t n = ::recv(fd_, buf, sizeof buf, 0);
      if (n <= 0) return {};
      got.append(buf, static_cast<std::size_t>(n));
    }
    return got;
  }

 private:
  int fd_;
};

}  // namespace

TEST_CASE("a job's ETA and elapsed time follow the collector's clock", "[collector][clock]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const auto leases = h.lease_all();  // the first lease starts this process's rate
  CHECK_FALSE(h.status(job).eta_s.has_value());
  h.clock.advance(6s);
  for (std::size_t i = 0; i < 3; ++i) REQUIRE(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);
  protocol::JobStatus s = h.status(job);
  CHECK(s.elapsed_s == 6.0);
  CHECK(s.eta_s == 18.0);  // 9 tiles left at 3 tiles in 6 s
  h.clock.advance(4s);
  s = h.status(job);
  CHECK(s.elapsed_s == 10.0);
  CHECK(s.eta_s == 30.0);  // 9 tiles left at 3 tiles in 10 s
}

TEST_CASE("a leased tile is offered again once its lease is older than the bound, on the collector's clock",
          "[collector][clock]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  REQUIRE(h.lease_all().size() == kTiles);
  const auto floor = h.config.queue.reoffer_floor;  // the bound before any tile time is known
  h.clock.advance(floor - 1ms);
  CHECK_FALSE(h.lease());
  h.clock.advance(1ms);
  const auto again = h.lease();
  REQUIRE(again);
  CHECK(again->job == job);
  CHECK(h.metrics().queue.reoffers == 1);
}

TEST_CASE("a failed image write is tried again after its delay on the collector's clock", "[collector][clock]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const auto leases = h.lease_all();
  for (std::size_t i = 0; i + 1 < leases.size(); ++i) h.put_ok(leases[i]);
  // The output directory becomes a file: the image cannot be written.
  const fs::path out = dir.path() / "out";
  fs::remove_all(out);
  write_text(out, "not a directory");

  h.start_loop();  // the collector is about to sleep on its clock
  CHECK(h.put_ok(leases.back()) == protocol::SubmitResult::kStored);
  REQUIRE(h.clock.wait_for_sleepers(1, kBound));
  CHECK(h.clock.next_deadline() == h.clock.now() + dtraced::collector::kFinishRetryDelay);
  CHECK(metric(h, &coll::CollectorCounters::image_write_failures) == 1);
  CHECK(h.status(job).state == protocol::JobState::kRendering);

  SECTION("once the delay has passed, the image is written") {
    fs::remove(out);
    fs::create_directory(out);
    h.clock.advance(dtraced::collector::kFinishRetryDelay);
    REQUIRE(eventually([&] { return h.status(job).state == protocol::JobState::kDone; }));
    CHECK(fs::exists(out / "job-1.png"));
    CHECK(metric(h, &coll::CollectorCounters::images_written) == 1);
    CHECK(metric(h, &coll::CollectorCounters::image_write_failures) == 1);
    CHECK(h.stop_loop() == 0);
    CHECK(stored_state(h.config).jobs[0].state == "done");
  }
  SECTION("a stop does not wait for the delay; a restart writes the image") {
    CHECK(h.stop_loop() == 0);
    CHECK(stored_state(h.config).jobs[0].state == "rendering");
  }
}

TEST_CASE("a stop lets a request in flight go on until the grace ends on the collector's clock",
          "[collector][clock][socket]") {
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.limits.read_timeout = std::chrono::minutes(10);  // a socket deadline, in real time: out of the way
  config.shutdown_grace = 30s;
  Harness h(config);
  require_ok(h.collector.listen());
  h.start_loop();

  // A tile upload whose body never comes: "100 Continue" says its head was admitted and the server
  // now waits for the body.
  RawSocket upload(h.collector.port());
  upload.send(
      fmt::format("PUT /v1/jobs/1/tiles/0 HTTP/1.1\r\nHost: test\r\nAuthorization: Bearer {}\r\n"
                  "Expect: 100-continue\r\nContent-Length: 100\r\n\r\n",
                  kToken));
  CHECK(upload.read_until("\r\n\r\n").starts_with("HTTP/1.1 100"));

  h.collector.stop();
  REQUIRE(h.clock.wait_for_sleepers(1, kBound));
  CHECK(h.clock.next_deadline() == h.clock.now() + config.shutdown_grace);
  CHECK(h.loop.wait_for(0s) == std::future_status::timeout);  // still waiting for the upload
  h.clock.advance(config.shutdown_grace);
  CHECK(h.stop_loop() == 0);
  CHECK(upload.read_until("\r\n") == "");  // cut without an answer
}

TEST_CASE("over a real socket: listen, serve, and stop gracefully", "[collector][service][socket]") {
  TempDir dir;
  Harness h(dir);
  require_ok(h.collector.listen());
  REQUIRE(h.collector.port() != 0);
  h.start_loop();
  const auto url = dtraced::http::parse_base_url(fmt::format("http://127.0.0.1:{}", h.collector.port()));
  REQUIRE(url);
  const dtraced::http::ClientTimeouts timeouts{5s, 5s, 5s};
  auto res = dtraced::http::request_sync(*url, dtraced::http::make_request(Verb::get, "/healthz"), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::ok);
  res = dtraced::http::request_sync(*url, make(Verb::post, "/v1/jobs", submit_body()), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::created);
  res = dtraced::http::request_sync(*url, make(Verb::get, "/v1/jobs", "", ""), timeouts, 1 << 20);
  REQUIRE(res.ok());
  CHECK(res.response.result() == Status::unauthorized);
  CHECK(h.stop_loop() == 0);
  // The job survived the stop.
  CHECK(stored_state(h.config).jobs.size() == 1);
}
