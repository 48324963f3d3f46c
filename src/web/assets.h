// dtraced::web assets: the collector's web page files, compiled into the binary.
//
// Owns: the files of src/web/static (index.html, app.js, app.css, favicon.svg) as byte arrays
// that src/web/embed.cmake generates at build time, each with the URL path it is served at, its
// content type and its ETag (a quoted prefix of the SHA-256 of its bytes, computed by the build).
// Nothing here knows HTTP beyond those strings: the collector's router serves them.
//
//   /                  index.html    text/html; charset=utf-8
//   /ui/app.js         app.js        text/javascript; charset=utf-8
//   /ui/app.css        app.css       text/css; charset=utf-8
//   /ui/favicon.svg    favicon.svg   image/svg+xml
//
// Thread safety: immutable data; every function is pure.
#pragma once

#include <span>
#include <string_view>

namespace dtraced::web {

struct Asset {
  std::string_view url_path;      // "/" or "/ui/<file>"
  std::string_view content_type;  // the Content-Type value
  std::string_view etag;          // quoted, as an ETag header carries it
  std::span<const unsigned char> bytes;

  std::string_view text() const { return {reinterpret_cast<const char*>(bytes.data()), bytes.size()}; }
};

// Every embedded file, in a fixed order.
std::span<const Asset> all_assets();

// The file served at `url_path` (the target's path, without a query), or null.
const Asset* find_asset(std::string_view url_path);

}  // namespace dtraced::web
