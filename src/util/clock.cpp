#include "util/clock.h"

#include <utility>
#include <vector>

namespace dtraced::util {

std::int64_t RealClock::unix_seconds() const {
  return std::chrono::duration_cast<std::chrono::seconds>(std::chrono::system_clock::now().time_since_epoch()).count();
}

const Clock& real_clock() {
  static const RealClock clock;
  return clock;
}

ManualClock::ManualClock(TimePoint start, std::int64_t unix_start)
    : now_(start), start_(start), unix_start_(unix_start) {}

TimePoint ManualClock::now() const {
  std::lock_guard lock(mu_);
  return now_;
}

std::int64_t ManualClock::unix_seconds() const {
  std::lock_guard lock(mu_);
  return unix_start_ + std::chrono::duration_cast<std::chrono::seconds>(now_ - start_).count();
}

std::uint64_t ManualClock::wake_at(TimePoint deadline, std::function<void()> wake) const {
  std::unique_lock lock(mu_);
  const std::uint64_t id = next_id_++;
  if (deadline <= now_) {
    lock.unlock();
    wake();
    return id;
  }
  wakes_.emplace(std::pair(deadline, id), std::move(wake));
  changed_.notify_all();
  return id;
}

void ManualClock::cancel_wake(std::uint64_t id) const {
  if (id == 0) return;
  std::lock_guard lock(mu_);
  for (auto it = wakes_.begin(); it != wakes_.end(); ++it) {
    if (it->first.second == id) {
      wakes_.erase(it);
      changed_.notify_all();
      return;
    }
  }
}

void ManualClock::advance(SteadyClock::duration by) {
  TimePoint target;
  {
    std::lock_guard lock(mu_);
    target = now_ + by;
  }
  advance_to(target);
}

void ManualClock::advance_to(TimePoint t) {
  std::vector<std::function<void()>> due;
  {
    std::lock_guard lock(mu_);
    if (t > now_) now_ = t;
    while (!wakes_.empty() && wakes_.begin()->first.first <= now_) {
      due.push_back(std::move(wakes_.begin()->second));
      wakes_.erase(wakes_.begin());
    }
    changed_.notify_all();
  }
  for (auto& wake : due) wake();
}

std::optional<TimePoint> ManualClock::next_deadline() const {
  std::lock_guard lock(mu_);
  if (wakes_.empty()) return std::nullopt;
  return wakes_.begin()->first.first;
}

std::size_t ManualClock::sleepers() const {
  std::lock_guard lock(mu_);
  return wakes_.size();
}

bool ManualClock::wait_for_sleepers(std::size_t n, std::chrono::milliseconds bound) const {
  std::unique_lock lock(mu_);
  return changed_.wait_for(lock, bound, [&] { return wakes_.size() >= n; });
}

}  // namespace dtraced::util
