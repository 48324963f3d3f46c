// dtraced::collector admission: whether a request may reach a handler, decided in one place.
//
// Owns: admit(), the one rule for a request's head (the health check, the CA and enrollment need
// no token; every other request needs a live credential's bearer token (401; a revoked one gets
// "this credential was revoked"), then a route, then a role that may call it (credentials.h,
// route_allows: 403); the route sets the body limit), which both the
// server's header check (before the body is read) and the handler (for requests that reach it
// by other paths, such as tests) apply; and the body check the handler adds once the body is in.
// Pure functions of the request, the token check and the credential table: tested without
// sockets.
//
// Also LogThrottle, which keeps a flood of refused requests from flooding the log.
//
// Thread safety: pure functions; a LogThrottle has one owner (the loop).
#pragma once

#include <chrono>
#include <cstdint>
#include <optional>

#include "collector/credentials.h"
#include "collector/refusal.h"
#include "collector/routes.h"
#include "collector/web_access.h"
#include "collector/web_session.h"
#include "http/types.h"
#include "util/result.h"

namespace dtraced::collector {

struct Admitted {
  Route route;
  // The largest body this request may carry: the route's limit under the configured cap, or
  // no limit of the collector's own for the health check (the server's limit still holds).
  std::uint64_t body_limit = 0;
  // Who sent it: the bearer token's credential, or the page session's; nullopt for the routes
  // that need none (route_is_public).
  std::optional<Principal> who;
};

// The health check (no token), else the token (401), else the route (404, 405, 400). The page's
// targets (web_access.h) are 404 here: this is admission without the web page. Only the operator
// token is known (no credentials).
util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, std::uint64_t max_body_bytes);

// What admission needs to know of the web page: whether it is served, its sessions, the time, and
// whether the collector listens with TLS (the Origin a state change must carry).
struct PageAccess {
  bool enabled = false;
  const SessionStore* sessions = nullptr;  // required when enabled
  TimePoint now{};
  PageScheme scheme = PageScheme::kHttp;
};

// As above, and the page's targets (docs/web-access.md): 404 unless enabled; static files need
// nothing; POST/DELETE /ui/session must be same-origin (403); /ui/api/... needs a live session
// cookie and no bearer header (401), then a route, and when it changes state, same origin (for
// page.scheme) and the session's CSRF header (403). A page route's body limit is kMaxPageBodyBytes.
util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, std::uint64_t max_body_bytes,
                                      const PageAccess& page);

// As above with the credentials of `table` too, and the role check (a page session has the role
// of the token that signed in, and is refused once that credential is revoked). When a role is
// refused (403), `refused_role` (if given) says which.
util::Result<Admitted, Refusal> admit(const http::Request& head, const TokenCheck& token, const CredentialTable& table,
                                      std::uint64_t max_body_bytes, const PageAccess& page,
                                      std::optional<Role>* refused_role = nullptr);

// The 403 of a role that may not call `kind`.
Refusal role_refusal(Role role, RouteKind kind);

// 413 when the body is over the admitted limit.
util::Result<void, Refusal> check_body_size(std::uint64_t body_bytes, std::uint64_t body_limit);

// Lets one log line through per interval and counts the ones it held back, so that a peer
// hammering the collector with bad tokens costs a line every few seconds, not one per request.
class LogThrottle {
 public:
  explicit LogThrottle(Duration interval = std::chrono::seconds(10)) : interval_(interval) {}
  // Whether to log the event at `now`; if so, `held_back` is how many were not logged since the
  // last line.
  bool allow(TimePoint now, std::uint64_t& held_back);

 private:
  Duration interval_;
  std::optional<TimePoint> last_;
  std::uint64_t held_ = 0;
};

}  // namespace dtraced::collector
