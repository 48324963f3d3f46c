#include "worker/backoff.h"

#include <algorithm>
#include <cassert>

namespace dtraced::worker {

Backoff::Backoff(Ms initial, Ms max) : initial_(initial), max_(max) {
  assert(initial.count() > 0);
  assert(initial <= max);
}

Backoff::Ms Backoff::cap(std::uint32_t failures) const {
  // Doubling stops as soon as it reaches max, so a large failure count cannot overflow.
  Ms cap = initial_;
  for (std::uint32_t i = 0; i < failures && cap < max_; ++i) cap = std::min(max_, cap * 2);
  return cap;
}

Backoff::Ms Backoff::delay(std::uint32_t failures, std::mt19937_64& rng) const {
  std::uniform_int_distribution<Ms::rep> uniform(0, cap(failures).count());
  return Ms{uniform(rng)};
}

std::chrono::milliseconds jittered_retry_after(std::chrono::milliseconds asked, std::mt19937_64& rng) {
  const auto base = std::clamp(asked, kMinRetryAfter, kMaxRetryAfter).count();
  std::uniform_int_distribution<std::chrono::milliseconds::rep> uniform(base, base + base / 2);
  return std::chrono::milliseconds{uniform(rng)};
}

}  // namespace dtraced::worker
