// dtraced::util clock: the one way the daemons read time, so that tests can drive it.
//
// Owns: the Clock interface (a monotonic clock for deadlines and rates, and the wall clock for
// what is recorded), the real clock, and ManualClock, a clock that moves only when a test moves
// it. The daemons take a `const Clock&` and never read std::chrono clocks themselves; their
// sleeps go through async::sleep_until (async/async.h), which waits on an Asio timer for the real
// clock and on ManualClock's wake list for a manual one. Socket deadlines (connect, read, write)
// stay in real time: they bound what the kernel does, not what the daemon decides.
//
// Thread safety: every member function of every clock may be called from any thread.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>

namespace dtraced::util {

using SteadyClock = std::chrono::steady_clock;
using TimePoint = SteadyClock::time_point;

class Clock {
 public:
  virtual ~Clock() = default;

  // Monotonic time: deadlines, timeouts, rates.
  virtual TimePoint now() const = 0;
  // Wall-clock seconds since the Unix epoch: what is stored and shown (a job's creation time).
  virtual std::int64_t unix_seconds() const = 0;

  // For clocks that do not follow real time: calls `wake` (from the thread that moves the
  // clock, without holding a lock) once now() >= deadline, at once if it already is, and returns
  // a non-zero id for cancel_wake. A real-time clock returns 0 and never calls `wake`: the
  // caller then waits on a real timer (async::sleep_until does both).
  virtual std::uint64_t wake_at(TimePoint deadline, std::function<void()> wake) const = 0;
  // Forgets a wake that has not run yet; harmless after it ran. Id 0 is ignored.
  virtual void cancel_wake(std::uint64_t id) const = 0;
};

// std::chrono's steady and system clocks.
class RealClock final : public Clock {
 public:
  TimePoint now() const override { return SteadyClock::now(); }
  std::int64_t unix_seconds() const override;
  std::uint64_t wake_at(TimePoint, std::function<void()>) const override { return 0; }
  void cancel_wake(std::uint64_t) const override {}
};

// The process's real clock. It has no state: sharing it shares nothing mutable.
const Clock& real_clock();

// A clock for tests: it starts at `start` (and `unix_start` on the wall clock) and moves only by
// advance() and advance_to(); sleepers wake when it passes their deadline, so a test decides when
// a backoff or a grace period is over instead of waiting for it.
class ManualClock final : public Clock {
 public:
  explicit ManualClock(TimePoint start = TimePoint{} + std::chrono::hours(1), std::int64_t unix_start = 1'700'000'000);

  TimePoint now() const override;
  std::int64_t unix_seconds() const override;
  std::uint64_t wake_at(TimePoint deadline, std::function<void()> wake) const override;
  void cancel_wake(std::uint64_t id) const override;

  // Moves the clock forward (never back) and runs the wakes whose deadline it passed, in deadline
  // order, on the calling thread.
  void advance(SteadyClock::duration by);
  void advance_to(TimePoint t);

  // The earliest deadline anyone sleeps until, if anyone does.
  std::optional<TimePoint> next_deadline() const;
  // How many wakes are pending.
  std::size_t sleepers() const;
  // Blocks the calling thread until at least `n` wakes are pending, or `bound` of real time has
  // passed (then false): "the daemon is now waiting on the clock".
  bool wait_for_sleepers(std::size_t n, std::chrono::milliseconds bound) const;

 private:
  mutable std::mutex mu_;
  mutable std::condition_variable changed_;
  TimePoint now_;
  const TimePoint start_;
  const std::int64_t unix_start_;
  mutable std::uint64_t next_id_ = 1;
  // By deadline, then id (the order they were registered in).
  mutable std::map<std::pair<TimePoint, std::uint64_t>, std::function<void()>> wakes_;
};

}  // namespace dtraced::util
