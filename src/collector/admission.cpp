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

const CredentialTable& no_credentials() {
  static const CredentialTable kEmpty;
  return kEmpty;
}

// The role check of an admitted route.
util::Result<Admitted, Refusal> with_role(Admitted admitted, std::optional<Role>* refused_role) {
  if (admitted.who && !route_is_public(admitted.route.kind) && !route_allows(admitted.route.kind, admitted.who->role)) {
    if (refused_role != nullptr) *refused_role = admitted.who->role;
    return role_refusal(admitted.who->role, admitted.route.kind);
  }
  return admitted;
}

// The page's targets, once they are known to be served.
util::Result<Admitted, Refusal> admit_page(const http::Request& head, std::string_view target, std::uint64_t max_body,
                                           const PageAccess& page, const CredentialTable& table,
                                           std::optional<Role>* refused_role) {
  const bool changes_state = head.method() != http::Verb::get && head.method() != http::Verb::head;
  const std::string cookie = session_cookie(head);
  std::optional<Principal> who;
  if (is_page_api_path(target_path(target))) {
    // The session before the route, as the token comes before it on /v1: nothing about the
    // API's paths is told to a caller without one.
    if (head.find(boost::beast::http::field::authorization) != head.end()) {
      return unauthorized("the page's API takes the session cookie, not a bearer token (use /v1 with the token)");
    }
    const auto live = cookie.empty() ? std::nullopt : page.sessions->find(cookie, page.now);
    if (!live) return unauthorized("not signed in, or the session expired: sign in again");
    who = live->who;
    if (who->role != Role::kOperator) {
      const Credential* c = table.find_name(who->name);
      if (c == nullptr || c->revoked()) return unauthorized("this credential was revoked");
    }
  }
  auto matched = match_route(head.method(), target);
  if (!matched) return std::move(matched).error();
  Route route = std::move(matched).value();
  if (changes_state) {
    if (auto same = check_same_origin(head, page.scheme); !same) return std::move(same).error();
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
  return with_role(Admitted{std::move(route), limit, std::move(who)}, refused_role);
}

}  // namespace

Refusal role_refusal(Role role, RouteKind kind) {
  return Refusal{
      http::Status::forbidden,
      util::Error(fmt::format("this credential (role {}) may not use {}", role_name(role), route_label(kind))),
      {}};
}

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token,
                                      std::uint64_t max_body_bytes) {
  return admit(head, token, max_body_bytes, PageAccess{});
}

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, std::uint64_t max_body_bytes,
                                      const PageAccess& page) {
  return admit(head, token, no_credentials(), max_body_bytes, page);
}

util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, const CredentialTable& table,
                                      std::uint64_t max_body_bytes, const PageAccess& page,
                                      std::optional<Role>* refused_role) {
  const std::string_view target(head.target().data(), head.target().size());
  if (is_page_path(target_path(target))) {
    if (!page.enabled) return Refusal{http::Status::not_found, util::Error("no such endpoint"), {}};
    return admit_page(head, target, max_body_bytes, page, table, refused_role);
  }
  if (is_health_check(head.method(), target)) {
    Admitted health;
    health.route.kind = RouteKind::kHealthz;
    health.body_limit = std::numeric_limits<std::uint64_t>::max();
    return health;
  }
  if (is_public_path(target)) {
    // No token asked for, none looked at: enrollment is how a worker gets one.
    auto matched = match_route(head.method(), target);
    if (!matched) return std::move(matched).error();
    const std::uint64_t limit = std::min(route_body_limit(matched->kind), max_body_bytes);
    return Admitted{std::move(matched).value(), limit, std::nullopt};
  }
  const Authentication auth = authenticate(head, token, table);
  if (auth.kind == Authentication::Kind::kNone) {
    return Refusal{http::Status::unauthorized, util::Error("missing or wrong bearer token"), {}};
  }
  if (auth.kind == Authentication::Kind::kRevoked) {
    return Refusal{http::Status::unauthorized, util::Error("this credential was revoked"), {}};
  }
  auto matched = match_route(head.method(), target);
  if (!matched) return std::move(matched).error();
  const std::uint64_t limit = std::min(route_body_limit(matched->kind), max_body_bytes);
  return with_role(Admitted{std::move(matched).value(), limit, auth.who}, refused_role);
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
