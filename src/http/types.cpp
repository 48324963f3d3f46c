#include "http/types.h"

#include <utility>

#include <boost/beast/http/field.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>

namespace dtraced::http {
namespace {

constexpr unsigned kHttp11 = 11;

Response make_response(Status status, std::string body, std::string_view content_type) {
  Response res{status, kHttp11};
  res.set(boost::beast::http::field::content_type, content_type);
  res.body() = std::move(body);
  res.prepare_payload();
  return res;
}

}  // namespace

Response make_json_response(Status status, const boost::json::value& body) {
  return make_response(status, boost::json::serialize(body), kJsonContentType);
}

Response make_error(Status status, std::string_view message, std::string_view field) {
  boost::json::object body;
  body["error"] = boost::json::string_view(message.data(), message.size());
  body["field"] = boost::json::string_view(field.data(), field.size());
  return make_json_response(status, body);
}

Response make_text_response(Status status, std::string body, std::string_view content_type) {
  return make_response(status, std::move(body), content_type);
}

Response make_binary_response(Status status, std::string body, std::string_view content_type) {
  return make_response(status, std::move(body), content_type);
}

Request make_request(Verb method, std::string_view target, std::string body, std::string_view content_type) {
  Request req{method, target, kHttp11};
  if (!content_type.empty()) req.set(boost::beast::http::field::content_type, content_type);
  req.body() = std::move(body);
  return req;
}

}  // namespace dtraced::http
