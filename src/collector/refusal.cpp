#include "collector/refusal.h"

#include <utility>

#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "protocol/messages.h"

namespace dtraced::collector {

namespace bhttp = boost::beast::http;

Refusal bad_request(std::string message, std::string field) {
  return Refusal{http::Status::bad_request, util::Error(std::move(message), std::move(field)), {}};
}

Refusal busy(std::string message) {
  return Refusal{http::Status::service_unavailable, util::Error(std::move(message)), {}};
}

Refusal job_not_found(std::uint64_t id) {
  return Refusal{http::Status::not_found, util::Error(fmt::format("no such job: {}", id)), {}};
}

Refusal decode_failure(const util::Errors& errors) {
  protocol::ErrorBody body = protocol::error_body(errors);
  return bad_request(std::move(body.error), std::move(body.field));
}

http::Response respond(const Refusal& refusal) {
  http::Response res = http::make_error(refusal.status, refusal.error.message, refusal.error.path);
  if (!refusal.allow.empty()) res.set(bhttp::field::allow, refusal.allow);
  if (refusal.status == http::Status::unauthorized) res.set(bhttp::field::www_authenticate, "Bearer");
  if (refusal.status == http::Status::service_unavailable) res.set(bhttp::field::retry_after, kBusyRetryAfterSeconds);
  return res;
}

}  // namespace dtraced::collector
