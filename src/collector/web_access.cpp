#include "collector/web_access.h"

#include <array>

#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "jsonio/reader.h"
#include "protocol/messages.h"

namespace dtraced::collector {
namespace {

namespace bhttp = boost::beast::http;

std::string_view header(const http::Request& req, std::string_view name) {
  const auto it = req.find(boost::beast::string_view(name.data(), name.size()));
  if (it == req.end()) return {};
  return {it->value().data(), it->value().size()};
}

Refusal forbidden(std::string message) { return Refusal{http::Status::forbidden, util::Error(std::move(message)), {}}; }

// Decodes a small JSON object of the page: the body under kMaxPageBodyBytes, its keys among
// `keys`, read by `read`; a 400 naming the first bad field.
template <typename T, typename Read>
util::Result<T, Refusal> decode_page_object(std::string_view text, std::span<const std::string_view> keys, Read read) {
  jsonio::Reader r({}, protocol::kMaxDecodeErrors);
  const std::optional<boost::json::value> body = r.parse(text, "body", kMaxPageBodyBytes, 4);
  const jsonio::Path root;
  const boost::json::object* o = body ? r.object(*body, root) : nullptr;
  T message{};
  if (o != nullptr) {
    jsonio::Fields f(r, *o, root, keys);
    read(f, message);
  }
  if (r.failed()) return decode_failure(r.take_errors());
  return message;
}

}  // namespace

std::string_view scheme_name(PageScheme scheme) { return scheme == PageScheme::kHttps ? "https" : "http"; }

bool is_page_path(std::string_view path) { return path == "/" || path == "/ui" || path.starts_with("/ui/"); }

bool is_page_api_path(std::string_view path) { return path.starts_with("/ui/api/") || path == "/ui/api"; }

std::string session_cookie(const http::Request& req) {
  // Cookie: a=1; dtraced_session=HEX; b=2 (RFC 6265 section 4.2.1: pairs separated by "; ").
  const auto [from, to] = req.equal_range(bhttp::field::cookie);
  for (auto field = from; field != to; ++field) {
    std::string_view rest(field->value().data(), field->value().size());
    while (!rest.empty()) {
      const std::size_t semi = rest.find(';');
      std::string_view pair = rest.substr(0, semi);
      rest = semi == std::string_view::npos ? std::string_view() : rest.substr(semi + 1);
      while (!pair.empty() && pair.front() == ' ') pair.remove_prefix(1);
      const std::size_t eq = pair.find('=');
      if (eq != std::string_view::npos && pair.substr(0, eq) == kSessionCookie) {
        std::string_view value = pair.substr(eq + 1);
        while (!value.empty() && value.back() == ' ') value.remove_suffix(1);
        return std::string(value.substr(0, 128));
      }
    }
  }
  return {};
}

std::string session_set_cookie(std::string_view id, std::int64_t max_age_s, PageScheme scheme) {
  return fmt::format("{}={}; Path=/ui; HttpOnly; SameSite=Strict; Max-Age={}{}", kSessionCookie, id, max_age_s,
                     scheme == PageScheme::kHttps ? "; Secure" : "");
}

std::string session_clear_cookie(PageScheme scheme) {
  return fmt::format("{}=; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=0{}", kSessionCookie,
                     scheme == PageScheme::kHttps ? "; Secure" : "");
}

util::Result<void, Refusal> check_same_origin(const http::Request& req, PageScheme scheme) {
  if (req.find(bhttp::field::origin) != req.end()) {
    const std::string_view origin = header(req, "Origin");
    const std::string_view host = header(req, "Host");
    if (host.empty() || origin != fmt::format("{}://{}", scheme_name(scheme), host)) {
      return forbidden("cross-origin request refused: Origin is not this collector's");
    }
  }
  if (req.find("Sec-Fetch-Site") != req.end()) {
    const std::string_view site = header(req, "Sec-Fetch-Site");
    if (site != "same-origin" && site != "none") return forbidden("cross-site request refused (Sec-Fetch-Site)");
  }
  return {};
}

void add_page_headers(http::Response& res, bool no_store) {
  res.set("Content-Security-Policy",
          boost::beast::string_view(kPageContentSecurityPolicy.data(), kPageContentSecurityPolicy.size()));
  res.set("X-Content-Type-Options", "nosniff");
  res.set(bhttp::field::x_frame_options, "DENY");
  res.set("Referrer-Policy", "no-referrer");
  if (no_store) res.set(bhttp::field::cache_control, "no-store");
}

util::Result<std::string, Refusal> decode_sign_in(std::string_view body) {
  static constexpr std::array<std::string_view, 1> kKeys{"token"};
  struct SignIn {
    std::string token;
  };
  auto decoded =
      decode_page_object<SignIn>(body, kKeys, [](jsonio::Fields& f, SignIn& m) { f.string("token", m.token, 4096); });
  if (!decoded) return std::move(decoded).error();
  return std::move(decoded->token);
}

util::Result<FocusRect, Refusal> decode_focus(std::string_view body) {
  static constexpr std::array<std::string_view, 4> kKeys{"x", "y", "width", "height"};
  constexpr std::int64_t kMax = 1 << 20;
  return decode_page_object<FocusRect>(body, kKeys, [](jsonio::Fields& f, FocusRect& m) {
    f.integer("x", m.x, 0, kMax);
    f.integer("y", m.y, 0, kMax);
    f.integer("width", m.width, 1, kMax);
    f.integer("height", m.height, 1, kMax);
  });
}

}  // namespace dtraced::collector
