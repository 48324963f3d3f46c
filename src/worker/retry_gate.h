// dtraced::worker retry gate: when requests of one kind (leases, or submissions) may go out.
//
// After a failure the next request waits a backoff delay; while the collector keeps failing, or
// has no work ("retry after"), only one request at a time goes out (the probe) and the others
// wait for its outcome, so that a worker with many threads asks once, not once per thread. Probes
// are taken in the order the requests arrived at the gate, and a request that failed queues again
// at the back: if the collector fails on one tile only, the others still get their turn, succeed,
// and end the backoff for everyone. Failures are counted in rounds: the requests that were
// already in flight when the collector went away fail together, and count (and back off) once.
//
// Refusals are the other way a collector can fail a worker: it answers every lease, and then
// refuses the tile (a 4xx that sending it again cannot change, or "job gone" for a job it leased
// again). Each lease then succeeds, so failures never count up, and without refusals the worker
// would lease, render and be refused as fast as the network allows (2,100 requests/s were seen).
// So refusals in a row count on their own, only an acknowledged tile ends them, and while they
// last leases go one at a time, each after a backoff drawn from the refusals in a row.
//
// Time: the gate reads its deadlines from the util::Clock it is given and sleeps on it through
// async::sleep_until, so a test with a util::ManualClock decides when a backoff is over.
//
// Thread safety: none. One owner, the worker's event loop: the gate, its waits and its Attempts
// belong to the executor it was made with.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <random>
#include <set>
#include <utility>

#include "async/async.h"
#include "util/clock.h"
#include "worker/backoff.h"

namespace dtraced::worker {

class RetryGate {
 public:
  // A request allowed out. Report its outcome with succeeded() or failed(); one dropped without
  // either (its coroutine stopped) just frees the probe for another request.
  class Attempt {
   public:
    Attempt(Attempt&& other) noexcept
        : gate_(std::exchange(other.gate_, nullptr)), round_(other.round_), probe_(other.probe_) {}
    Attempt(const Attempt&) = delete;
    Attempt& operator=(const Attempt&) = delete;
    Attempt& operator=(Attempt&&) = delete;
    ~Attempt() {
      if (gate_ != nullptr) gate_->finish(*this);
    }

    // Whether this request is the one probe a failing or idle collector gets at a time.
    bool probe() const { return probe_; }

   private:
    friend class RetryGate;
    Attempt(RetryGate* gate, std::uint64_t round, bool probe) : gate_(gate), round_(round), probe_(probe) {}

    RetryGate* gate_;
    std::uint64_t round_;
    bool probe_;
  };

  // `clock` and `rng` (the retry jitter) outlive the gate; the rng may be shared with other gates
  // of the same event loop.
  RetryGate(const async::Executor& executor, const util::Clock& clock, Backoff backoff, std::mt19937_64& rng)
      : clock_(clock), backoff_(backoff), rng_(rng), changed_(executor) {}

  // Waits until a request may go out; nullopt once `stop` is set.
  async::Awaitable<std::optional<Attempt>> enter(async::Event& stop);

  // The collector answered. Returns the number of failures in a row this ends (0 normally).
  std::uint32_t succeeded(Attempt& attempt);

  // The request failed. Returns the failures in a row counting this one, or 0 when another
  // request of the same round has already failed (and backed off) for it.
  std::uint32_t failed(Attempt& attempt);

  // The collector would not take a tile it leased: the next request waits a backoff drawn from
  // the refusals in a row, and requests go one at a time until accepted(). Returns the refusals
  // in a row counting this one.
  std::uint32_t refused();

  // The collector took a tile: refusals end. Returns the refusals in a row this ends.
  std::uint32_t accepted();

  // The collector has no work: ask again (one request at a time) no sooner than `delay` from now.
  void idle_for(std::chrono::milliseconds delay);

  // The collector has work again: every request may go out at once.
  void busy();

  // Whether requests go out freely now: no failures, refusals or idleness in force. A request
  // made outside the gate (the next lease asked for in a tile's upload) is made only then.
  bool open() const { return failures_ == 0 && refusals_ == 0 && !idle_; }

 private:
  struct Ticket;

  void finish(Attempt& attempt);

  const util::Clock& clock_;
  Backoff backoff_;
  std::mt19937_64& rng_;
  async::Signal changed_;  // failures, idleness or the probe changed
  std::uint32_t failures_ = 0;
  std::uint64_t round_ = 0;
  std::uint32_t refusals_ = 0;
  bool probing_ = false;
  std::uint64_t next_ticket_ = 0;
  std::set<std::uint64_t> waiting_;  // tickets of the requests at the gate, oldest first
  bool idle_ = false;
  util::TimePoint backoff_until_ = util::TimePoint::min();
  util::TimePoint idle_until_ = util::TimePoint::min();
  util::TimePoint refused_until_ = util::TimePoint::min();
};

}  // namespace dtraced::worker
