#include "collector/routes.h"

#include <charconv>
#include <optional>
#include <utility>
#include <vector>

#include <boost/beast/core/string.hpp>
#include <boost/beast/http/field.hpp>
#include <fmt/format.h>
#include <openssl/crypto.h>

#include "collector/credentials.h"
#include "collector/web_access.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "web/assets.h"

namespace dtraced::collector {
namespace {

// Paths have at most five segments ("v1", "jobs", id, "tiles", tile); anything longer is 404
// without looking further.
constexpr std::size_t kMaxSegments = 6;

Refusal not_found() { return Refusal{http::Status::not_found, util::Error("no such endpoint"), {}}; }

Refusal wrong_method(std::string_view allow) {
  return Refusal{http::Status::method_not_allowed, util::Error(fmt::format("method not allowed here; use {}", allow)),
                 std::string(allow)};
}

// Decimal digits without sign or leading zeros, at most `max`.
std::optional<std::uint64_t> parse_decimal(std::string_view s, std::uint64_t max) {
  if (s.empty() || (s.size() > 1 && s[0] == '0')) return std::nullopt;
  std::uint64_t v = 0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (ec != std::errc() || end != s.data() + s.size() || v > max) return std::nullopt;
  return v;
}

std::optional<JobId> parse_job_id(std::string_view s) {
  auto v = parse_decimal(s, protocol::kMaxId);
  if (!v || *v == 0) return std::nullopt;
  return *v;
}

// Splits "/a/b/c" into {"a", "b", "c"}; nullopt past kMaxSegments.
std::optional<std::vector<std::string_view>> split_path(std::string_view path) {
  std::vector<std::string_view> segments;
  std::size_t pos = 1;  // past the leading '/'
  while (true) {
    if (segments.size() == kMaxSegments) return std::nullopt;
    const std::size_t next = path.find('/', pos);
    segments.push_back(path.substr(pos, next == std::string_view::npos ? std::string_view::npos : next - pos));
    if (next == std::string_view::npos) break;
    pos = next + 1;
  }
  return segments;
}

// "a=1&b=2" as (key, value) pairs in order; empty items skipped, a missing '=' an empty value.
// Bounded by the request line, which the header limit bounds.
std::vector<std::pair<std::string_view, std::string_view>> query_items(std::string_view query) {
  std::vector<std::pair<std::string_view, std::string_view>> items;
  while (!query.empty()) {
    const std::size_t amp = query.find('&');
    const std::string_view item = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view() : query.substr(amp + 1);
    if (item.empty()) continue;
    const std::size_t eq = item.find('=');
    items.emplace_back(item.substr(0, eq), eq == std::string_view::npos ? std::string_view() : item.substr(eq + 1));
  }
  return items;
}

// The image route's query: format=NAME (image::format_from_name) and frame=N (a frame number),
// each at most once.
util::Result<void, Refusal> parse_image_query(std::string_view query, Route& route) {
  bool format_seen = false, frame_seen = false;
  for (const auto& [key, value] : query_items(query)) {
    if (key == "format") {
      if (format_seen) return bad_request("format given twice", "/format");
      format_seen = true;
      const std::optional<image::ImageFormat> named = image::format_from_name(value);
      if (!named) return bad_request(fmt::format("format must be {}", image::name_list()), "/format");
      route.image_format = *named;
    } else if (key == "frame") {
      if (frame_seen) return bad_request("frame given twice", "/frame");
      frame_seen = true;
      std::uint32_t frame = 0;
      const auto [end, ec] = std::from_chars(value.data(), value.data() + value.size(), frame);
      if (ec != std::errc() || end != value.data() + value.size() || value.empty() ||
          (value.size() > 1 && value.front() == '0')) {
        return bad_request("frame must be a frame number (decimal, 0 to 4294967295)", "/frame");
      }
      route.image_frame = frame;
    } else {
      return bad_request(
          fmt::format("unknown query parameter '{}' (this endpoint takes format and frame)", key.substr(0, 64)),
          "/format");
    }
  }
  return {};
}

// GET /v1/jobs: state=NAME (protocol::job_state_from_string) and limit=N, each at most once.
util::Status parse_list_query(std::string_view query, Route& route) {
  bool seen_state = false;
  bool seen_limit = false;
  for (const auto& [key, value] : query_items(query)) {
    if (key == "state") {
      if (seen_state) return util::Error("state given twice", "/state");
      seen_state = true;
      route.list_state = protocol::job_state_from_string(value);
      if (!route.list_state) return util::Error("state must be queued, rendering, paused, done or cancelled", "/state");
    } else if (key == "limit") {
      if (seen_limit) return util::Error("limit given twice", "/limit");
      seen_limit = true;
      const auto limit = parse_decimal(value, protocol::kMaxListedJobs);
      if (!limit || *limit == 0) {
        return util::Error(fmt::format("limit must be a whole number from 1 to {}", protocol::kMaxListedJobs),
                           "/limit");
      }
      route.list_limit = static_cast<std::size_t>(*limit);
    } else {
      return util::Error(
          fmt::format("unknown query parameter '{}' (this endpoint takes state and limit)", key.substr(0, 64)),
          fmt::format("/{}", key.substr(0, 64)));
    }
  }
  return {};
}

// DELETE /v1/jobs/{id}: image=keep (the default) or image=delete, at most once.
util::Status parse_delete_query(std::string_view query, Route& route) {
  bool seen = false;
  for (const auto& [key, value] : query_items(query)) {
    if (key != "image") {
      return util::Error(fmt::format("unknown query parameter '{}' (this endpoint takes image)", key.substr(0, 64)),
                         fmt::format("/{}", key.substr(0, 64)));
    }
    if (seen) return util::Error("image given twice", "/image");
    seen = true;
    if (value != "keep" && value != "delete") return util::Error("image must be keep or delete", "/image");
    route.delete_image = value == "delete";
  }
  return {};
}

// GET /ui/api/jobs/{id}/tiles: since=SEQ and frame=N, each at most once.
util::Result<void, Refusal> parse_tiles_query(std::string_view query, Route& route) {
  bool since_seen = false, frame_seen = false;
  for (const auto& [key, value] : query_items(query)) {
    if (key == "since") {
      if (since_seen) return bad_request("since given twice", "/since");
      since_seen = true;
      const auto since = parse_decimal(value, std::uint64_t{1} << 53);
      if (!since && value != "0") return bad_request("since must be a sequence number (decimal, from 0)", "/since");
      route.since = since.value_or(0);
    } else if (key == "frame") {
      if (frame_seen) return bad_request("frame given twice", "/frame");
      frame_seen = true;
      const auto frame = parse_decimal(value, 0xffffffffu);
      if (!frame && value != "0") {
        return bad_request("frame must be a frame number (decimal, 0 to 4294967295)", "/frame");
      }
      route.image_frame = static_cast<std::uint32_t>(frame.value_or(0));
    } else {
      return bad_request(
          fmt::format("unknown query parameter '{}' (this endpoint takes since and frame)", key.substr(0, 64)),
          fmt::format("/{}", key.substr(0, 64)));
    }
  }
  return {};
}

// "/", "/ui/<file>", "/ui/session" and "/ui/api/...".
util::Result<Route, Refusal> match_page_route(http::Verb method, std::string_view path, std::string_view query) {
  Route route;
  const auto only = [&](http::Verb verb, std::string_view allow) -> util::Result<void, Refusal> {
    if (method != verb) return wrong_method(allow);
    return {};
  };
  if (is_page_api_path(path)) {
    // The /v1 route of the same name, if the page may call it; and the page's own two.
    const std::string_view rest = path.substr(std::string_view("/ui/api").size());
    auto split = split_path(rest.empty() ? std::string_view("/") : rest);
    if (split && split->size() == 3 && (*split)[0] == "jobs" && ((*split)[2] == "tiles" || (*split)[2] == "focus")) {
      const auto id = parse_job_id((*split)[1]);
      if (!id) return not_found();
      route.job = *id;
      route.page = true;
      if ((*split)[2] == "tiles") {
        if (auto ok = only(http::Verb::get, "GET"); !ok) return std::move(ok).error();
        route.kind = RouteKind::kJobTiles;
        if (auto parsed = parse_tiles_query(query, route); !parsed) return std::move(parsed).error();
      } else {
        if (auto ok = only(http::Verb::post, "POST"); !ok) return std::move(ok).error();
        route.kind = RouteKind::kJobFocus;
        if (!query.empty()) return bad_request("this endpoint takes no query parameters");
      }
      return route;
    }
    std::string v1 = fmt::format("/v1{}", rest);
    if (!query.empty()) v1 += fmt::format("?{}", query);
    auto matched = match_route(method, v1);
    if (matched && page_may_call(matched->kind)) {
      route = std::move(matched).value();
      route.page = true;
      return route;
    }
    if (!matched && matched.error().status != http::Status::method_not_allowed) return std::move(matched).error();
    // The methods the page may use on this path: none makes it a path the page does not have.
    std::string allow;
    for (const auto& [verb, name] : {std::pair{http::Verb::get, "GET"}, std::pair{http::Verb::post, "POST"}}) {
      auto other = match_route(verb, v1);
      if (other && page_may_call(other->kind)) allow += allow.empty() ? name : fmt::format(", {}", name);
    }
    if (allow.empty()) return not_found();
    return Refusal{http::Status::method_not_allowed, util::Error(fmt::format("method not allowed here; use {}", allow)),
                   allow};
  }
  if (path == "/ui/session") {
    if (method == http::Verb::post) {
      route.kind = RouteKind::kSessionCreate;
    } else if (method == http::Verb::get) {
      route.kind = RouteKind::kSessionGet;
    } else if (method == http::Verb::delete_) {
      route.kind = RouteKind::kSessionDelete;
    } else {
      return wrong_method("GET, POST, DELETE");
    }
    if (!query.empty()) return bad_request("this endpoint takes no query parameters");
    return route;
  }
  if (web::find_asset(path) == nullptr) return not_found();
  if (auto ok = only(http::Verb::get, "GET"); !ok) return std::move(ok).error();
  if (!query.empty()) return bad_request("this endpoint takes no query parameters");
  route.kind = RouteKind::kPageAsset;
  route.asset = std::string(path);
  return route;
}

}  // namespace

bool page_may_call(RouteKind kind) {
  switch (kind) {
    case RouteKind::kListJobs:
    case RouteKind::kJobStatus:
    case RouteKind::kJobImage:
    case RouteKind::kWorkers:
    case RouteKind::kCancelJob:
    case RouteKind::kPauseJob:
    case RouteKind::kResumeJob:
    case RouteKind::kRequeueJob:
    case RouteKind::kJobPriority:
    case RouteKind::kJobTiles:
    case RouteKind::kJobFocus:
      return true;
    default:
      return false;
  }
}

util::Result<Route, Refusal> match_route(http::Verb method, std::string_view target) {
  if (target.empty() || target[0] != '/') return bad_request("request target must be a path starting with '/'");
  const std::size_t qmark = target.find('?');
  const std::string_view path = target.substr(0, qmark);
  const std::string_view query = qmark == std::string_view::npos ? std::string_view() : target.substr(qmark + 1);
  if (is_page_path(path)) return match_page_route(method, path, query);
  auto split = split_path(path);
  if (!split) return not_found();
  const std::vector<std::string_view>& seg = *split;

  Route route;
  std::string_view allow;  // the one method this path takes
  const auto is = [&](std::initializer_list<std::string_view> expected) {
    if (seg.size() != expected.size()) return false;
    std::size_t i = 0;
    for (std::string_view e : expected) {
      if (!e.empty() && seg[i] != e) return false;  // "" matches any segment (a parameter)
      ++i;
    }
    return true;
  };

  if (is({"healthz"})) {
    route.kind = RouteKind::kHealthz;
    allow = "GET";
  } else if (is({"metrics"})) {
    route.kind = RouteKind::kMetrics;
    allow = "GET";
  } else if (is({"v1", "jobs"})) {
    if (method == http::Verb::post) {
      route.kind = RouteKind::kSubmitJob;
    } else if (method == http::Verb::get) {
      route.kind = RouteKind::kListJobs;
    } else {
      return wrong_method("GET, POST");
    }
    allow = method == http::Verb::post ? "POST" : "GET";
  } else if (is({"v1", "workers"})) {
    route.kind = RouteKind::kWorkers;
    allow = "GET";
  } else if (is({"v1", "ca"})) {
    route.kind = RouteKind::kCa;
    allow = "GET";
  } else if (is({"v1", "enroll"})) {
    route.kind = RouteKind::kEnroll;
    allow = "POST";
  } else if (is({"v1", "enroll-codes"})) {
    route.kind = RouteKind::kCreateEnrollCode;
    allow = "POST";
  } else if (is({"v1", "credentials"})) {
    if (method == http::Verb::post) {
      route.kind = RouteKind::kCreateCredential;
    } else if (method == http::Verb::get) {
      route.kind = RouteKind::kListCredentials;
    } else {
      return wrong_method("GET, POST");
    }
    allow = method == http::Verb::post ? "POST" : "GET";
  } else if (is({"v1", "credentials", "", "revoke"})) {
    if (!is_credential_name(seg[2])) return not_found();
    route.kind = RouteKind::kRevokeCredential;
    route.name = std::string(seg[2]);
    allow = "POST";
  } else if (is({"v1", "lease"})) {
    route.kind = RouteKind::kLease;
    allow = "POST";
  } else if (is({"v1", "scenes", ""})) {
    if (!protocol::is_digest(seg[2])) return not_found();
    route.kind = RouteKind::kScene;
    route.digest = std::string(seg[2]);
    allow = "GET";
  } else if (seg.size() >= 3 && seg[0] == "v1" && seg[1] == "jobs") {
    const auto id = parse_job_id(seg[2]);
    if (!id) return not_found();
    route.job = *id;
    if (is({"v1", "jobs", ""})) {
      if (method == http::Verb::delete_) {
        route.kind = RouteKind::kDeleteJob;
        allow = "DELETE";
      } else if (method == http::Verb::get) {
        route.kind = RouteKind::kJobStatus;
        allow = "GET";
      } else {
        return wrong_method("GET, DELETE");
      }
    } else if (is({"v1", "jobs", "", "image"})) {
      route.kind = RouteKind::kJobImage;
      allow = "GET";
    } else if (is({"v1", "jobs", "", "cancel"})) {
      route.kind = RouteKind::kCancelJob;
      allow = "POST";
    } else if (is({"v1", "jobs", "", "priority"})) {
      route.kind = RouteKind::kJobPriority;
      allow = "POST";
    } else if (is({"v1", "jobs", "", "requeue"})) {
      route.kind = RouteKind::kRequeueJob;
      allow = "POST";
    } else if (is({"v1", "jobs", "", "pause"})) {
      route.kind = RouteKind::kPauseJob;
      allow = "POST";
    } else if (is({"v1", "jobs", "", "resume"})) {
      route.kind = RouteKind::kResumeJob;
      allow = "POST";
    } else if (is({"v1", "jobs", "", "tiles", ""})) {
      const auto tile = parse_decimal(seg[4], protocol::kMaxTilesPerJob - 1);
      if (!tile) return not_found();
      route.kind = RouteKind::kPutTile;
      route.tile = static_cast<TileIndex>(*tile);
      allow = "PUT";
    } else {
      return not_found();
    }
  } else {
    return not_found();
  }

  const bool method_ok =
      (allow == "GET" && method == http::Verb::get) || (allow == "POST" && method == http::Verb::post) ||
      (allow == "PUT" && method == http::Verb::put) || (allow == "DELETE" && method == http::Verb::delete_);
  if (!method_ok) return wrong_method(allow);

  if (route.kind == RouteKind::kJobImage) {
    if (auto parsed = parse_image_query(query, route); !parsed) return std::move(parsed).error();
  } else if (route.kind == RouteKind::kListJobs) {
    if (util::Status parsed = parse_list_query(query, route); !parsed) {
      return bad_request(parsed.error().message, parsed.error().path);
    }
  } else if (route.kind == RouteKind::kDeleteJob) {
    if (util::Status parsed = parse_delete_query(query, route); !parsed) {
      return bad_request(parsed.error().message, parsed.error().path);
    }
  } else if (!query.empty() && route.kind != RouteKind::kHealthz) {
    return bad_request("this endpoint takes no query parameters");
  }
  return route;
}

std::uint64_t route_body_limit(RouteKind kind) {
  switch (kind) {
    case RouteKind::kPutTile:
      return protocol::kMaxTilePayloadBytes;
    case RouteKind::kSubmitJob:
      return protocol::kMaxJobSubmitBytes;
    default:
      return protocol::kMaxMessageBytes;
  }
}

std::uint64_t route_body_limit(const Route& route) {
  switch (route.kind) {
    case RouteKind::kPageAsset:
    case RouteKind::kSessionCreate:
    case RouteKind::kSessionGet:
    case RouteKind::kSessionDelete:
      return kMaxPageBodyBytes;
    default:
      return route.page ? kMaxPageBodyBytes : route_body_limit(route.kind);
  }
}

bool is_public_path(std::string_view target) {
  const std::string_view path = target.substr(0, target.find('?'));
  return path == "/healthz" || path == "/v1/ca" || path == "/v1/enroll";
}

bool is_health_check(http::Verb method, std::string_view target) {
  return method == http::Verb::get && target.substr(0, target.find('?')) == "/healthz";
}

TokenCheck::TokenCheck(std::string_view token) : expected_(util::sha256_bytes(token)) {}

bool TokenCheck::accepts(const http::Request& req) const {
  constexpr std::string_view kScheme = "bearer";
  const auto it = req.find(boost::beast::http::field::authorization);
  std::string_view presented;
  bool well_formed = false;
  if (it != req.end()) {
    const std::string_view value(it->value().data(), it->value().size());
    if (value.size() > kScheme.size() && boost::beast::iequals(value.substr(0, kScheme.size()), kScheme) &&
        value[kScheme.size()] == ' ') {
      presented = value.substr(kScheme.size() + 1);
      while (!presented.empty() && presented.front() == ' ') presented.remove_prefix(1);
      well_formed = !presented.empty();
    }
  }
  // Hash whatever was presented (even nothing), so a refusal costs the same either way.
  const util::Sha256Digest digest = util::sha256_bytes(presented);
  const bool equal = CRYPTO_memcmp(digest.data(), expected_.data(), digest.size()) == 0;
  return well_formed && equal;
}

bool TokenCheck::accepts_token(std::string_view presented) const {
  const bool equal = accepts_digest(util::sha256_bytes(presented));
  return !presented.empty() && equal;
}

bool TokenCheck::accepts_digest(const util::Sha256Digest& presented_sha256) const {
  return CRYPTO_memcmp(presented_sha256.data(), expected_.data(), presented_sha256.size()) == 0;
}

}  // namespace dtraced::collector
