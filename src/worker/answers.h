// dtraced::worker answers: what the collector's answer to a lease or a submission means for the
// worker, as pure functions of the exchange (README.md, "HTTP API"), tested without sockets.
//
// A lease answer is a lease, a "retry after", or a failure to retry with backoff. A submission's
// answer (which may carry the next lease the upload asked for, protocol::kNextLeaseHeader) is one
// of four verdicts: acknowledged, job gone, rejected (a bug: sending it again cannot
// help), or retry (network errors, 5xx, 401, 408, 429, and any answer that cannot be read).
//
// Stateless functions over values: thread-safe.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <optional>
#include <set>
#include <string>
#include <utility>

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
  // With retry_after: the collector has finished all its work and is going away
  // (protocol::kFinishedHeader is "1"; any other value is read as "not finished").
  bool collector_finished = false;
  std::string error;  // a failure, to retry with backoff
  bool token_rejected = false;
};

// The meaning of the answer to POST /v1/lease.
LeaseAnswer classify_lease(const http::ClientResult& result);
// A lease reply (POST /v1/lease's, or an upload answer's "next") as a LeaseAnswer; `response`
// holds the protocol::kFinishedHeader that a retry-after may come with.
LeaseAnswer lease_answer(protocol::LeaseReply reply, const http::Response& response);

enum class SubmitVerdict {
  kAcknowledged,  // stored or already done: the tile is safe
  kJobGone,       // drop it and everything else of its job
  kRejected,      // the collector will never take it: drop it and say so
  kRetry,         // keep it and try again
};

struct SubmitAnswer {
  SubmitAnswer() = default;
  SubmitAnswer(SubmitVerdict v, std::string m, bool token = false)
      : verdict(v), message(std::move(m)), token_rejected(token) {}
  SubmitVerdict verdict = SubmitVerdict::kRetry;
  std::string message;
  bool token_rejected = false;
  // With kAcknowledged or kJobGone: the next lease (a lease or a retry-after) the answer carried,
  // when the upload asked for one and the collector gave it (protocol::UploadAnswer).
  std::optional<LeaseAnswer> next;
};

// The meaning of the answer to PUT /v1/jobs/{job}/tiles/{tile}.
SubmitAnswer classify_submit(const http::ClientResult& result);

// Jobs answered "gone" (the most recent kRememberedGoneJobs), to tell the normal end of a job
// from a collector that leases a job again and again and answers "gone" for every tile of it
// (a refusal, which the worker must back off from: retry_gate.h).
inline constexpr std::size_t kRememberedGoneJobs = 1024;

class GoneAnswers {
 public:
  // A "gone" answer for `job`; `marked` says whether the worker still has the job marked gone
  // (pipeline.cpp unmarks a job the collector leases again). Returns whether the answer is a
  // refusal: the job was answered gone before and has been leased again since. The first answer,
  // and those for tiles in flight when it came, are the news that a job ended, not a refusal.
  bool refusal(std::uint64_t job, bool marked);

 private:
  std::set<std::uint64_t> jobs_;
  std::deque<std::uint64_t> order_;
};

}  // namespace dtraced::worker
