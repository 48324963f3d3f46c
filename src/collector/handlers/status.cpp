// GET /healthz and GET /metrics, and the answers the handler files share.
#include <string>
#include <utility>

#include <boost/json/value.hpp>

#include "collector/handlers.h"
#include "collector/metrics.h"
#include "protocol/worker_messages.h"

namespace dtraced::collector {

http::Response get_health() { return http::make_json_response(http::Status::ok, boost::json::value{{"ok", true}}); }

http::Response get_metrics(const Context& c) {
  return http::make_text_response(http::Status::ok, format_metrics(c.metrics()), kMetricsContentType);
}

http::Response json_answer(http::Status status, std::string body) {
  return http::make_text_response(status, std::move(body), http::kJsonContentType);
}

http::Response submit_answer(protocol::SubmitResult result) {
  const http::Status status = result == protocol::SubmitResult::kJobGone ? http::Status::gone : http::Status::ok;
  return json_answer(status, protocol::encode(result));
}

http::Response upload_answer(protocol::SubmitResult result, const std::optional<LeaseAnswer>& grant) {
  if (!grant) return submit_answer(result);
  const http::Status status = result == protocol::SubmitResult::kJobGone ? http::Status::gone : http::Status::ok;
  if (grant->text.empty()) {
    http::Response res = json_answer(status, protocol::encode(protocol::UploadAnswer{result, grant->reply}));
    if (grant->finished) res.set(protocol::kFinishedHeader, "1");
    return res;
  }
  // protocol::encode(UploadAnswer)'s splice, with the lease reply already encoded (a test
  // compares the two).
  std::string body = R"({"result":")";
  body += protocol::to_string(result);
  body += R"(","next":)";
  body += grant->text;
  body += '}';
  http::Response res = json_answer(status, std::move(body));
  if (grant->finished) res.set(protocol::kFinishedHeader, "1");
  return res;
}

}  // namespace dtraced::collector
