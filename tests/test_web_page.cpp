// The collector's web page through its handler (collector_testing.h): route matching, sessions,
// the Origin and CSRF rules, security headers, the tile delta and the region focus.
#include <algorithm>
#include <array>
#include <cstdint>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <boost/json/parse.hpp>
#include <openssl/evp.h>

#include "collector/routes.h"
#include "collector/web_access.h"
#include "collector/web_session.h"
#include "collector_testing.h"
#include "page_testing.h"

namespace {

using namespace dtraced;
using namespace dtraced::testing;
using coll::RouteKind;
namespace bhttp = boost::beast::http;
namespace json = boost::json;

const coll::TimePoint t0 = coll::TimePoint{} + std::chrono::hours(1000);

void check_page_headers(const Response& res) {
  INFO("status " << res.result_int());
  CHECK(header_of(res, "Content-Security-Policy") == coll::kPageContentSecurityPolicy);
  CHECK(header_of(res, "X-Content-Type-Options") == "nosniff");
  CHECK(header_of(res, "X-Frame-Options") == "DENY");
  CHECK(header_of(res, "Referrer-Policy") == "no-referrer");
}

struct Session {
  std::string cookie, csrf;
};

// What GET /ui/session says of `cookie`: 200 either way, with signed_in, a csrf only when true.
bool signed_in(Harness& h, const std::string& cookie) {
  const Response res = h.collector.handle_sync(browser(Verb::get, "/ui/session", {}, cookie));
  REQUIRE(res.result() == Status::ok);
  check_page_headers(res);
  const json::object body = json::parse(res.body()).as_object();
  const bool in = body.at("signed_in").as_bool();
  CHECK(body.contains("csrf") == in);
  return in;
}

Session sign_in(Harness& h) {
  const Response res = h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})"));
  REQUIRE(res.result() == Status::ok);
  check_page_headers(res);
  CHECK(header_of(res, "Cache-Control") == "no-store");
  const std::string set = header_of(res, "Set-Cookie");
  REQUIRE(set.starts_with("dtraced_session="));
  CHECK(set.find("; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=43200") != std::string::npos);
  Session s;
  s.cookie = set.substr(16, 64);
  const json::value body = json::parse(res.body());
  s.csrf = std::string(body.at("csrf").as_string());
  CHECK(body.at("expires_in_s").as_int64() == 43200);
  CHECK(coll::is_session_secret(s.cookie));
  CHECK(coll::is_session_secret(s.csrf));
  return s;
}

std::string unbase64(std::string_view text) {
  std::string out(text.size() / 4 * 3 + 3, '\0');
  const int n = EVP_DecodeBlock(reinterpret_cast<unsigned char*>(out.data()),
                                reinterpret_cast<const unsigned char*>(text.data()), static_cast<int>(text.size()));
  REQUIRE(n >= 0);
  std::size_t pad = 0;
  while (pad < text.size() && text[text.size() - 1 - pad] == '=') ++pad;
  out.resize(static_cast<std::size_t>(n) - pad);
  return out;
}

image::ImageRGBf decode_png(std::string_view bytes) {
  auto img = image::decode_image(image::ImageFormat::kPng, bytes, "test");
  if (!img) FAIL(img.error().to_string());
  return std::move(img).value();
}

// Every tile of a delta, drawn from its atlas onto `canvas` as the page does.
void draw_delta(const json::value& delta, image::ImageRGBf& canvas) {
  const json::array& tiles = delta.at("tiles").as_array();
  if (tiles.empty()) return;
  const image::ImageRGBf atlas = decode_png(unbase64(delta.at("atlas").as_string()));
  for (const json::value& t : tiles) {
    const auto x = t.at("x").to_number<std::uint32_t>(), y = t.at("y").to_number<std::uint32_t>();
    const auto w = t.at("width").to_number<std::uint32_t>(), hgt = t.at("height").to_number<std::uint32_t>();
    const auto ax = t.at("ax").to_number<std::uint32_t>(), ay = t.at("ay").to_number<std::uint32_t>();
    for (std::uint32_t j = 0; j < hgt; ++j) {
      for (std::uint32_t i = 0; i < w; ++i) std::copy_n(atlas.pixel(ax + i, ay + j), 3, canvas.pixel(x + i, y + j));
    }
  }
}

json::value get_delta(Harness& h, const Session& s, std::uint64_t job, std::uint64_t since, Response* raw = nullptr) {
  Response res = h.collector.handle_sync(
      browser(Verb::get, fmt::format("/ui/api/jobs/{}/tiles?since={}", job, since), {}, s.cookie));
  REQUIRE(res.result() == Status::ok);
  check_page_headers(res);
  CHECK(header_of(res, "Cache-Control") == "no-store");
  json::value v = json::parse(res.body());
  if (raw != nullptr) *raw = std::move(res);
  return v;
}

std::vector<std::uint32_t> tile_ids(const json::value& delta) {
  std::vector<std::uint32_t> out;
  for (const json::value& t : delta.at("tiles").as_array()) out.push_back(t.at("tile").to_number<std::uint32_t>());
  return out;
}

}  // namespace

// ---- routes ------------------------------------------------------------------------------------

TEST_CASE("web routes: the page's paths, methods and queries", "[web][routes]") {
  using coll::match_route;
  const auto kind = [](Verb v, std::string_view t) {
    auto r = match_route(v, t);
    INFO(t);
    REQUIRE(r.ok());
    return r.value();
  };
  const auto status = [](Verb v, std::string_view t) {
    auto r = match_route(v, t);
    INFO(t);
    REQUIRE_FALSE(r.ok());
    return r.error().status;
  };
  CHECK(kind(Verb::get, "/").kind == RouteKind::kPageAsset);
  CHECK(kind(Verb::get, "/ui/app.js").asset == "/ui/app.js");
  CHECK(kind(Verb::get, "/ui/app.css").kind == RouteKind::kPageAsset);
  CHECK(kind(Verb::get, "/ui/favicon.svg").kind == RouteKind::kPageAsset);
  CHECK(kind(Verb::post, "/ui/session").kind == RouteKind::kSessionCreate);
  CHECK(kind(Verb::get, "/ui/session").kind == RouteKind::kSessionGet);
  CHECK(kind(Verb::delete_, "/ui/session").kind == RouteKind::kSessionDelete);
  const coll::Route tiles = kind(Verb::get, "/ui/api/jobs/7/tiles?since=345&frame=12");
  CHECK(tiles.kind == RouteKind::kJobTiles);
  CHECK(tiles.job == 7);
  CHECK(tiles.since == 345);
  CHECK(tiles.image_frame == 12u);
  CHECK(tiles.page);
  CHECK(kind(Verb::get, "/ui/api/jobs/7/tiles").since == 0);
  CHECK(kind(Verb::post, "/ui/api/jobs/7/focus").kind == RouteKind::kJobFocus);
  // The /v1 routes the page may call, marked as reached through it.
  const std::pair<Verb, std::string_view> mapped[] = {{Verb::get, "/ui/api/jobs?state=rendering&limit=5"},
                                                      {Verb::get, "/ui/api/jobs/3"},
                                                      {Verb::get, "/ui/api/jobs/3/image?frame=2"},
                                                      {Verb::get, "/ui/api/workers"},
                                                      {Verb::post, "/ui/api/jobs/3/cancel"},
                                                      {Verb::post, "/ui/api/jobs/3/pause"},
                                                      {Verb::post, "/ui/api/jobs/3/resume"},
                                                      {Verb::post, "/ui/api/jobs/3/requeue"},
                                                      {Verb::post, "/ui/api/jobs/3/priority"}};
  for (const auto& [v, t] : mapped) {
    const coll::Route r = kind(v, t);
    CHECK(r.page);
    CHECK(coll::page_may_call(r.kind));
    CHECK(coll::route_body_limit(r) == coll::kMaxPageBodyBytes);
  }
  CHECK(kind(Verb::get, "/ui/api/jobs?limit=5").list_limit == 5);
  // 404: no such file or route, and the routes the page may not call.
  for (const std::string_view t :
       {"/ui", "/ui/", "/ui/index.html", "/favicon.ico", "/ui/api", "/ui/api/lease", "/ui/api/jobs/3/tiles/2",
        "/ui/api/scenes/abc", "/ui/api/jobs/0/tiles", "/ui/api/jobs/x/focus"}) {
    CHECK(status(Verb::get, t) == Status::not_found);
  }
  CHECK(status(Verb::post, "/ui/api/lease") == Status::not_found);
  CHECK(status(Verb::put, "/ui/api/jobs/3/tiles/2") == Status::not_found);
  // 405 with the allowed methods.
  CHECK(status(Verb::post, "/") == Status::method_not_allowed);
  CHECK(status(Verb::put, "/ui/session") == Status::method_not_allowed);
  CHECK(status(Verb::get, "/ui/api/jobs/3/focus") == Status::method_not_allowed);
  CHECK(status(Verb::post, "/ui/api/jobs/3/tiles") == Status::method_not_allowed);
  CHECK(status(Verb::post, "/ui/api/jobs") == Status::method_not_allowed);  // no submission from the page
  CHECK(status(Verb::delete_, "/ui/api/jobs/3") == Status::method_not_allowed);
  // 400 naming the query parameter.
  for (const std::string_view t :
       {"/?x=1", "/ui/app.js?v=2", "/ui/session?a", "/ui/api/jobs/3/tiles?since=x", "/ui/api/jobs/3/tiles?since=01",
        "/ui/api/jobs/3/tiles?since=1&since=2", "/ui/api/jobs/3/tiles?frame=-1", "/ui/api/jobs/3/tiles?what=1",
        "/ui/api/jobs/3/focus?x=1"}) {
    CHECK(status(t.starts_with("/ui/api/jobs/3/focus") ? Verb::post : Verb::get, t) == Status::bad_request);
  }
  CHECK(match_route(Verb::get, "/ui/api/jobs/3/tiles?what=1").error().error.path == "/what");
  CHECK(coll::route_body_limit(kind(Verb::post, "/ui/session")) == coll::kMaxPageBodyBytes);
}

// ---- sessions ----------------------------------------------------------------------------------

TEST_CASE("web sessions: random ids, expiry, the cap and sign-out", "[web][sessions]") {
  coll::SessionStore store({.max_sessions = 3, .lifetime = std::chrono::hours(12)});
  const auto a = store.create(t0);
  REQUIRE(a);
  CHECK(coll::is_session_secret(a->id));
  CHECK(a->id != a->csrf);
  const auto live = store.find(a->id, t0 + std::chrono::hours(1));
  REQUIRE(live);
  CHECK(live->csrf == a->csrf);
  CHECK(live->remaining == std::chrono::hours(11));
  CHECK(store.csrf_matches(a->id, a->csrf, t0));
  CHECK_FALSE(store.csrf_matches(a->id, a->id, t0));
  CHECK_FALSE(store.csrf_matches(a->id, "", t0));
  CHECK_FALSE(store.find(a->csrf, t0));  // the CSRF token is no cookie
  CHECK_FALSE(store.find("not hex", t0));
  // Expiry, by the clock only.
  CHECK(store.find(a->id, t0 + std::chrono::hours(12) - std::chrono::seconds(1)));
  CHECK_FALSE(store.find(a->id, t0 + std::chrono::hours(12)));
  // The cap drops the oldest.
  const auto b = store.create(t0 + std::chrono::seconds(1));
  const auto c = store.create(t0 + std::chrono::seconds(2));
  const auto d = store.create(t0 + std::chrono::seconds(3));
  REQUIRE((b && c && d));
  CHECK(store.size() == 3);
  CHECK_FALSE(store.find(a->id, t0 + std::chrono::seconds(4)));
  CHECK(store.find(b->id, t0 + std::chrono::seconds(4)));
  CHECK(store.remove(b->id));
  CHECK_FALSE(store.remove(b->id));
  CHECK_FALSE(store.find(b->id, t0 + std::chrono::seconds(4)));
  CHECK(store.size() == 2);
  store.sweep(t0 + std::chrono::hours(13));
  CHECK(store.size() == 0);
}

TEST_CASE("web sign-in limiter: more than 10 failures a minute refuse sign-ins", "[web][sessions]") {
  coll::SignInLimiter limiter;
  for (int i = 0; i < 11; ++i) {
    REQUIRE(limiter.allows(t0 + std::chrono::seconds(i)));
    limiter.failed(t0 + std::chrono::seconds(i));
  }
  CHECK_FALSE(limiter.allows(t0 + std::chrono::seconds(20)));
  CHECK(limiter.retry_after(t0 + std::chrono::seconds(20)) == std::chrono::seconds(40));
  CHECK(limiter.allows(t0 + std::chrono::seconds(60)));  // the first failure left the window
}

TEST_CASE("web access: the cookie, its attributes and the same-origin rule", "[web][access]") {
  using coll::PageScheme;
  Request req = http::make_request(Verb::post, "/ui/session");
  req.set(bhttp::field::cookie, "a=b; dtraced_session=abc; c=d");
  CHECK(coll::session_cookie(req) == "abc");
  req.set(bhttp::field::cookie, "dtraced_sessionx=1");
  CHECK(coll::session_cookie(req).empty());
  // Neither header: not a browser's cross-site request, whatever the scheme.
  CHECK(coll::check_same_origin(req, PageScheme::kHttp).ok());
  CHECK(coll::check_same_origin(req, PageScheme::kHttps).ok());
  req.set(bhttp::field::host, "farm:7878");
  req.set(bhttp::field::origin, "http://farm:7878");
  CHECK(coll::check_same_origin(req, PageScheme::kHttp).ok());
  req.set(bhttp::field::origin, "http://evil.example");
  CHECK(coll::check_same_origin(req, PageScheme::kHttp).error().status == Status::forbidden);
  req.set(bhttp::field::origin, "null");
  CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttp).ok());
  req.erase(bhttp::field::origin);
  req.set("Sec-Fetch-Site", "cross-site");
  CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttp).ok());
  CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttps).ok());
  req.set("Sec-Fetch-Site", "same-site");
  CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttp).ok());
  req.set("Sec-Fetch-Site", "none");
  CHECK(coll::check_same_origin(req, PageScheme::kHttp).ok());
  CHECK(coll::session_clear_cookie(PageScheme::kHttp) ==
        "dtraced_session=; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=0");
  CHECK(coll::session_set_cookie("ab12", 60, PageScheme::kHttp) ==
        "dtraced_session=ab12; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=60");
}

TEST_CASE("web access: over HTTPS the Origin is https://<Host> and the cookie is Secure", "[web][access]") {
  using coll::PageScheme;
  CHECK(coll::scheme_name(PageScheme::kHttp) == "http");
  CHECK(coll::scheme_name(PageScheme::kHttps) == "https");
  CHECK(coll::page_scheme(true) == PageScheme::kHttps);
  CHECK(coll::page_scheme(false) == PageScheme::kHttp);
  Request req = http::make_request(Verb::post, "/ui/session");
  req.set(bhttp::field::host, "farm.example:7878");
  req.set("Sec-Fetch-Site", "same-origin");
  req.set(bhttp::field::origin, "https://farm.example:7878");
  CHECK(coll::check_same_origin(req, PageScheme::kHttps).ok());
  // The same page's origin over the other scheme is another origin.
  const auto https_on_plain = coll::check_same_origin(req, PageScheme::kHttp);
  REQUIRE_FALSE(https_on_plain.ok());
  CHECK(https_on_plain.error().status == Status::forbidden);
  req.set(bhttp::field::origin, "http://farm.example:7878");
  const auto http_on_tls = coll::check_same_origin(req, PageScheme::kHttps);
  REQUIRE_FALSE(http_on_tls.ok());
  CHECK(http_on_tls.error().status == Status::forbidden);
  for (const std::string_view other : {"https://evil.example", "https://farm.example", "https://farm.example:7879",
                                       "https://farm.example:7878/", "null"}) {
    INFO(other);
    req.set(bhttp::field::origin, other);
    CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttps).ok());
  }
  req.erase(bhttp::field::host);
  req.set(bhttp::field::origin, "https://");
  CHECK_FALSE(coll::check_same_origin(req, PageScheme::kHttps).ok());  // no Host: nothing to be the same as

  CHECK(coll::session_set_cookie("ab12", 60, PageScheme::kHttps) ==
        "dtraced_session=ab12; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=60; Secure");
  CHECK(coll::session_clear_cookie(PageScheme::kHttps) ==
        "dtraced_session=; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=0; Secure");
}

// ---- through the handler -----------------------------------------------------------------------

TEST_CASE("web page: static files with ETag, security headers, and --no-web-ui", "[web][page]") {
  TempDir dir;
  Harness h(dir);
  for (const std::string_view path : {"/", "/ui/app.js", "/ui/app.css", "/ui/favicon.svg"}) {
    INFO(path);
    const Response res = h.collector.handle_sync(browser(Verb::get, std::string(path)));
    REQUIRE(res.result() == Status::ok);
    check_page_headers(res);
    CHECK(header_of(res, "Cache-Control") == "no-cache");
    const std::string etag = header_of(res, "ETag");
    CHECK(etag.size() == 34);
    Request again = browser(Verb::get, std::string(path));
    again.set(bhttp::field::if_none_match, etag);
    const Response cached = h.collector.handle_sync(std::move(again));
    CHECK(cached.result() == Status::not_modified);
    CHECK(cached.body().empty());
    check_page_headers(cached);
  }
  CHECK(header_of(h.collector.handle_sync(browser(Verb::get, "/")), "Content-Type") == "text/html; charset=utf-8");
  // Errors of the page's paths carry the headers too.
  for (const auto& [verb, target, expected] : {std::tuple{Verb::get, "/ui/nothing", Status::not_found},
                                               std::tuple{Verb::post, "/", Status::method_not_allowed},
                                               std::tuple{Verb::get, "/ui/api/jobs", Status::unauthorized}}) {
    const Response res = h.collector.handle_sync(browser(verb, target));
    CHECK(res.result() == expected);
    check_page_headers(res);
    CHECK(header_of(res, "Cache-Control") == "no-store");
  }
  // The /v1 API is as it was: no page headers.
  CHECK(header_of(h.call(Verb::get, "/v1/jobs"), "Content-Security-Policy").empty());
  // A page request without a session is not a refused bearer token.
  CHECK(h.metrics().counters.auth_failures == 0);

  TempDir off_dir;
  coll::CollectorConfig off = make_config(off_dir);
  off.web_ui = false;
  Harness no_page(off);
  for (const std::string_view path : {"/", "/ui/app.js", "/ui/session", "/ui/api/jobs"}) {
    CHECK(no_page.collector.handle_sync(browser(Verb::get, std::string(path))).result() == Status::not_found);
  }
  CHECK(no_page.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})")).result() ==
        Status::not_found);
}

TEST_CASE("web page: sign-in, the session, credentials per route, CSRF and Origin", "[web][page]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();

  // Wrong token: 401, counted; no cookie.
  Response wrong = h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "guess"})"));
  CHECK(wrong.result() == Status::unauthorized);
  CHECK(header_of(wrong, "Set-Cookie").empty());
  check_page_headers(wrong);
  CHECK(h.metrics().counters.sign_in_failures == 1);
  CHECK(h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"tokn": "x"})")).result() ==
        Status::bad_request);
  CHECK(h.collector.handle_sync(browser(Verb::post, "/ui/session", std::string(5000, ' '))).result() ==
        Status::payload_too_large);

  CHECK(signed_in(h, "") == false);
  CHECK(signed_in(h, std::string(64, 'a')) == false);
  const Session s = sign_in(h);
  CHECK(signed_in(h, s.cookie));
  Response live = h.collector.handle_sync(browser(Verb::get, "/ui/session", {}, s.cookie));
  REQUIRE(live.result() == Status::ok);
  CHECK(json::parse(live.body()).at("csrf").as_string() == s.csrf);

  // Every /ui/api route without the cookie: 401.
  const std::pair<Verb, std::string> api[] = {{Verb::get, "/ui/api/jobs"},
                                              {Verb::get, fmt::format("/ui/api/jobs/{}", job)},
                                              {Verb::get, fmt::format("/ui/api/jobs/{}/image", job)},
                                              {Verb::get, "/ui/api/workers"},
                                              {Verb::get, fmt::format("/ui/api/jobs/{}/tiles?since=0", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/focus", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/cancel", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/pause", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/resume", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/requeue", job)},
                                              {Verb::post, fmt::format("/ui/api/jobs/{}/priority", job)},
                                              {Verb::get, "/ui/api/nowhere"}};
  for (const auto& [verb, target] : api) {
    INFO(target);
    const Response res = h.collector.handle_sync(browser(verb, target, "{}", {}, s.csrf));
    CHECK(res.result() == Status::unauthorized);
    check_page_headers(res);
  }
  // With it: the same answers as /v1.
  const Response listed = h.collector.handle_sync(browser(Verb::get, "/ui/api/jobs", {}, s.cookie));
  CHECK(listed.result() == Status::ok);
  CHECK(listed.body() == h.call(Verb::get, "/v1/jobs").body());
  CHECK(h.collector.handle_sync(browser(Verb::get, "/ui/api/workers", {}, s.cookie)).result() == Status::ok);
  CHECK(h.collector.handle_sync(browser(Verb::get, "/ui/api/nowhere", {}, s.cookie)).result() == Status::not_found);

  // A bearer header on /ui/api is refused, even beside a good cookie; a cookie on /v1 is ignored.
  Request bearer = browser(Verb::get, "/ui/api/jobs", {}, s.cookie);
  bearer.set(bhttp::field::authorization, "Bearer s3cret-token");
  CHECK(h.collector.handle_sync(std::move(bearer)).result() == Status::unauthorized);
  CHECK(h.collector.handle_sync(browser(Verb::get, "/v1/jobs", {}, s.cookie)).result() == Status::unauthorized);

  const std::string priority = fmt::format("/ui/api/jobs/{}/priority", job);
  // Missing or wrong CSRF header: 403.
  CHECK(h.collector.handle_sync(browser(Verb::post, priority, R"({"priority": 3})", s.cookie)).result() ==
        Status::forbidden);
  CHECK(h.collector.handle_sync(browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.cookie)).result() ==
        Status::forbidden);
  // Cross-origin: 403, whatever the CSRF header.
  Request cross = browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.csrf);
  cross.set(bhttp::field::origin, "http://evil.example");
  const Response refused = h.collector.handle_sync(std::move(cross));
  CHECK(refused.result() == Status::forbidden);
  check_page_headers(refused);
  Request site = browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.csrf);
  site.set("Sec-Fetch-Site", "cross-site");
  CHECK(h.collector.handle_sync(std::move(site)).result() == Status::forbidden);
  Request cross_sign_in = browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})");
  cross_sign_in.set(bhttp::field::origin, "http://evil.example");
  CHECK(h.collector.handle_sync(std::move(cross_sign_in)).result() == Status::forbidden);
  CHECK(h.status(job).priority == 0);
  // Right: the change is made.
  const Response changed =
      h.collector.handle_sync(browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.csrf));
  CHECK(changed.result() == Status::ok);
  CHECK(header_of(changed, "Cache-Control") == "no-store");
  CHECK(h.status(job).priority == 3);
  CHECK(h.collector.handle_sync(browser(Verb::post, fmt::format("/ui/api/jobs/{}/cancel", job), {}, s.cookie, s.csrf))
            .result() == Status::ok);
  CHECK(h.status(job).state == protocol::JobState::kCancelled);

  // Expiry on the collector's clock.
  h.clock.advance(std::chrono::hours(12));
  CHECK(signed_in(h, s.cookie) == false);
  CHECK(h.collector.handle_sync(browser(Verb::get, "/ui/api/jobs", {}, s.cookie)).result() == Status::unauthorized);

  // Sign out: 204, the cookie cleared, the session gone.
  const Session t = sign_in(h);
  const Response out = h.collector.handle_sync(browser(Verb::delete_, "/ui/session", {}, t.cookie, t.csrf));
  CHECK(out.result() == Status::no_content);
  CHECK(header_of(out, "Set-Cookie").find("Max-Age=0") != std::string::npos);
  check_page_headers(out);
  CHECK(signed_in(h, t.cookie) == false);
}

TEST_CASE("web page: a collector with TLS wants https:// origins and sets a Secure cookie", "[web][page]") {
  // The handler never touches certificates: config.tls.enabled only tells it how it is reached.
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.tls.enabled = true;
  Harness h(config);
  const std::uint64_t job = h.submit();
  const auto over_https = [](Request req) {
    if (req.find(bhttp::field::origin) != req.end()) req.set(bhttp::field::origin, "https://127.0.0.1:7878");
    return req;
  };

  // Sign-in from the http:// origin of the same host and port: another origin, 403, no cookie.
  const Response plain = h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})"));
  CHECK(plain.result() == Status::forbidden);
  CHECK(header_of(plain, "Set-Cookie").empty());
  check_page_headers(plain);

  const Response in =
      h.collector.handle_sync(over_https(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})")));
  REQUIRE(in.result() == Status::ok);
  const std::string set = header_of(in, "Set-Cookie");
  REQUIRE(set.starts_with("dtraced_session="));
  CHECK(set.ends_with("; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=43200; Secure"));
  Session s;
  s.cookie = set.substr(16, 64);
  s.csrf = std::string(json::parse(in.body()).at("csrf").as_string());
  CHECK(signed_in(h, s.cookie));

  // A state change from http:// is refused and changes nothing; from https:// it is made.
  const std::string priority = fmt::format("/ui/api/jobs/{}/priority", job);
  CHECK(h.collector.handle_sync(browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.csrf)).result() ==
        Status::forbidden);
  CHECK(h.status(job).priority == 0);
  CHECK(h.collector.handle_sync(over_https(browser(Verb::post, priority, R"({"priority": 3})", s.cookie, s.csrf)))
            .result() == Status::ok);
  CHECK(h.status(job).priority == 3);

  // Signing out clears the cookie with the same attributes.
  const Response out = h.collector.handle_sync(over_https(browser(Verb::delete_, "/ui/session", {}, s.cookie, s.csrf)));
  CHECK(out.result() == Status::no_content);
  CHECK(header_of(out, "Set-Cookie") == "dtraced_session=; Path=/ui; HttpOnly; SameSite=Strict; Max-Age=0; Secure");
  CHECK(signed_in(h, s.cookie) == false);
}

TEST_CASE("web page: without TLS an https:// origin is refused and the cookie is not Secure", "[web][page]") {
  TempDir dir;
  Harness h(dir);
  Request req = browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})");
  req.set(bhttp::field::origin, "https://127.0.0.1:7878");
  CHECK(h.collector.handle_sync(std::move(req)).result() == Status::forbidden);
  const Response in = h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})"));
  REQUIRE(in.result() == Status::ok);
  CHECK(header_of(in, "Set-Cookie").find("Secure") == std::string::npos);
}

TEST_CASE("web page: more than 10 failed sign-ins a minute get 429", "[web][page]") {
  TempDir dir;
  Harness h(dir);
  for (int i = 0; i < 11; ++i) {
    REQUIRE(h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "guess"})")).result() ==
            Status::unauthorized);
  }
  const Response limited = h.collector.handle_sync(browser(Verb::post, "/ui/session", R"({"token": "s3cret-token"})"));
  CHECK(limited.result() == Status::too_many_requests);
  CHECK_FALSE(header_of(limited, "Retry-After").empty());
  h.clock.advance(std::chrono::minutes(1));
  sign_in(h);
}

TEST_CASE("web page: the tile delta matches the job's PNG, with seq, ETag, leases and written", "[web][delta]") {
  TempDir dir;
  Harness h(dir);
  const Session s = sign_in(h);
  const std::uint64_t job = h.submit();
  std::vector<protocol::Lease> leases;
  for (int i = 0; i < 5; ++i) leases.push_back(*h.lease());
  for (int i = 0; i < 3; ++i) REQUIRE(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);

  Response raw;
  const json::value first = get_delta(h, s, job, 0, &raw);
  CHECK(first.at("job").as_int64() == static_cast<std::int64_t>(job));
  CHECK(first.at("width").as_int64() == 32);
  CHECK(first.at("height").as_int64() == 24);
  CHECK(first.at("tile_size").as_int64() == 8);
  CHECK(first.at("written").as_bool() == false);
  CHECK(first.at("more").as_bool() == false);
  CHECK(tile_ids(first) == std::vector<std::uint32_t>{leases[0].tile, leases[1].tile, leases[2].tile});
  CHECK(first.at("tiles").as_array()[0].at("worker").as_string() == "unknown");  // the harness sends no name
  const std::int64_t seq = first.at("seq").as_int64();
  // The two leases still out, with their worker.
  std::vector<std::uint32_t> leased;
  for (const json::value& l : first.at("leased").as_array()) {
    leased.push_back(l.at("tile").to_number<std::uint32_t>());
    CHECK(l.at("worker").as_string() == "test");
  }
  CHECK(leased == std::vector<std::uint32_t>{leases[3].tile, leases[4].tile});

  // Unchanged: 304 on the ETag, decided before any encoding.
  const std::string etag = header_of(raw, "ETag");
  Request again = browser(Verb::get, fmt::format("/ui/api/jobs/{}/tiles?since={}", job, 0), {}, s.cookie);
  again.set(bhttp::field::if_none_match, etag);
  const Response cached = h.collector.handle_sync(std::move(again));
  CHECK(cached.result() == Status::not_modified);
  check_page_headers(cached);

  // Newer tiles only.
  REQUIRE(h.put_ok(leases[3]) == protocol::SubmitResult::kStored);
  const json::value second = get_delta(h, s, job, static_cast<std::uint64_t>(seq));
  CHECK(tile_ids(second) == std::vector<std::uint32_t>{leases[3].tile});
  CHECK(second.at("seq").as_int64() == seq + 1);
  CHECK(second.at("leased").as_array().size() == 1);

  // Drawn onto a black canvas, the deltas give exactly the pixels of GET image's PNG.
  image::ImageRGBf canvas(32, 24);
  draw_delta(first, canvas);
  draw_delta(second, canvas);
  const image::ImageRGBf png = decode_png(h.call(Verb::get, fmt::format("/v1/jobs/{}/image", job)).body());
  CHECK(canvas.rgb == png.rgb);

  // Once the frame is written: written, no tiles.
  for (const auto& l : h.lease_all()) h.put_ok(l);
  for (int i = 4; i < 5; ++i) h.put_ok(leases[i]);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  const json::value done = get_delta(h, s, job, 0);
  CHECK(done.at("written").as_bool());
  CHECK(done.at("tiles").as_array().empty());
  CHECK_FALSE(done.as_object().contains("atlas"));
  CHECK(h.collector.handle_sync(browser(Verb::get, "/ui/api/jobs/99/tiles?since=0", {}, s.cookie)).result() ==
        Status::not_found);
  CHECK(h.collector.handle_sync(browser(Verb::get, fmt::format("/ui/api/jobs/{}/tiles?frame=5", job), {}, s.cookie))
            .result() == Status::not_found);
}

TEST_CASE("web page: a focus hands out the region's tiles next, nearest its centre first", "[web][focus]") {
  TempDir dir;
  Harness h(dir);
  const Session s = sign_in(h);
  const std::uint64_t job = h.submit();  // 32x24 in tiles of 8: 4 columns, 3 rows
  const std::string focus = fmt::format("/ui/api/jobs/{}/focus", job);
  // Bad bodies: 400 naming the field.
  const std::pair<std::string, std::string> bad[] = {{R"({"x": 1, "y": 1, "width": 0, "height": 1})", "/width"},
                                                     {R"({"x": -1, "y": 1, "width": 1, "height": 1})", "/x"},
                                                     {R"({"x": 1, "y": 1, "width": 1})", "/height"},
                                                     {R"({"x": 40, "y": 1, "width": 1, "height": 1})", "/x"},
                                                     {R"({"x": 1, "y": 24, "width": 1, "height": 1})", "/y"},
                                                     {R"({"x": 1, "y": 1, "width": 1, "height": 1, "z": 1})", "/z"}};
  for (const auto& [body, field] : bad) {
    INFO(body);
    const Response res = h.collector.handle_sync(browser(Verb::post, focus, body, s.cookie, s.csrf));
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).field == field);
  }
  // The bottom-right 2x2 tiles' region, centred in tile 11 (x 24..32, y 16..24).
  const Response res = h.collector.handle_sync(
      browser(Verb::post, focus, R"({"x": 20, "y": 14, "width": 40, "height": 40})", s.cookie, s.csrf));
  REQUIRE(res.result() == Status::ok);
  CHECK(json::parse(res.body()).at("tiles").as_int64() == 4);
  std::vector<std::uint32_t> order;
  for (int i = 0; i < 4; ++i) order.push_back(h.lease()->tile);
  // Clipped to (20,14)-(32,24), centre (26,19): the tiles by the distance of their centres.
  CHECK(order == std::vector<std::uint32_t>{11, 10, 7, 6});
  CHECK(h.lease()->tile == 0);  // then the old order
  // A click on a leased tile moves nothing.
  const Response click = h.collector.handle_sync(
      browser(Verb::post, focus, R"({"x": 30, "y": 20, "width": 1, "height": 1})", s.cookie, s.csrf));
  CHECK(json::parse(click.body()).at("tiles").as_int64() == 0);
  const coll::MetricsSnapshot m = h.metrics();
  CHECK(m.counters.focus_requests == 2);
  CHECK(m.counters.focus_tiles == 4);
}

TEST_CASE("web page: a focus changes the order of tiles, never the image", "[web][focus]") {
  // Two collectors render the same job from the same (fake, deterministic) tile pixels; one is
  // told to focus in the middle. Their written images are the same bytes.
  const auto render = [](bool focused) {
    TempDir dir;
    std::string bytes;
    {
      Harness h(dir);
      const std::uint64_t job = h.submit();
      REQUIRE(job == 1);
      std::vector<std::uint32_t> order;
      auto first = h.lease();
      order.push_back(first->tile);
      h.put_ok(*first);
      if (focused) {
        const Session s = sign_in(h);
        const Response res = h.collector.handle_sync(browser(
            Verb::post, "/ui/api/jobs/1/focus", R"({"x": 12, "y": 8, "width": 8, "height": 8})", s.cookie, s.csrf));
        REQUIRE(res.result() == Status::ok);
      }
      while (auto l = h.lease()) {
        order.push_back(l->tile);
        h.put_ok(*l);
      }
      REQUIRE(h.status(job).state == protocol::JobState::kDone);
      CHECK((order[1] == 5) == focused);  // the middle tile came second only when focused
      std::ifstream in(dir.path() / "out" / "job-1.png", std::ios::binary);
      bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    }
    return bytes;
  };
  const std::string plain = render(false);
  const std::string focused = render(true);
  REQUIRE_FALSE(plain.empty());
  CHECK(plain == focused);
}

TEST_CASE("web page: tiles restored at start-up get sequence numbers and a new generation", "[web][delta]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::vector<std::uint32_t> stored;
  std::int64_t generation = 0;
  std::uint64_t job = 0;
  {
    Harness h(config);
    job = h.submit();
    for (int i = 0; i < 2; ++i) {
      const protocol::Lease l = *h.lease();
      h.put_ok(l);
      stored.push_back(l.tile);
    }
    const json::value before = get_delta(h, sign_in(h), job, 0);
    generation = before.at("generation").as_int64();
    CHECK(tile_ids(before) == stored);
  }
  Harness h(config);
  const Session s = sign_in(h);  // the restart signed everyone out: a new session
  const json::value after = get_delta(h, s, job, 0);
  CHECK(after.at("generation").as_int64() != generation);
  CHECK(tile_ids(after) == stored);
  for (const json::value& t : after.at("tiles").as_array()) CHECK(t.at("worker").as_string() == "");
  const std::int64_t seq = after.at("seq").as_int64();
  CHECK(seq == 2);
  // A tile stored now comes after them.
  const protocol::Lease l = *h.lease();
  h.put_ok(l);
  const json::value next = get_delta(h, s, job, static_cast<std::uint64_t>(seq));
  CHECK(tile_ids(next) == std::vector<std::uint32_t>{l.tile});
  CHECK(next.at("seq").as_int64() == 3);
}
