#include "cli/retry.h"

#include <algorithm>
#include <charconv>
#include <string_view>
#include <system_error>

#include <fmt/format.h>

#include "protocol/messages.h"
#include "worker/backoff.h"

namespace dtraced::cli {

std::optional<std::chrono::milliseconds> parse_retry_after(std::string_view field) {
  // RFC 9110: delay-seconds = 1*DIGIT. Past a day it is not a wait a person would sit through.
  constexpr std::uint32_t kMaxSeconds = 86'400;
  std::uint32_t seconds = 0;
  const auto [end, ec] = std::from_chars(field.data(), field.data() + field.size(), seconds);
  if (field.empty() || ec != std::errc() || end != field.data() + field.size() || seconds > kMaxSeconds) {
    return std::nullopt;
  }
  return std::chrono::seconds(seconds);
}

Failure classify(const http::ClientResult& result, http::Verb verb, const std::string& target) {
  Failure f;
  if (!result.ok()) {
    const bool no_answer = result.error == http::ClientError::kConnect || result.error == http::ClientError::kIo ||
                           result.error == http::ClientError::kTimeout;
    f.retryable = no_answer && verb == http::Verb::get;
    // A refused certificate is an answer, and a final one: it says who the collector is not.
    f.reason = result.error == http::ClientError::kTls
                   ? fmt::format("the collector could not be trusted ({})", result.message)
                   : fmt::format("no answer from the collector ({})", result.message);
    return f;
  }
  const unsigned code = result.response.result_int();
  std::string what = fmt::format("HTTP {}", code);
  if (const auto err = protocol::decode_error_body(result.response.body()); err.ok()) {
    const protocol::ErrorBody& e = err.value();
    what = e.field.empty() ? e.error : fmt::format("{}: {}", e.field, e.error);
  }
  if (code == 503) {
    f.retryable = true;
    f.retry_after = parse_retry_after(result.response[boost::beast::http::field::retry_after]);
    f.reason = fmt::format("collector busy (503 {}: {})", target, what);
  } else {
    f.reason = fmt::format("{} {}: {}", code, target, what);
  }
  return f;
}

RetryPolicy::Ms RetryPolicy::spent(util::TimePoint now) const {
  if (failures_ == 0) return Ms{0};
  return std::chrono::duration_cast<Ms>(now - run_start_);
}

std::optional<RetryPolicy::Ms> RetryPolicy::next_wait(const Failure& failure, util::TimePoint now) {
  if (failures_ == 0) run_start_ = now;
  const Ms used = spent(now);
  const std::uint32_t before = failures_++;
  if (!failure.retryable || used >= budget_) return std::nullopt;
  const worker::Backoff backoff(kInitial, kMax);
  Ms wait = std::max(backoff.delay(before, rng_), kMinWait);
  if (failure.retry_after) wait = std::max(wait, worker::jittered_retry_after(*failure.retry_after, rng_));
  return std::min(wait, budget_ - used);
}

}  // namespace dtraced::cli
