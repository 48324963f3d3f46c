// dtraced::collector web access: the rules of the web page's routes (docs/web-access.md).
//
// Owns: which targets belong to the page (`/` and `/ui/...`), the session cookie's name and how
// it is read from a request and written into a response, the same-origin check of a request
// that changes state (Origin must be <scheme>://<Host>, http or https as the collector listens;
// Sec-Fetch-Site same-origin or none), the cookie's Secure attribute over HTTPS, the security headers of every page
// response, the page's body limit, and the decoders of the two bodies only the page sends (sign-in, focus). Pure
// functions of the request: testable without sockets.
//
// Thread safety: pure functions.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "collector/refusal.h"
#include "http/types.h"
#include "util/result.h"

namespace dtraced::collector {

inline constexpr std::string_view kSessionCookie = "dtraced_session";
inline constexpr std::string_view kCsrfHeader = "X-Dtraced-CSRF";
// Every body the page sends is small: a sign-in, a priority, a rectangle.
inline constexpr std::uint64_t kMaxPageBodyBytes = 4096;

inline constexpr std::string_view kPageContentSecurityPolicy =
    "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
    "frame-ancestors 'none'; base-uri 'none'; form-action 'self'";

// How the collector's listener speaks, which the page's origin and cookie follow: plain HTTP, or
// HTTPS (config.tls.enabled).
enum class PageScheme { kHttp, kHttps };
// "http" or "https".
std::string_view scheme_name(PageScheme scheme);
// The page's scheme for a collector that listens with TLS or not (config.tls.enabled).
inline PageScheme page_scheme(bool tls_enabled) { return tls_enabled ? PageScheme::kHttps : PageScheme::kHttp; }

// Whether a target's path (without its query) is the page's: "/", "/ui" or "/ui/...".
bool is_page_path(std::string_view path);
// Whether it is the page's API, which takes the session cookie only: "/ui/api/...".
bool is_page_api_path(std::string_view path);
// The path of a request target (before any '?').
inline std::string_view target_path(std::string_view target) { return target.substr(0, target.find('?')); }

// The value of the request's dtraced_session cookie, or "" when it has none.
std::string session_cookie(const http::Request& req);

// Set-Cookie for a new session of `max_age_s` seconds, and for signing out; over HTTPS with the
// Secure attribute (the browser then never sends the cookie over plain HTTP).
std::string session_set_cookie(std::string_view id, std::int64_t max_age_s, PageScheme scheme);
std::string session_clear_cookie(PageScheme scheme);

// 403 when the request carries an Origin that is not <scheme>://<its Host> (so over HTTPS an
// Origin of http://<Host> is refused, and over plain HTTP one of https://<Host>), or a
// Sec-Fetch-Site other than same-origin or none (a browser's cross-site request); fine without
// either header (a non-browser client, which has no ambient cookie to abuse).
util::Result<void, Refusal> check_same_origin(const http::Request& req, PageScheme scheme);

// The security headers of every page response (Content-Security-Policy, X-Content-Type-Options,
// X-Frame-Options, Referrer-Policy), and Cache-Control: no-store when `no_store` (the API's
// answers and errors; static files set their own).
void add_page_headers(http::Response& res, bool no_store);

// POST /ui/session's body: {"token": "..."}.
util::Result<std::string, Refusal> decode_sign_in(std::string_view body);

// POST /ui/api/jobs/{id}/focus's body: a rectangle in displayed coordinates.
struct FocusRect {
  std::int64_t x = 0, y = 0, width = 0, height = 0;
};
util::Result<FocusRect, Refusal> decode_focus(std::string_view body);

}  // namespace dtraced::collector
