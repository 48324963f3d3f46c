#include "collector/admission.h"

#include <algorithm>
#include <limits>
#include <string_view>
#include <utility>

#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "collector/web_access.h"

namespace dtraced::collector {

namespace {

Refusal unauthorized(std::string message) {
  return Refusal{http::Status::unauthorized, util::Error(std::move(message)), {}};
}

// The page's targets, once they are known to be served.
util::Result<Admitted, Refusal> admit_page(const http::Request& head, std::string_view target, std::uint64_t max_body,
                                           const PageAccess& page) {
  const bool changes_state = head.method() != http::Verb::get && head.method() != http::Verb::head;
  const std::string cookie = session_cookie(head);
  if (is_page_api_path(target_path(target))) {
    // The session before the route, as the token comes before it on /v1: nothing about the
    // API's paths is told to a caller without one.
    if (head.find(boost::beast::http::field::authorization) != head.end()) {
      return unauthorized("the page's API takes the session cookie, not a bearer token (use /v1 with the token)");
    }
    if (cookie.empty() || !page.sessions->find(cookie, page.now)) {
      return unauthorized("not signed in, or the session expired: sign in again");
    }
  }
  auto matched = match_route(head.method(), target);
  if (!matched) return std::move(matched).error();
  Route route = std::move(matched).value();
  if (changes_state) {
    if (auto same = check_same_origin(head); !same) return std::move(same).error();
    // Signing in has no session yet; signing out of one that is gone needs no proof.
    const bool needs_csrf = route.page || (route.kind == RouteKind::kSessionDelete && !cookie.empty() &&
                                           page.sessions->find(cookie, page.now));
    if (needs_csrf) {
      const auto it = head.find(boost::beast::string_view(kCsrfHeader.data(), kCsrfHeader.size()));
      const std::string_view csrf =
          it == head.end() ? std::string_view() : std::string_view(it->value().data(), it->value().size());
      if (!page.sessions->csrf_matches(cookie, csrf, page.now)) {
        return Refusal{http::Status::forbidden,
                       util::Error(fmt::format("missing or wrong {} header (from GET /ui/session)", kCsrfHeader)),
                       {}};
      }
    }
  }
  const std::uint64_t limit = std::min(route_body_limit(route), max_body);
  return Admitted{std::move(route), limit};
}

}  // namespace

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token,
                                      std::uint64_t max_body_bytes) {
  return admit(head, token, max_body_bytes, PageAccess{});
}

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, std::uint64_t max_body_bytes,
                                      const PageAccess& page) {
  const std::string_view target(head.target().data(), head.target().size());
  if (is_page_path(target_path(target))) {
    if (!page.enabled) return Refusal{http::Status::not_found, util::Error("no such endpoint"), {}};
    return admit_page(head, target, max_body_bytes, page);
  }
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
