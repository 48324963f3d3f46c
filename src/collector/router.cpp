#include "collector/router.h"

#include <algorithm>
#include <chrono>
#include <string>
#include <string_view>
#include <utility>

#include <fmt/format.h>

#include "collector/admission.h"
#include "collector/handlers.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// Logs a refused token with the peer's address, at most once per LogThrottle interval.
void note_auth_failure(Context& c, const http::Request& head) {
  ++c.counters.auth_failures;
  std::uint64_t held_back = 0;
  if (!c.auth_failure_log.allow(c.clock.now(), held_back)) return;
  const std::string peer = request_peer(head);
  const auto target = head.target();
  util::log_warn(
      "collector: refused a request for {} from {}: missing or wrong bearer token{}",
      std::string_view(target.data(), std::min<std::size_t>(target.size(), 128)),
      peer.empty() ? "an unknown address" : peer,
      held_back == 0 ? std::string() : fmt::format(" ({} more refused since the last such line)", held_back));
}

util::Result<Admitted, Refusal> admit_counted(Context& c, const http::Request& head) {
  auto admitted = admit(head, c.token, c.config.limits.max_body_bytes);
  if (!admitted && admitted.error().status == http::Status::unauthorized) note_auth_failure(c, head);
  return admitted;
}

http::Response timed_lease(Context& c, const http::Request& req) {
  const TimePoint start = c.clock.now();
  http::Response res = lease_tile(c, req);
  c.counters.lease_seconds.observe(std::chrono::duration<double>(c.clock.now() - start).count());
  return res;
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
  sweep_workers(c);

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
      co_return co_await get_job_image(c, route.job, route.image_format, route.image_frame);
    case RouteKind::kCancelJob:
      co_return co_await cancel_job(c, route.job);
    case RouteKind::kLease:
      co_return timed_lease(c, req);
    case RouteKind::kScene:
      co_return co_await get_scene(c, std::move(route.digest));
    case RouteKind::kPutTile:
      co_return co_await put_tile(c, std::move(route), std::move(req));
    case RouteKind::kJobPriority:
      co_return co_await set_job_priority(c, route.job, std::move(req));
    case RouteKind::kRequeueJob:
      co_return co_await requeue_job(c, route.job);
    case RouteKind::kPauseJob:
      co_return co_await pause_job(c, route.job);
    case RouteKind::kResumeJob:
      co_return co_await resume_job(c, route.job);
    case RouteKind::kDeleteJob:
      co_return co_await delete_job(c, route.job, route.delete_image);
    case RouteKind::kWorkers:
      co_return list_workers(c);
  }
  co_return http::make_error(http::Status::internal_server_error, "unhandled route");
}

}  // namespace dtraced::collector
