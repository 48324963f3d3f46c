#include "collector/admission.h"

#include <algorithm>
#include <limits>
#include <string_view>
#include <utility>

#include <fmt/format.h>

namespace dtraced::collector {

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token,
                                      std::uint64_t max_body_bytes) {
  const std::string_view target(head.target().data(), head.target().size());
  if (is_health_check(head.method(), target)) {
    Admitted health;
    health.route.kind = RouteKind::kHealthz;
    health.body_limit = std::numeric_limits<std::uint64_t>::max();
    return health;
  }
  if (!token.accepts(head)) {
    return Refusal{http::Status::unauthorized, util::Error("missing or wrong bearer token"), {}};
  }
  auto matched = match_route(head.method(), target);
  if (!matched) return std::move(matched).error();
  const std::uint64_t limit = std::min(route_body_limit(matched->kind), max_body_bytes);
  return Admitted{std::move(matched).value(), limit};
}

util::Result<void, Refusal> check_body_size(std::uint64_t body_bytes, std::uint64_t body_limit) {
  if (body_bytes <= body_limit) return {};
  return Refusal{http::Status::payload_too_large,
                 util::Error(fmt::format("request body of {} bytes exceeds this endpoint's limit of {} bytes",
                                         body_bytes, body_limit)),
                 {}};
}

bool LogThrottle::allow(TimePoint now, std::uint64_t& held_back) {
  if (last_ && now - *last_ < interval_) {
    ++held_;
    return false;
  }
  last_ = now;
  held_back = held_;
  held_ = 0;
  return true;
}

}  // namespace dtraced::collector
