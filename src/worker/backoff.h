// dtraced::worker retry delays: exponential backoff with full jitter, and the jitter added to a
// collector's "retry after N ms".
//
// Why full jitter (a delay drawn uniformly from [0, cap]): after a collector restart every worker
// of a farm retries at once; spreading each retry over the whole window turns that herd into a
// trickle, and the cap doubles per consecutive failure so a long outage costs a request every few
// seconds per worker, not a spin. The randomness comes from a generator the caller owns (one per
// worker, seeded), never from a global one.
//
// Pure functions of their arguments (the generator is advanced): thread-safe on distinct
// generators.
#pragma once

#include <chrono>
#include <cstdint>
#include <random>

namespace dtraced::worker {

// A collector may answer "retry after 0 ms" (or 1 ms): asking again that soon would spin, so
// never sooner than the shortest wait a collector sends by default (queue.min_retry_after).
inline constexpr std::chrono::milliseconds kMinRetryAfter{50};
// Nor later than the longest the protocol lets it ask for (protocol::kMaxRetryAfterMs): a worker
// told to wait longer (a newer or broken collector) still asks again within a minute.
inline constexpr std::chrono::milliseconds kMaxRetryAfter{60'000};

class Backoff {
 public:
  using Ms = std::chrono::milliseconds;

  // 0 < initial <= max (asserted; WorkerConfig validation guarantees it).
  Backoff(Ms initial, Ms max);

  // The window after `failures` consecutive failures (0 for the first retry): min(max, initial x
  // 2^failures). Non-decreasing in `failures`, never above max, no overflow for any count.
  Ms cap(std::uint32_t failures) const;

  // A delay drawn uniformly from [0, cap(failures)].
  Ms delay(std::uint32_t failures, std::mt19937_64& rng) const;

  Ms initial() const { return initial_; }
  Ms max() const { return max_; }

 private:
  Ms initial_;
  Ms max_;
};

// How long to wait when the collector says "retry after `asked`": uniformly in [base, 1.5 x base]
// with base = `asked` clamped to [kMinRetryAfter, kMaxRetryAfter]; never sooner than asked (up to
// the ceiling), so that the workers a collector turns away together do not come back together.
std::chrono::milliseconds jittered_retry_after(std::chrono::milliseconds asked, std::mt19937_64& rng);

}  // namespace dtraced::worker
