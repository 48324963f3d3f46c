#include "worker/answers.h"

#include <string_view>
#include <utility>
#include <variant>

#include <boost/beast/core/string.hpp>
#include <fmt/format.h>

#include "protocol/worker_messages.h"

namespace dtraced::worker {

bool should_log_failure(std::uint32_t failures_in_a_row) {
  return failures_in_a_row == 1 || (failures_in_a_row > 0 && failures_in_a_row % kLogEveryNthFailure == 0);
}

std::string describe_answer(const http::Response& response) {
  const unsigned status = response.result_int();
  const auto error = protocol::decode_error_body(response.body());
  if (error) {
    const protocol::ErrorBody& body = error.value();
    if (body.field.empty()) return fmt::format("HTTP {}: {}", status, body.error);
    return fmt::format("HTTP {}: {} (at {})", status, body.error, body.field);
  }
  std::string excerpt = response.body().substr(0, kMaxQuotedBodyBytes);
  for (char& c : excerpt) {
    if (c < 0x20 || c > 0x7e) c = '?';
  }
  if (excerpt.empty()) return fmt::format("HTTP {}", status);
  return fmt::format("HTTP {}: {}", status, excerpt);
}

LeaseAnswer classify_lease(const http::ClientResult& result) {
  LeaseAnswer answer;
  if (!result.ok()) {
    answer.error = result.message;
    return answer;
  }
  if (result.response.result() == http::Status::unauthorized) {
    answer.error = fmt::format("credential rejected ({})", describe_answer(result.response));
    answer.token_rejected = true;
    return answer;
  }
  if (result.response.result() != http::Status::ok) {
    answer.error = describe_answer(result.response);
    return answer;
  }
  auto reply = protocol::decode_lease_reply(result.response.body());
  if (!reply) {
    answer.error = fmt::format("malformed lease reply: {}", reply.error().front().to_string());
    return answer;
  }
  return lease_answer(std::move(reply).value(), result.response);
}

LeaseAnswer lease_answer(protocol::LeaseReply reply, const http::Response& response) {
  LeaseAnswer answer;
  if (auto* lease = std::get_if<protocol::Lease>(&reply)) {
    answer.lease = std::move(*lease);
  } else {
    answer.retry_after = std::chrono::milliseconds{std::get<protocol::RetryAfter>(reply).ms};
    const auto it =
        response.find(boost::beast::string_view(protocol::kFinishedHeader.data(), protocol::kFinishedHeader.size()));
    if (it != response.end()) {
      const std::string_view value(it->value().data(), it->value().size());
      answer.collector_finished = protocol::parse_finished_header(value).value_or(false);
    }
  }
  return answer;
}

SubmitAnswer classify_submit(const http::ClientResult& result) {
  if (!result.ok()) return {SubmitVerdict::kRetry, result.message};
  const http::Response& response = result.response;
  const unsigned status = response.result_int();
  if (response.result() == http::Status::ok) {
    auto decoded = protocol::decode_upload_answer(response.body());
    if (!decoded) {
      // Probably stored, but it cannot be known: sending it again is harmless (already done).
      return {SubmitVerdict::kRetry, fmt::format("malformed answer: {}", decoded.error().front().to_string())};
    }
    protocol::UploadAnswer& upload = decoded.value();
    SubmitAnswer answer{SubmitVerdict::kAcknowledged, std::string(protocol::to_string(upload.result))};
    if (upload.result == protocol::SubmitResult::kJobGone) answer = {SubmitVerdict::kJobGone, "job gone"};
    if (upload.next) answer.next = lease_answer(std::move(*upload.next), response);
    return answer;
  }
  if (response.result() == http::Status::gone) {
    SubmitAnswer answer{SubmitVerdict::kJobGone, describe_answer(response)};
    // The job is gone, not the farm's work: the answer may carry the next lease all the same.
    if (auto decoded = protocol::decode_upload_answer(response.body()); decoded && decoded.value().next) {
      answer.next = lease_answer(std::move(*decoded.value().next), response);
    }
    return answer;
  }
  if (response.result() == http::Status::unauthorized) {
    return {SubmitVerdict::kRetry, fmt::format("credential rejected ({})", describe_answer(response)),
            /*token_rejected=*/true};
  }
  // Timeouts and rate limits are the collector's state, not the tile's.
  if (response.result() == http::Status::request_timeout || response.result() == http::Status::too_many_requests ||
      status >= 500) {
    return {SubmitVerdict::kRetry, describe_answer(response)};
  }
  if (status >= 400) return {SubmitVerdict::kRejected, describe_answer(response)};
  return {SubmitVerdict::kRetry, fmt::format("unexpected answer: {}", describe_answer(response))};
}

bool GoneAnswers::refusal(std::uint64_t job, bool marked) {
  if (jobs_.contains(job)) return !marked;
  jobs_.insert(job);
  order_.push_back(job);
  if (order_.size() > kRememberedGoneJobs) {
    jobs_.erase(order_.front());
    order_.pop_front();
  }
  return false;
}

}  // namespace dtraced::worker
