#include "worker/retry_gate.h"

#include <algorithm>
#include <limits>
#include <utility>

#include <boost/asio/experimental/awaitable_operators.hpp>

namespace dtraced::worker {

using namespace async::net::experimental::awaitable_operators;

// A request's place in the line for probes, from its arrival at the gate until it leaves.
struct RetryGate::Ticket {
  explicit Ticket(RetryGate& gate) : gate(gate), number(gate.next_ticket_++) { gate.waiting_.insert(number); }
  Ticket(const Ticket&) = delete;
  Ticket& operator=(const Ticket&) = delete;
  ~Ticket() {
    gate.waiting_.erase(number);
    gate.changed_.notify_all();  // the next in line may probe now
  }
  RetryGate& gate;
  const std::uint64_t number;
};

async::Awaitable<std::optional<RetryGate::Attempt>> RetryGate::enter(async::Event& stop) {
  const Ticket ticket(*this);
  for (;;) {
    if (stop.is_set()) co_return std::nullopt;
    const util::TimePoint not_before = std::max({backoff_until_, idle_until_, refused_until_});
    if (clock_.now() < not_before) {
      co_await (async::sleep_until(clock_, not_before, &stop) || changed_.wait());
      continue;
    }
    const bool probe = failures_ > 0 || idle_ || refusals_ > 0;
    if (probe && (probing_ || *waiting_.begin() != ticket.number)) {
      co_await (changed_.wait() || stop.wait());
      continue;
    }
    if (probe) probing_ = true;
    co_return std::optional<Attempt>(Attempt(this, round_, probe));
  }
}

std::uint32_t RetryGate::succeeded(Attempt& attempt) {
  finish(attempt);
  const std::uint32_t ended = failures_;
  if (failures_ > 0) {
    failures_ = 0;
    ++round_;
    backoff_until_ = util::TimePoint::min();
    changed_.notify_all();
  }
  return ended;
}

std::uint32_t RetryGate::failed(Attempt& attempt) {
  finish(attempt);
  if (attempt.round_ != round_) return 0;
  if (failures_ < std::numeric_limits<std::uint32_t>::max()) ++failures_;
  ++round_;
  backoff_until_ = clock_.now() + backoff_.delay(failures_ - 1, rng_);
  changed_.notify_all();
  return failures_;
}

std::uint32_t RetryGate::refused() {
  if (refusals_ < std::numeric_limits<std::uint32_t>::max()) ++refusals_;
  // Later than any wait already set: tiles refused together (in flight at once) do not shorten it.
  refused_until_ = std::max(refused_until_, clock_.now() + backoff_.delay(refusals_ - 1, rng_));
  changed_.notify_all();
  return refusals_;
}

std::uint32_t RetryGate::accepted() {
  const std::uint32_t ended = std::exchange(refusals_, 0);
  if (ended > 0) {
    refused_until_ = util::TimePoint::min();
    changed_.notify_all();
  }
  return ended;
}

void RetryGate::idle_for(std::chrono::milliseconds delay) {
  idle_ = true;
  idle_until_ = std::max(idle_until_, clock_.now() + delay);
}

void RetryGate::busy() {
  if (!idle_) return;
  idle_ = false;
  idle_until_ = util::TimePoint::min();
  changed_.notify_all();
}

void RetryGate::finish(Attempt& attempt) {
  if (attempt.gate_ == nullptr) return;
  attempt.gate_ = nullptr;
  if (attempt.probe_) {
    probing_ = false;
    changed_.notify_all();
  }
}

}  // namespace dtraced::worker
