// dtraced::cli retries: how the client verbs ride out a busy or briefly unreachable collector.
//
// Owns: which failed exchanges are worth repeating (classify), and the policy that spaces the
// repeats and ends them (RetryPolicy), shared by every client verb and by `status --wait`:
//   - a 503 is retried whatever the method: the collector sends it before changing anything (a
//     full store queue, a failed transaction that rolled back, too many connections, a large
//     answer held back; none follows a stored change), so repeating a POST cannot apply it twice;
//   - no answer at all (refused, reset, a deadline passed) is retried for a GET only: a POST that
//     got no answer may have been applied;
//   - anything else (4xx, other 5xx, an answer too large or not HTTP) is final.
// The wait before a retry is the workers' capped exponential backoff with full jitter
// (worker/backoff.h), never shorter than a 503's Retry-After (jittered up to half again, so the
// clients a collector turned away together do not come back together), and never past the
// budget: a run of failures ends once it has lasted `budget`, with one last try at the end.
//
// Thread safety: a RetryPolicy belongs to one verb's thread; classify is a pure function.
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>
#include <random>
#include <string>

#include "http/client.h"
#include "http/types.h"
#include "util/clock.h"

namespace dtraced::cli {

// What a failed exchange means for the next try.
struct Failure {
  bool retryable = false;
  std::optional<std::chrono::milliseconds> retry_after;  // a 503's Retry-After, when it had one
  std::string reason;  // for the wait line: "collector busy (503 ...)", "no answer from ..."
};

// `result` of a `verb` request for `target`, which was not a 2xx answer.
Failure classify(const http::ClientResult& result, http::Verb verb, const std::string& target);

// A Retry-After field in seconds ("2"), as a duration; nullopt for anything else (an HTTP date,
// a negative or absurd number).
std::optional<std::chrono::milliseconds> parse_retry_after(std::string_view field);

class RetryPolicy {
 public:
  using Ms = std::chrono::milliseconds;
  static constexpr Ms kInitial{500};
  static constexpr Ms kMax{5'000};
  // Never retry sooner than this, so a collector that says "0" is not spun on.
  static constexpr Ms kMinWait{100};

  RetryPolicy(Ms budget, std::uint64_t seed) : budget_(budget), rng_(seed) {}

  // After a failed attempt at `now`: how long to wait before the next one, or nullopt when the
  // failure is final or this run of failures has used its budget.
  std::optional<Ms> next_wait(const Failure& failure, util::TimePoint now);

  // Ends the current run of failures (the next failure starts a new one with a full budget).
  void succeeded() { failures_ = 0; }

  // Consecutive failures so far, and how long they have lasted at `now`.
  std::uint32_t failures() const { return failures_; }
  Ms spent(util::TimePoint now) const;
  Ms budget() const { return budget_; }

 private:
  Ms budget_;
  std::mt19937_64 rng_;
  std::uint32_t failures_ = 0;
  util::TimePoint run_start_;
};

}  // namespace dtraced::cli
