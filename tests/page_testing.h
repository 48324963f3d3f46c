// The web page's requests as a browser sends them, for the tests of the page's access rules
// (test_web_page.cpp, test_collector_roles.cpp).
#pragma once

#include <string>
#include <string_view>
#include <utility>

#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "collector/web_access.h"
#include "http/types.h"

namespace dtraced::testing {

// A request as a browser on the page sends it (no bearer token); a cookie goes after another
// site's, as browsers mix them.
inline http::Request browser(http::Verb method, std::string target, std::string body = {}, std::string_view cookie = {},
                             std::string_view csrf = {}) {
  namespace bhttp = boost::beast::http;
  http::Request req =
      http::make_request(method, target, std::move(body), method == http::Verb::get ? "" : "application/json");
  req.set(bhttp::field::host, "127.0.0.1:7878");
  if (!cookie.empty()) req.set(bhttp::field::cookie, fmt::format("other=1; dtraced_session={}", cookie));
  if (!csrf.empty()) req.set(collector::kCsrfHeader, csrf);
  if (method != http::Verb::get) {
    req.set(bhttp::field::origin, "http://127.0.0.1:7878");
    req.set("Sec-Fetch-Site", "same-origin");
  }
  return req;
}

// A header field of an answer by name, "" when absent.
inline std::string header_of(const http::Response& res, std::string_view name) {
  const auto it = res.find(boost::beast::string_view(name.data(), name.size()));
  return it == res.end() ? std::string() : std::string(it->value());
}

}  // namespace dtraced::testing
