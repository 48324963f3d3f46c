// The web page's files as the build embeds them (src/web/embed.cmake, web/assets.h).
#include <set>
#include <string>

#include <catch2/catch.hpp>

#include "web/assets.h"

using dtraced::web::all_assets;
using dtraced::web::Asset;
using dtraced::web::find_asset;

TEST_CASE("the page's four files are embedded at their URL paths", "[web]") {
  REQUIRE(all_assets().size() == 4);
  const struct {
    const char* path;
    const char* type;
  } expected[] = {{"/", "text/html; charset=utf-8"},
                  {"/ui/app.js", "text/javascript; charset=utf-8"},
                  {"/ui/app.css", "text/css; charset=utf-8"},
                  {"/ui/favicon.svg", "image/svg+xml"}};
  std::set<std::string> etags;
  for (const auto& e : expected) {
    INFO(e.path);
    const Asset* asset = find_asset(e.path);
    REQUIRE(asset != nullptr);
    CHECK(asset->content_type == e.type);
    CHECK_FALSE(asset->bytes.empty());
    // A quoted hex prefix of the content's SHA-256, different for each file.
    REQUIRE(asset->etag.size() == 34);
    CHECK(asset->etag.front() == '"');
    CHECK(asset->etag.back() == '"');
    CHECK(asset->etag.substr(1, 32).find_first_not_of("0123456789abcdef") == std::string::npos);
    etags.insert(std::string(asset->etag));
  }
  CHECK(etags.size() == 4);
  CHECK(find_asset("/index.html") == nullptr);
  CHECK(find_asset("/ui/") == nullptr);
  CHECK(find_asset("/ui/app.js?x=1") == nullptr);
}

TEST_CASE("the embedded page references its files and holds no inline script", "[web]") {
  const std::string html(find_asset("/")->text());
  CHECK(html.find("<!doctype html>") == 0);
  CHECK(html.find("src=\"/ui/app.js\"") != std::string::npos);
  CHECK(html.find("href=\"/ui/app.css\"") != std::string::npos);
  CHECK(html.find("<link rel=\"icon\" href=\"/ui/favicon.svg\">") != std::string::npos);
  CHECK(html.find("style=") == std::string::npos);
  CHECK(html.find("<script>") == std::string::npos);
}
