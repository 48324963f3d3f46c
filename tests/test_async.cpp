// dtraced::async and util::Clock: sleeps end when the injected clock says so (a ManualClock moved
// by the test, or the real clock), an Event ends them early, on_pool brings results and
// exceptions back to the loop, and ManualClock's wake list is ordered and cancellable.
#include <chrono>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/thread_pool.hpp>
#include <catch2/catch.hpp>

#include "async/async.h"
#include "util/clock.h"

namespace {

namespace net = boost::asio;
using namespace std::chrono_literals;
using dtraced::util::ManualClock;

}  // namespace

TEST_CASE("a ManualClock moves only when told and wakes sleepers in deadline order", "[async][clock]") {
  ManualClock clock;
  const auto t0 = clock.now();
  const auto u0 = clock.unix_seconds();
  std::vector<int> woke;
  clock.wake_at(t0 + 30ms, [&] { woke.push_back(30); });
  const std::uint64_t cancelled = clock.wake_at(t0 + 20ms, [&] { woke.push_back(20); });
  clock.wake_at(t0 + 10ms, [&] { woke.push_back(10); });
  CHECK(clock.sleepers() == 3);
  CHECK(clock.next_deadline() == t0 + 10ms);
  clock.cancel_wake(cancelled);
  CHECK(clock.sleepers() == 2);

  clock.advance(9ms);
  CHECK(woke.empty());
  clock.advance(25ms);
  CHECK(woke == std::vector<int>{10, 30});
  CHECK(clock.now() == t0 + 34ms);
  CHECK(clock.sleepers() == 0);
  // A deadline already passed wakes at once; the clock never goes back.
  clock.wake_at(t0, [&] { woke.push_back(0); });
  CHECK(woke.back() == 0);
  clock.advance_to(t0);
  CHECK(clock.now() == t0 + 34ms);
  clock.advance(2s);
  CHECK(clock.unix_seconds() == u0 + 2);
}

TEST_CASE("sleep_until on a ManualClock ends when the test moves the clock", "[async][clock]") {
  ManualClock clock;
  net::io_context io;
  bool done = false;
  net::co_spawn(
      io,
      [&]() -> dtraced::async::Awaitable<> {
        co_await dtraced::async::sleep_for(clock, 1h);
        done = true;
      },
      dtraced::async::log_failure("sleeper"));
  // The loop runs until the sleeper waits; a real hour is not waited for.
  io.poll();
  REQUIRE(clock.sleepers() == 1);
  CHECK_FALSE(done);
  clock.advance(59min);
  io.poll();
  CHECK_FALSE(done);
  // From another thread, as a test thread would while the loop runs.
  std::thread mover([&] { clock.advance(1min); });
  mover.join();
  io.run();
  CHECK(done);
  CHECK(clock.sleepers() == 0);
}

TEST_CASE("an Event ends a sleep early and the clock's wake is forgotten", "[async][clock]") {
  ManualClock clock;
  net::io_context io;
  dtraced::async::Event stop(io.get_executor());
  bool done = false;
  net::co_spawn(
      io,
      [&]() -> dtraced::async::Awaitable<> {
        co_await dtraced::async::sleep_for(clock, 10s, &stop);
        done = true;
      },
      dtraced::async::log_failure("sleeper"));
  io.poll();
  REQUIRE(clock.sleepers() == 1);
  stop.set();
  io.run();
  CHECK(done);
  CHECK(clock.sleepers() == 0);
}

TEST_CASE("sleep_until on the real clock waits on a real timer", "[async][clock]") {
  net::io_context io;
  const auto& clock = dtraced::util::real_clock();
  const auto start = clock.now();
  bool done = false;
  net::co_spawn(
      io,
      [&]() -> dtraced::async::Awaitable<> {
        co_await dtraced::async::sleep_for(clock, 5ms);
        done = true;
      },
      dtraced::async::log_failure("sleeper"));
  io.run();
  CHECK(done);
  CHECK(clock.now() - start >= 5ms);  // a lower bound only: never a timing assertion's upper end
}

TEST_CASE("on_pool returns the pool's result, or its exception, on the loop", "[async]") {
  net::io_context io;
  net::thread_pool pool(1);
  const auto loop_thread = std::this_thread::get_id();
  std::string got;
  bool threw = false;
  bool resumed_on_loop = true;
  net::co_spawn(
      io,
      [&]() -> dtraced::async::Awaitable<> {
        auto work = [] { return std::string("from the pool"); };
        got = co_await dtraced::async::on_pool(pool, std::move(work));
        resumed_on_loop = resumed_on_loop && std::this_thread::get_id() == loop_thread;
        auto fail = []() -> int { throw std::runtime_error("no"); };
        try {
          co_await dtraced::async::on_pool(pool, std::move(fail));
        } catch (const std::runtime_error&) {
          threw = true;
        }
        resumed_on_loop = resumed_on_loop && std::this_thread::get_id() == loop_thread;
      },
      dtraced::async::log_failure("bridge"));
  io.run();
  pool.join();
  CHECK(got == "from the pool");
  CHECK(threw);
  CHECK(resumed_on_loop);
}
