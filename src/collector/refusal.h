// dtraced::collector refusals: a request the collector will not serve, as a value.
//
// Owns: Refusal, the one verdict every check of the collector returns when it says no (routes.h,
// admission.h, checks.h), and respond(), the one place that turns it into an HTTP answer: the
// JSON error shape of http/types.h, plus the fields its status calls for (Allow on a 405,
// WWW-Authenticate on a 401, Retry-After on a 503). Checks stay pure functions that tests compare
// field by field; only handlers build responses.
//
// Thread safety: plain values and pure functions.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "http/types.h"
#include "util/result.h"

namespace dtraced::collector {

// Retry-After, in seconds, on every 503 (a busy, failing or stopping collector).
inline constexpr std::string_view kBusyRetryAfterSeconds = "1";

struct Refusal {
  http::Status status = http::Status::bad_request;
  // What is wrong; its path is the JSON Pointer of the offending field ("" for the request as a
  // whole), answered as the error body's "field".
  util::Error error;
  std::string allow;  // 405: the methods the path takes
  bool operator==(const Refusal&) const = default;
};

// 400 naming the field.
Refusal bad_request(std::string message, std::string field = {});
// 503: try again later.
Refusal busy(std::string message);
// 404 for an unknown job.
Refusal job_not_found(std::uint64_t id);
// 400 from a decoder's errors: the first one, with a count of the others (protocol::error_body).
Refusal decode_failure(const util::Errors& errors);

http::Response respond(const Refusal& refusal);

}  // namespace dtraced::collector
