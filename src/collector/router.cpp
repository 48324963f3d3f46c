#include "collector/router.h"

#include <algorithm>
#include <chrono>
#include <string>
#include <string_view>
#include <utility>

#include <fmt/format.h>

#include "collector/admission.h"
#include "collector/handlers.h"
#include "collector/web_access.h"
#include "util/log.h"
#include "web/assets.h"

namespace dtraced::collector {
namespace {

// Logs a refused token with the peer's address, at most once per LogThrottle interval.
void note_auth_failure(Context& c, const http::Request& head, std::string_view why) {
  ++c.counters.auth_failures;
  std::uint64_t held_back = 0;
  if (!c.auth_failure_log.allow(c.clock.now(), held_back)) return;
  const std::string peer = request_peer(head);
  const auto target = head.target();
  util::log_warn(
      "collector: refused a request for {} from {}: {}{}",
      std::string_view(target.data(), std::min<std::size_t>(target.size(), 128)),
      peer.empty() ? "an unknown address" : peer, why,
      held_back == 0 ? std::string() : fmt::format(" ({} more refused since the last such line)", held_back));
}

bool is_page_request(const http::Request& head) {
  return is_page_path(target_path(std::string_view(head.target().data(), head.target().size())));
}

util::Result<Admitted, Refusal> admit_counted(Context& c, const http::Request& head) {
  const PageAccess page{c.config.web_ui, &c.sessions, c.clock.now(), page_scheme(c.config.tls.enabled)};
  std::optional<Role> refused_role;
  auto admitted = admit(head, c.token, c.credentials, c.config.limits.max_body_bytes, page, &refused_role);
  // A page request without a session is no refused token (the page asks before it signs in).
  if (!admitted && admitted.error().status == http::Status::unauthorized && !is_page_request(head)) {
    note_auth_failure(c, head, admitted.error().error.message);
  }
  if (refused_role) ++c.counters.role_refusals[static_cast<std::size_t>(*refused_role)];
  return admitted;
}

// Every answer of the page's targets carries its security headers (errors too); everything but
// the static files is no-store.
http::Response with_page_headers(const http::Request& head, http::Response res, bool is_asset) {
  if (is_page_request(head)) add_page_headers(res, !is_asset);
  return res;
}

async::Awaitable<http::Response> dispatch(Context& c, http::Request req);

http::Response timed_lease(Context& c, const http::Request& req, const Principal& who) {
  const TimePoint start = c.clock.now();
  http::Response res = lease_tile(c, req, who);
  c.counters.lease_seconds.observe(std::chrono::duration<double>(c.clock.now() - start).count());
  return res;
}

}  // namespace

std::optional<http::Response> check_request_header(Context& c, const http::Request& head, std::uint64_t& body_limit) {
  auto admitted = admit_counted(c, head);
  if (!admitted) return with_page_headers(head, respond(admitted.error()), false);
  body_limit = std::min(body_limit, admitted->body_limit);
  return std::nullopt;
}

bool is_authenticated(const Context& c, const http::Request& head) {
  if (c.config.web_ui && is_page_request(head)) {
    const std::string cookie = session_cookie(head);
    return !cookie.empty() && c.sessions.find(cookie, c.clock.now()).has_value();
  }
  return authenticate(head, c.token, c.credentials).kind == Authentication::Kind::kLive;
}

async::Awaitable<http::Response> handle_request(Context& c, http::Request req) {
  const bool page = is_page_request(req);
  if (!page) co_return co_await dispatch(c, std::move(req));
  http::Request head;
  head.method(req.method());
  head.target(req.target());
  const bool asset =
      req.method() == http::Verb::get &&
      web::find_asset(target_path(std::string_view(req.target().data(), req.target().size()))) != nullptr;
  http::Response res = co_await dispatch(c, std::move(req));
  const bool served_file = asset && res.result() != http::Status::not_found;
  co_return with_page_headers(head, std::move(res), served_file);
}

namespace {

async::Awaitable<http::Response> dispatch(Context& c, http::Request req) {
  auto admitted = admit_counted(c, req);
  if (!admitted) co_return respond(admitted.error());
  Route route = std::move(admitted->route);
  // Every route but the public ones has a principal (admission.h).
  const Principal who = admitted->who.value_or(Principal{});
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
      co_return timed_lease(c, req, who);
    case RouteKind::kScene:
      co_return co_await get_scene(c, std::move(route.digest));
    case RouteKind::kPutTile:
      co_return co_await put_tile(c, std::move(route), std::move(req), who);
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
    case RouteKind::kCa:
      co_return get_ca(c);
    case RouteKind::kCreateEnrollCode:
      co_return co_await create_enroll_code(c, req);
    case RouteKind::kEnroll:
      co_return co_await enroll(c, req);
    case RouteKind::kCreateCredential:
      co_return co_await create_credential(c, req);
    case RouteKind::kListCredentials:
      co_return list_credentials(c);
    case RouteKind::kRevokeCredential:
      co_return co_await revoke_credential(c, route.name);
    case RouteKind::kPageAsset:
      co_return get_page_asset(route.asset, req);
    case RouteKind::kSessionCreate:
      co_return sign_in(c, req);
    case RouteKind::kSessionGet:
      co_return get_session(c, req);
    case RouteKind::kSessionDelete:
      co_return sign_out(c, req);
    case RouteKind::kJobTiles:
      co_return co_await get_job_tiles(c, route, req);
    case RouteKind::kJobFocus:
      co_return focus_job(c, route.job, req);
  }
  co_return http::make_error(http::Status::internal_server_error, "unhandled route");
}

}  // namespace

}  // namespace dtraced::collector
