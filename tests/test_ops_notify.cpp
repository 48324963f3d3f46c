// The systemd notifier (async/systemd_notifier.h) on a ManualClock: WATCHDOG=1 every half
// period while the loop turns, STATUS= only when its text changes, nothing after the stop; the
// watchdog period from the environment's values; the collector's status line.
#include <chrono>
#include <string>
#include <string_view>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <catch2/catch.hpp>

#include "async/systemd_notifier.h"
#include "collector/systemd_status.h"
#include "util/clock.h"

namespace {

namespace net = boost::asio;
using namespace std::chrono_literals;
using dtraced::async::watchdog_period;

}  // namespace

TEST_CASE("the watchdog period is WATCHDOG_USEC when it is meant for this process", "[async][systemd]") {
  CHECK(watchdog_period("30000000", nullptr, 42) == std::chrono::microseconds(30000000));
  CHECK(watchdog_period("30000000", "42", 42) == std::chrono::microseconds(30000000));
  CHECK_FALSE(watchdog_period("30000000", "43", 42));  // inherited from a parent
  CHECK_FALSE(watchdog_period(nullptr, nullptr, 42));
  for (const char* bad : {"", "0", "-5", "30s", "1e6", " 5", "99999999999999999999999", "31536000000001"}) {
    INFO(bad);
    CHECK_FALSE(watchdog_period(bad, nullptr, 42));
  }
  CHECK_FALSE(watchdog_period("30000000", "x", 42));
}

TEST_CASE("the notifier pings every half period and sends STATUS only when it changes", "[async][systemd]") {
  dtraced::util::ManualClock clock;
  net::io_context io;
  dtraced::async::Event stop(io.get_executor());
  std::vector<std::string> sent;
  std::string status = "jobs: 0 queued";
  dtraced::async::NotifierOptions options;
  options.watchdog = 4s;
  options.status_every = 5s;
  bool ended = false;
  net::co_spawn(io,
                dtraced::async::run_systemd_notifier(
                    clock, options, stop, [&] { return status; }, [&](std::string_view s) { sent.emplace_back(s); }),
                [&](std::exception_ptr e) {
                  CHECK_FALSE(e);
                  ended = true;
                });
  io.poll();
  CHECK(sent == std::vector<std::string>{"WATCHDOG=1", "STATUS=jobs: 0 queued"});
  sent.clear();
  clock.advance(1999ms);
  io.poll();
  CHECK(sent.empty());
  clock.advance(1ms);  // 2 s: half the period
  io.poll();
  CHECK(sent == std::vector<std::string>{"WATCHDOG=1"});
  sent.clear();
  clock.advance(2s);  // 4 s
  io.poll();
  CHECK(sent == std::vector<std::string>{"WATCHDOG=1"});
  sent.clear();
  clock.advance(2s);  // 6 s: the status is looked at again, unchanged
  io.poll();
  CHECK(sent == std::vector<std::string>{"WATCHDOG=1"});
  sent.clear();
  status = "jobs: 1 queued";
  clock.advance(6s);  // 12 s: changed
  io.poll();
  CHECK(sent == std::vector<std::string>{"WATCHDOG=1", "STATUS=jobs: 1 queued"});
  sent.clear();
  stop.set();
  io.poll();
  CHECK(ended);
  CHECK(sent.empty());
  CHECK(clock.sleepers() == 0);
}

TEST_CASE("without a watchdog the notifier only keeps the status current", "[async][systemd]") {
  dtraced::util::ManualClock clock;
  net::io_context io;
  dtraced::async::Event stop(io.get_executor());
  std::vector<std::string> sent;
  int asked = 0;
  net::co_spawn(io,
                dtraced::async::run_systemd_notifier(
                    clock, {}, stop,
                    [&] {
                      ++asked;
                      return std::string("idle");
                    },
                    [&](std::string_view s) { sent.emplace_back(s); }),
                dtraced::async::log_failure("notifier"));
  io.poll();
  clock.advance(60s);
  io.poll();
  CHECK(sent == std::vector<std::string>{"STATUS=idle"});
  CHECK(asked >= 2);
  stop.set();
  io.run();
  CHECK(clock.sleepers() == 0);
}

TEST_CASE("the collector's status line counts jobs by state and workers active and quiet", "[collector][systemd]") {
  dtraced::collector::MetricsSnapshot m;
  m.jobs_by_state = {2, 1, 5, 3};
  CHECK(dtraced::collector::systemd_status(m, {}) ==
        "jobs: 2 queued, 1 rendering, 5 done, 3 cancelled; workers: 0 active, 0 quiet");
  CHECK(dtraced::collector::systemd_status(m, {.active = 4, .quiet = 1}) ==
        "jobs: 2 queued, 1 rendering, 5 done, 3 cancelled; workers: 4 active, 1 quiet");
  m.jobs_by_state[4] = 6;  // protocol::JobState::kPaused
  CHECK(dtraced::collector::systemd_status(m, {}) ==
        "jobs: 2 queued, 1 rendering, 6 paused, 5 done, 3 cancelled; workers: 0 active, 0 quiet");
}
