// dtraced::collector handlers: one function per route of README.md's "HTTP API".
//
// Owns: what each admitted request (admission.h) gets. A handler is a pure check (checks.h), then
// one effectful step on the Context (the queue, the store writer, the thread pool, an image),
// then an answer; each lives in a file of its concern under handlers/, so a new route is a new
// small file, a RouteKind (routes.h) and one line in the router (router.h).
//
//   handlers/jobs.cpp            POST /v1/jobs, GET /v1/jobs, GET /v1/jobs/{id}, POST .../cancel
//   handlers/tiles.cpp           PUT /v1/jobs/{id}/tiles/{tile}
//   handlers/lease.cpp           POST /v1/lease
//   handlers/scenes_images.cpp   GET /v1/scenes/{digest}, GET /v1/jobs/{id}/image
//   handlers/status.cpp          GET /healthz, GET /metrics
//   handlers/manage.cpp          POST /v1/jobs/{id}/priority, .../requeue, .../pause, .../resume
//   handlers/delete.cpp          DELETE /v1/jobs/{id}
//   handlers/workers.cpp         GET /v1/workers, and the registry updates of lease and tiles
//   handlers/credentials.cpp     GET /v1/ca, POST /v1/enroll-codes, POST /v1/enroll,
//                                POST and GET /v1/credentials, POST /v1/credentials/{name}/revoke
//   handlers/web.cpp             GET /, /ui/<file>, /ui/session (POST, GET, DELETE),
//                                GET /ui/api/jobs/{id}/tiles, POST /ui/api/jobs/{id}/focus
//
// Thread safety: on the loop only; each may suspend (co_await) while the pool or the store works,
// and looks its job up again afterwards.
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "async/async.h"
#include "collector/context.h"
#include "collector/refusal.h"
#include "collector/routes.h"
#include "http/types.h"
#include "image/image_io.h"
#include "protocol/messages.h"

namespace dtraced::collector {

async::Awaitable<http::Response> submit_job(Context& c, http::Request req);
// GET /v1/jobs?state=S&limit=N: the newest `route.list_limit` jobs in `route.list_state`, oldest first.
http::Response list_jobs(const Context& c, const Route& route);
http::Response get_job(const Context& c, JobId id);
async::Awaitable<http::Response> cancel_job(Context& c, JobId id);

// `who`: a worker credential's name is the worker's name (the request's own name is ignored);
// the operator token keeps the name the worker sends (protocol::kWorkerHeader, the lease body).
async::Awaitable<http::Response> put_tile(Context& c, Route route, http::Request req, const Principal& who);

http::Response lease_tile(Context& c, const http::Request& req, const Principal& who);
// What POST /v1/lease answers: a lease or a retry-after; `finished` with protocol::kFinishedHeader.
struct LeaseAnswer {
  protocol::LeaseReply reply;
  bool finished = false;
  // `reply` as protocol::encode writes it (grant_lease fills it; when empty it is encoded then).
  std::string text;
};
// POST /v1/lease's work after its body is decoded, shared with a tile upload that asks for its
// next lease (protocol::kNextLeaseHeader): the registry's note, the lingering collector's
// "finished", the pixel version check (the refusal), the queue.
util::Result<LeaseAnswer, Refusal> grant_lease(Context& c, const http::Request& req, const Principal& who,
                                               const protocol::LeaseRequest& request);
// A grant as POST /v1/lease answers it.
http::Response lease_answer(const LeaseAnswer& grant);
// The name a worker is recorded under: the credential's for a worker credential, else `sent`.
std::string recorded_worker_name(const Principal& who, std::string sent);

async::Awaitable<http::Response> get_scene(Context& c, std::string digest);
// `frame`: a frame number of the job (404 when it renders no such frame); without it, the frame
// being rendered.
async::Awaitable<http::Response> get_job_image(Context& c, JobId id, image::ImageFormat format,
                                               std::optional<std::uint32_t> frame);

// handlers/manage.cpp
async::Awaitable<http::Response> set_job_priority(Context& c, JobId id, http::Request req);
async::Awaitable<http::Response> requeue_job(Context& c, JobId id);
async::Awaitable<http::Response> pause_job(Context& c, JobId id);
async::Awaitable<http::Response> resume_job(Context& c, JobId id);

// handlers/delete.cpp
async::Awaitable<http::Response> delete_job(Context& c, JobId id, bool delete_image);

// handlers/workers.cpp
http::Response list_workers(Context& c);

// handlers/credentials.cpp (credentials.h)
// GET /v1/ca: Context::ca_pem, 404 when there is none (plain HTTP).
http::Response get_ca(const Context& c);
// POST /v1/enroll-codes {"expires_s", "name"} -> 201 {"code", "expires_unix"}.
async::Awaitable<http::Response> create_enroll_code(Context& c, const http::Request& req);
// POST /v1/enroll {"code", "name"} -> 201 {"name", "role": "worker", "token"}; 403 for an
// unknown, used or expired code, 429 past the failed-attempt limit.
async::Awaitable<http::Response> enroll(Context& c, const http::Request& req);
// POST /v1/credentials {"name", "role"} -> 201 {"name", "role", "token"}; 409 when the name exists.
async::Awaitable<http::Response> create_credential(Context& c, const http::Request& req);
// GET /v1/credentials -> {"credentials": [{"name", "role", "created_unix", "revoked_unix"?}]}.
http::Response list_credentials(const Context& c);
// POST /v1/credentials/{name}/revoke -> 200 {"name", "role", "revoked_unix", "leases_released"}:
// durable first, then refused from the next request on; a worker's leases are re-offered at once.
async::Awaitable<http::Response> revoke_credential(Context& c, std::string name);

// handlers/web.cpp: the web page (docs/web-access.md)
// GET / and GET /ui/<file>: an embedded file, with its ETag (304 on If-None-Match).
http::Response get_page_asset(const std::string& path, const http::Request& req);
// POST /ui/session, GET /ui/session, DELETE /ui/session.
http::Response sign_in(Context& c, const http::Request& req);
http::Response get_session(Context& c, const http::Request& req);
http::Response sign_out(Context& c, const http::Request& req);
// GET /ui/api/jobs/{id}/tiles?since=SEQ[&frame=N]: the tiles stored since SEQ, as an atlas PNG.
async::Awaitable<http::Response> get_job_tiles(Context& c, const Route& route, const http::Request& req);
// POST /ui/api/jobs/{id}/focus: the region's unfinished tiles to the front of the job's queue.
http::Response focus_job(Context& c, JobId id, const http::Request& req);
// The page's view of a job (JobRecord::tile_seq, leased_by): a tile leased to `worker`, and a
// tile stored from `worker`.
void note_page_lease(JobRecord& job, TileIndex tile, std::string_view worker);
void note_page_stored(JobRecord& job, TileIndex tile, std::string_view worker);

http::Response get_health();
http::Response get_metrics(const Context& c);

// ---- the worker registry (handlers/workers.cpp) ----------------------------------------------

// The request's source address as the server stamped it (http::kPeerHeader), "" if none.
std::string request_peer(const http::Request& req);
// "192.0.2.7", or "an unknown address".
std::string peer_text(const WorkerId& id);
// The sender of `req` under the name it gave.
WorkerId worker_id(const http::Request& req, std::string name);
// Counts a lease request of worker `name` in the registry (with the kIsaHeader it carries); logs a
// first request.
void note_lease_request(Context& c, const http::Request& req, const std::string& name,
                        const protocol::LeaseRequest& lease);
// Counts a tile upload's outcome; `rays` for a stored one. Logs a first request.
void note_tile_upload(Context& c, const WorkerId& id, TileOutcome outcome, std::uint64_t rays);
// A worker leased or returned a tile of `job`.
void note_job_served(Context& c, JobId job);
// `s` with no_worker_s set when its unfinished job has had no worker for kNoWorkerAfterS.
protocol::JobStatus with_worker_gap(const Context& c, protocol::JobStatus s);
// At most every few seconds: marks quiet workers (logging each once) and forgets old ones.
void sweep_workers(Context& c);

// A refusal (409) when `req` is from a worker of another pixel version than this collector's
// (protocol::kPixelVersionHeader): a different number, or, when `required`, none or a garbled one.
// Counted in the metrics; the caller answers with it.
std::optional<Refusal> pixel_version_refusal(Context& c, const http::Request& req, bool required);

// ---- answers shared by the handler files ------------------------------------------------------

// `body` (already JSON) with `status`.
http::Response json_answer(http::Status status, std::string body);
// A tile upload's answer: 410 for job_gone, else 200.
http::Response submit_answer(protocol::SubmitResult result);
// The same with the next lease the upload asked for (protocol::UploadAnswer); `grant` nullopt
// when there is none to give (the answer is then submit_answer's).
http::Response upload_answer(protocol::SubmitResult result, const std::optional<LeaseAnswer>& grant);

}  // namespace dtraced::collector
