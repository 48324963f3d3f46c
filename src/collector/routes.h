// dtraced::collector routes: which endpoint a request names, its body limit, and who may call it.
//
// Owns: the collector's URL space (README.md, "HTTP API") as pure functions of the request line,
// and the bearer-token check. No state beyond the expected token's digest; nothing here touches
// jobs, the queue or the store, so every rule is testable without sockets or an event loop.
//
//   GET  /healthz                      no token
//   GET  /metrics
//   POST /v1/jobs                      GET /v1/jobs
//   GET  /v1/jobs/{id}                 GET /v1/jobs/{id}/image[?format=png|ppm|pfm][&frame=N]
//   POST /v1/jobs/{id}/cancel          PUT /v1/jobs/{id}/tiles/{tile}
//   POST /v1/lease                     GET /v1/scenes/{digest}
//   POST /v1/jobs/{id}/priority        POST /v1/jobs/{id}/requeue
//   POST /v1/jobs/{id}/pause           POST /v1/jobs/{id}/resume
//   DELETE /v1/jobs/{id}[?image=keep|delete]
//   GET  /v1/workers
//   GET  /v1/ca                        no token (the CA workers trust; 404 on plain HTTP)
//   POST /v1/enroll                    no token (a join code buys a worker credential)
//   POST /v1/enroll-codes              POST /v1/credentials       GET /v1/credentials
//   POST /v1/credentials/{name}/revoke
// Which credential may call what: credentials.h (route_allows).
//   GET /v1/jobs takes ?state=S&limit=N (each at most once)
//
// The web page (docs/web-access.md; off with --no-web-ui, then all of these are 404):
//   GET  /                             GET /ui/app.js, /ui/app.css, /ui/favicon.svg   no credentials
//   POST /ui/session                   GET /ui/session            DELETE /ui/session
//   GET  /ui/api/jobs[?state=S&limit=N]                     GET /ui/api/jobs/{id}
//   GET  /ui/api/jobs/{id}/image[?frame=N]                  GET /ui/api/workers
//   POST /ui/api/jobs/{id}/cancel|pause|resume|requeue|priority
//   GET  /ui/api/jobs/{id}/tiles?since=SEQ[&frame=N]        POST /ui/api/jobs/{id}/focus
// /ui/api/... names the /v1 route of the same name (page_may_call lists which) and takes the
// session cookie only; /v1/... takes the bearer token only.
//
// Targets must be in origin form ("/path?query"). Ids are decimal without sign or leading zeros
// in [1, protocol::kMaxId]; tile indices decimal in [0, protocol::kMaxTilesPerJob); digests are
// protocol::is_digest. No percent-decoding is done: none of these segments needs it, and an
// encoded one is simply not a valid id. A path that matches nothing is 404; a known path with
// another method is 405 (with the allowed methods); a query parameter a route does not take is
// 400.
//
// Thread safety: match_route and route_body_limit are stateless; a TokenCheck is immutable after
// construction and may be shared.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "collector/queue.h"
#include "collector/refusal.h"
#include "http/types.h"
#include "image/image_io.h"
#include "protocol/messages.h"
#include "util/result.h"
#include "util/sha256.h"

namespace dtraced::collector {

using protocol::kWorkerHeader;

enum class RouteKind {
  kHealthz,
  kMetrics,
  kSubmitJob,
  kListJobs,
  kJobStatus,
  kJobImage,
  kCancelJob,
  kLease,
  kScene,
  kPutTile,
  kJobPriority,  // POST /v1/jobs/{id}/priority
  kRequeueJob,   // POST /v1/jobs/{id}/requeue
  kPauseJob,     // POST /v1/jobs/{id}/pause
  kResumeJob,    // POST /v1/jobs/{id}/resume
  kDeleteJob,    // DELETE /v1/jobs/{id}
  kWorkers,
  // Roles and enrollment (credentials.h, handlers/credentials.cpp).
  kCa,                // GET /v1/ca
  kCreateEnrollCode,  // POST /v1/enroll-codes
  kEnroll,            // POST /v1/enroll
  kCreateCredential,  // POST /v1/credentials
  kListCredentials,   // GET /v1/credentials
  kRevokeCredential,  // POST /v1/credentials/{name}/revoke
  // The web page (web_access.h, docs/web-access.md).
  kPageAsset,      // GET / and GET /ui/<file>: an embedded file (web/assets.h)
  kSessionCreate,  // POST /ui/session: sign in
  kSessionGet,     // GET /ui/session
  kSessionDelete,  // DELETE /ui/session: sign out
  kJobTiles,       // GET /ui/api/jobs/{id}/tiles?since=SEQ[&frame=N]: the tile delta
  kJobFocus,       // POST /ui/api/jobs/{id}/focus: render a region first
};

struct Route {
  RouteKind kind = RouteKind::kHealthz;
  JobId job = 0;                                               // kJobStatus, kJobImage, kCancelJob, kPutTile
  TileIndex tile = 0;                                          // kPutTile
  std::string digest;                                          // kScene
  image::ImageFormat image_format = image::ImageFormat::kPng;  // kJobImage
  std::optional<protocol::JobState> list_state;                // kListJobs: ?state=S
  std::size_t list_limit = protocol::kMaxListedJobs;           // kListJobs: ?limit=N, [1, kMaxListedJobs]
  bool delete_image = false;                                   // kDeleteJob: ?image=delete
  std::optional<std::uint32_t> image_frame = std::nullopt;     // kJobImage, kJobTiles: ?frame=N, a frame number
  std::string asset = {};                                      // kPageAsset: its URL path
  std::uint64_t since = 0;                                     // kJobTiles: ?since=SEQ
  std::string name = {};                                       // kRevokeCredential: the credential
  // Reached through the page (/ui/api/...): the session cookie, not the bearer token, admitted it.
  bool page = false;
  bool operator==(const Route&) const = default;
};

// The endpoint a request names, or why it names none (404, 405 with the allowed methods, 400 for
// a bad target or query).
util::Result<Route, Refusal> match_route(http::Verb method, std::string_view target);

// The largest request body the route accepts: protocol::kMaxTilePayloadBytes for tiles,
// kMaxJobSubmitBytes for submissions, kMaxMessageBytes for everything else; kMaxPageBodyBytes
// (web_access.h) for every route of the page.
std::uint64_t route_body_limit(RouteKind kind);
std::uint64_t route_body_limit(const Route& route);

// Whether the page may call this kind through /ui/api/... (the reads and the job verbs the page
// offers; never a worker's route, a submission or a delete).
bool page_may_call(RouteKind kind);

// Everything but the health check, the CA and enrollment needs a token.
inline bool route_needs_token(RouteKind kind) {
  return kind != RouteKind::kHealthz && kind != RouteKind::kCa && kind != RouteKind::kEnroll;
}

// True for exactly `GET /healthz` (with or without a query): answered before the token check.
bool is_health_check(http::Verb method, std::string_view target);
// True for the paths of the routes that need no token: /healthz, /v1/ca and /v1/enroll (any
// method, so that a wrong one gets its 405 without a token).
bool is_public_path(std::string_view target);

// Accepts `Authorization: Bearer <token>` (scheme case-insensitive) for the one token it was
// built with. The comparison is over the SHA-256 digests of the presented and the expected token
// with CRYPTO_memcmp, so its time depends neither on where they differ nor on their lengths.
class TokenCheck {
 public:
  explicit TokenCheck(std::string_view token);
  bool accepts(const http::Request& req) const;
  // Whether `presented` is the token (the web page's sign-in), compared the same way.
  bool accepts_token(std::string_view presented) const;
  // Whether a non-empty presented token with this SHA-256 is the token (for a caller that has the
  // digest already: authenticate_token hashes a token once for this and the credential table).
  bool accepts_digest(const util::Sha256Digest& presented_sha256) const;

 private:
  util::Sha256Digest expected_;
};

}  // namespace dtraced::collector
