#include "collector/router.h"

#include <algorithm>
#include <utility>

#include "collector/admission.h"
#include "collector/handlers.h"

namespace dtraced::collector {
namespace {

util::Result<Admitted, Refusal> admit_counted(Context& c, const http::Request& head) {
  auto admitted = admit(head, c.token, c.config.limits.max_body_bytes);
  if (!admitted && admitted.error().status == http::Status::unauthorized) ++c.counters.auth_failures;
  return admitted;
}

}  // namespace

std::optional<http::Response> check_request_header(Context& c, const http::Request& head, std::uint64_t& body_limit) {
  auto admitted = admit_counted(c, head);
  if (!admitted) return respond(admitted.error());
  body_limit = std::min(body_limit, admitted->body_limit);
  return std::nullopt;
}

bool is_authenticated(const Context& c, const http::Request& head) { return c.token.accepts(head); }

async::Awaitable<http::Response> handle_request(Context& c, http::Request req) {
  auto admitted = admit_counted(c, req);
  if (!admitted) co_return respond(admitted.error());
  Route route = std::move(admitted->route);
  if (route.kind == RouteKind::kHealthz) co_return get_health();
  if (auto sized = check_body_size(req.body().size(), admitted->body_limit); !sized) co_return respond(sized.error());
  if (!c.opened) co_return respond(busy("the collector is starting"));

  switch (route.kind) {
    case RouteKind::kHealthz:
      co_return get_health();
    case RouteKind::kMetrics:
      co_return get_metrics(c);
    case RouteKind::kSubmitJob:
      co_return co_await submit_job(c, std::move(req));
    case RouteKind::kListJobs:
      co_return list_jobs(c, route);
    case RouteKind::kJobStatus:
      co_return get_job(c, route.job);
    case RouteKind::kJobImage:
      co_return co_await get_job_image(c, route.job, route.image_format);
    case RouteKind::kCancelJob:
      co_return co_await cancel_job(c, route.job);
    case RouteKind::kLease:
      co_return lease_tile(c, req.body());
    case RouteKind::kScene:
      co_return co_await get_scene(c, std::move(route.digest));
    case RouteKind::kPutTile:
      co_return co_await put_tile(c, std::move(route), std::move(req));
    case RouteKind::kJobPriority:
      co_return co_await set_job_priority(c, route.job, std::move(req));
    case RouteKind::kRequeueJob:
      co_return co_await requeue_job(c, route.job);
  }
  co_return http::make_error(http::Status::internal_server_error, "unhandled route");
}

}  // namespace dtraced::collector
