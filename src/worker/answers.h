// dtraced::worker answers: what the collector's answer to a lease or a submission means for the
// worker, as pure functions of the exchange (README.md, "HTTP API"), tested without sockets.
//
// A lease answer is a lease, a "retry after", or a failure to retry with backoff. A submission's
// answer is one of four verdicts: acknowledged, job gone, rejected (a bug: sending it again cannot
// help), or retry (network errors, 5xx, 401, 408, 429, and any answer that cannot be read).
//
// Stateless functions over values: thread-safe.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "http/client.h"
#include "http/types.h"
#include "protocol/messages.h"

namespace dtraced::worker {

// A failing collector is logged on the first failure of a run of failures and then every
// kLogEveryNthFailure-th: an outage of an hour leaves a few dozen lines, not one per attempt.
inline constexpr std::uint32_t kLogEveryNthFailure = 10;
// Bytes of an unexpected answer's body quoted in a log line.
inline constexpr std::size_t kMaxQuotedBodyBytes = 200;

// Whether the failure that makes `failures_in_a_row` is one to log (see kLogEveryNthFailure).
bool should_log_failure(std::uint32_t failures_in_a_row);

// "HTTP 503: the store is busy" from an answer that is not the one hoped for: the JSON error
// body when there is one, else the start of the body with anything unprintable masked.
std::string describe_answer(const http::Response& response);

// Exactly one of: a lease, a "retry after", or an error.
struct LeaseAnswer {
  std::optional<protocol::Lease> lease;
  std::optional<std::chrono::milliseconds> retry_after;
  std::string error;  // a failure, to retry with backoff
  bool token_rejected = false;
};

// The meaning of the answer to POST /v1/lease.
LeaseAnswer classify_lease(const http::ClientResult& result);

enum class SubmitVerdict {
  kAcknowledged,  // stored or already done: the tile is safe
  kJobGone,       // drop it and everything else of its job
  kRejected,      // the collector will never take it: drop it and say so
  kRetry,         // keep it and try again
};

struct SubmitAnswer {
  SubmitVerdict verdict = SubmitVerdict::kRetry;
  std::string message;
  bool token_rejected = false;
};

// The meaning of the answer to PUT /v1/jobs/{job}/tiles/{tile}.
SubmitAnswer classify_submit(const http::ClientResult& result);

}  // namespace dtraced::worker
