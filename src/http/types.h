// dtraced::http message types and response builders, shared by the server, the client and the
// routes built on them.
//
// Owns: the one request and one response type every dtraced endpoint speaks (Beast messages with
// a std::string body: JSON, Prometheus text and binary tile payloads all fit), and builders that
// set status, Content-Type and Content-Length the same way everywhere, including the JSON error
// shape {"error": message, "field": JSON Pointer} that every 4xx and 5xx carries ("" as the field
// names the request as a whole).
//
// Stateless functions: thread-safe.
#pragma once

#include <string>
#include <string_view>

#include <boost/beast/http/message.hpp>
#include <boost/beast/http/status.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/beast/http/verb.hpp>
#include <boost/json/fwd.hpp>

namespace dtraced::http {

using Request = boost::beast::http::request<boost::beast::http::string_body>;
using Response = boost::beast::http::response<boost::beast::http::string_body>;
using Status = boost::beast::http::status;
using Verb = boost::beast::http::verb;

inline constexpr std::string_view kJsonContentType = "application/json";
inline constexpr std::string_view kTextContentType = "text/plain; charset=utf-8";
inline constexpr std::string_view kBinaryContentType = "application/octet-stream";

// HTTP/1.1 response with `body` serialised compactly, Content-Type application/json.
Response make_json_response(Status status, const boost::json::value& body);

// {"error": message, "field": field} with `status` (a 4xx or 5xx). `field` is the JSON Pointer
// of the offending value, or "" when the problem is the request as a whole.
Response make_error(Status status, std::string_view message, std::string_view field = "");

// HTTP/1.1 responses with a text or binary body.
Response make_text_response(Status status, std::string body, std::string_view content_type = kTextContentType);
Response make_binary_response(Status status, std::string body, std::string_view content_type = kBinaryContentType);

// HTTP/1.1 request for the client; `content_type` is set only when not empty. The client fills
// in Host, Connection and Content-Length when it sends it.
Request make_request(Verb method, std::string_view target, std::string body = {}, std::string_view content_type = {});

}  // namespace dtraced::http
