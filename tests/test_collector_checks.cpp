// The collector's pure pieces, without sockets, a store or an event loop: routes and the token
// check, admission (the one rule for a request's head), the refusals every handler gives before it
// changes anything (a submission's room, a cancellation, a tile upload's six checks) and how a
// refusal is answered, a submission's row and record, and tile blobs.
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector/admission.h"
#include "collector/checks.h"
#include "collector/jobs.h"
#include "collector/refusal.h"
#include "collector/routes.h"
#include "collector/submission.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"

namespace {

namespace coll = dtraced::collector;
namespace protocol = dtraced::protocol;
namespace bhttp = boost::beast::http;
using coll::Refusal;
using coll::Route;
using coll::RouteKind;
using dtraced::http::Request;
using dtraced::http::Status;
using dtraced::http::Verb;

constexpr std::string_view kToken = "s3cret-token";

Request request(Verb method, std::string target, std::string_view authorization = {}) {
  Request req = dtraced::http::make_request(method, target);
  if (!authorization.empty()) req.set(bhttp::field::authorization, authorization);
  return req;
}

Request authorized(Verb method, std::string target) {
  return request(method, std::move(target), fmt::format("Bearer {}", kToken));
}

// Job 3: 32x24 pixels in tiles of 8, 12 tiles, rendering.
coll::JobRecord job_record() {
  coll::JobRecord job;
  job.id = 3;
  job.settings.width = 32;
  job.settings.height = 24;
  job.settings.samples = 4;
  job.tile_size = 8;
  REQUIRE(coll::init_frames(job));  // tiles_total and tile_indices: 12
  job.state = protocol::JobState::kRendering;
  return job;
}

// The payload of tile `tile` of job_record(), with the job's own rectangle.
protocol::TilePayload tile_payload(std::uint32_t tile) {
  protocol::TilePayload p;
  p.job = 3;
  p.tile = tile;
  p.rect = dtraced::scene::TileGrid(32, 24, 8).rect(tile);
  p.rgb.assign(std::size_t{p.rect.width} * p.rect.height * 3, 0.5f);
  return p;
}

Route tile_route(std::uint64_t job, std::uint32_t tile) {
  Route r;
  r.kind = RouteKind::kPutTile;
  r.job = job;
  r.tile = tile;
  return r;
}

}  // namespace

// ---- routes and the token ------------------------------------------------------------------------

TEST_CASE("routes map method and target to an endpoint", "[collector][routes]") {
  using coll::match_route;
  const auto kind = [](Verb v, std::string_view t) {
    auto r = match_route(v, t);
    REQUIRE(r.ok());
    return r.value();
  };
  const auto error = [](Verb v, std::string_view t) {
    auto r = match_route(v, t);
    REQUIRE_FALSE(r.ok());
    return r.error();
  };
  CHECK(kind(Verb::get, "/healthz").kind == RouteKind::kHealthz);
  CHECK(kind(Verb::get, "/metrics").kind == RouteKind::kMetrics);
  CHECK(kind(Verb::post, "/v1/jobs").kind == RouteKind::kSubmitJob);
  CHECK(kind(Verb::get, "/v1/jobs").kind == RouteKind::kListJobs);
  CHECK(kind(Verb::get, "/v1/jobs/7") == Route{RouteKind::kJobStatus, 7, 0, "", dtraced::image::ImageFormat::kPng,
                                               std::nullopt, dtraced::protocol::kMaxListedJobs});
  CHECK(kind(Verb::get, "/v1/jobs/7/image").image_format == dtraced::image::ImageFormat::kPng);
  CHECK(kind(Verb::get, "/v1/jobs/7/image?format=pfm").image_format == dtraced::image::ImageFormat::kPfm);
  CHECK(kind(Verb::get, "/v1/jobs/7/image?format=ppm").image_format == dtraced::image::ImageFormat::kPpm);
  CHECK(kind(Verb::post, "/v1/jobs/9007199254740991/cancel").job == 9007199254740991ull);
  const Route tile = kind(Verb::put, "/v1/jobs/3/tiles/0");
  CHECK((tile.kind == RouteKind::kPutTile && tile.job == 3 && tile.tile == 0));
  CHECK(kind(Verb::post, "/v1/lease").kind == RouteKind::kLease);
  const std::string digest(64, 'a');
  CHECK(kind(Verb::get, "/v1/scenes/" + digest).digest == digest);

  CHECK(error(Verb::get, "/nope").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/jobs/0").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/jobs/007").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/jobs/-1").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/jobs/9007199254740992").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/jobs/1/").status == Status::not_found);
  CHECK(error(Verb::put, "/v1/jobs/1/tiles/x").status == Status::not_found);
  CHECK(error(Verb::put, "/v1/jobs/1/tiles/262144").status == Status::not_found);
  CHECK(error(Verb::get, "/v1/scenes/" + std::string(64, 'A')).status == Status::not_found);
  CHECK(error(Verb::get, "/a/b/c/d/e/f/g/h").status == Status::not_found);
  const Refusal wrong = error(Verb::put, "/v1/jobs/1");
  CHECK(wrong.status == Status::method_not_allowed);
  CHECK(wrong.allow == "GET, DELETE");
  CHECK(kind(Verb::delete_, "/v1/jobs/1").kind == RouteKind::kDeleteJob);
  CHECK_FALSE(kind(Verb::delete_, "/v1/jobs/1").delete_image);
  CHECK_FALSE(kind(Verb::delete_, "/v1/jobs/1?image=keep").delete_image);
  CHECK(kind(Verb::delete_, "/v1/jobs/1?image=delete").delete_image);
  CHECK(error(Verb::delete_, "/v1/jobs/1?image=yes").error.path == "/image");
  CHECK(error(Verb::delete_, "/v1/jobs/1/cancel").allow == "POST");
  CHECK(kind(Verb::post, "/v1/jobs/3/pause").kind == RouteKind::kPauseJob);
  CHECK(kind(Verb::post, "/v1/jobs/3/resume").job == 3);
  CHECK(kind(Verb::post, "/v1/jobs/3/resume").kind == RouteKind::kResumeJob);
  CHECK(error(Verb::get, "/v1/jobs/3/resume").allow == "POST");
  CHECK(error(Verb::get, "/v1/lease").allow == "POST");
  CHECK(error(Verb::get, "/v1/jobs/1/image?format=jpg").status == Status::bad_request);
  CHECK(error(Verb::get, "/v1/jobs/1/image?size=2").error.path == "/format");
  CHECK(error(Verb::get, "/v1/jobs/1/image?format=png&format=pfm").status == Status::bad_request);
  CHECK(error(Verb::get, "/v1/jobs?x=1").status == Status::bad_request);
  CHECK(error(Verb::get, "http://host/v1/jobs").status == Status::bad_request);

  CHECK(coll::route_body_limit(RouteKind::kPutTile) == protocol::kMaxTilePayloadBytes);
  CHECK(coll::route_body_limit(RouteKind::kSubmitJob) == protocol::kMaxJobSubmitBytes);
  CHECK(coll::route_body_limit(RouteKind::kLease) == protocol::kMaxMessageBytes);
  CHECK(coll::is_health_check(Verb::get, "/healthz"));
  CHECK_FALSE(coll::is_health_check(Verb::post, "/healthz"));
}

TEST_CASE("the token check accepts exactly the bearer token", "[collector][routes]") {
  const coll::TokenCheck check(kToken);
  const auto with = [](std::string_view value) { return request(Verb::get, "/metrics", value); };
  CHECK(check.accepts(with(fmt::format("Bearer {}", kToken))));
  CHECK(check.accepts(with(fmt::format("bearer {}", kToken))));
  CHECK_FALSE(check.accepts(with("")));
  CHECK_FALSE(check.accepts(with("Bearer")));
  CHECK_FALSE(check.accepts(with("Bearer ")));
  CHECK_FALSE(check.accepts(with(kToken)));
  CHECK_FALSE(check.accepts(with(fmt::format("Basic {}", kToken))));
  CHECK_FALSE(check.accepts(with(fmt::format("Bearer {}x", kToken))));
  CHECK_FALSE(check.accepts(with(fmt::format("Bearer {}", kToken.substr(1)))));
}

// ---- admission -------------------------------------------------------------------------------------

TEST_CASE("admission: the health check needs no token, everything else the token, then a route",
          "[collector][admission]") {
  const coll::TokenCheck token(kToken);
  constexpr std::uint64_t kCap = 1 << 20;

  auto health = coll::admit(request(Verb::get, "/healthz?probe=1"), token, kCap);
  REQUIRE(health.ok());
  CHECK(health->route.kind == RouteKind::kHealthz);
  CHECK(health->body_limit == std::numeric_limits<std::uint64_t>::max());  // the server's own limit holds

  // The token comes before the route: an unknown path without it is 401, not 404.
  for (const std::string target : {"/metrics", "/v1/nowhere", "/v1/jobs/1"}) {
    auto refused = coll::admit(request(Verb::get, target, "Bearer wrong"), token, kCap);
    REQUIRE_FALSE(refused.ok());
    CHECK(refused.error().status == Status::unauthorized);
    CHECK(refused.error().error.message == "missing or wrong bearer token");
  }
  auto missing = coll::admit(authorized(Verb::get, "/v1/nowhere"), token, kCap);
  REQUIRE_FALSE(missing.ok());
  CHECK(missing.error().status == Status::not_found);

  // The route's body limit, under the configured cap.
  auto tile = coll::admit(authorized(Verb::put, "/v1/jobs/1/tiles/2"), token, kCap);
  REQUIRE(tile.ok());
  CHECK(tile->route == tile_route(1, 2));
  CHECK(tile->body_limit == kCap);
  auto lease = coll::admit(authorized(Verb::post, "/v1/lease"), token, kCap);
  REQUIRE(lease.ok());
  CHECK(lease->body_limit == protocol::kMaxMessageBytes);

  CHECK(coll::check_body_size(10, 10).ok());
  const auto too_big = coll::check_body_size(11, 10);
  REQUIRE_FALSE(too_big.ok());
  CHECK(too_big.error().status == Status::payload_too_large);
  CHECK(too_big.error().error.message == "request body of 11 bytes exceeds this endpoint's limit of 10 bytes");
}

TEST_CASE("a refusal is answered with the JSON error shape and the fields its status needs", "[collector][admission]") {
  const auto unauthorized = coll::respond(Refusal{Status::unauthorized, {"missing or wrong bearer token"}, {}});
  CHECK(unauthorized.result() == Status::unauthorized);
  CHECK(unauthorized[bhttp::field::www_authenticate] == "Bearer");
  const auto busy = coll::respond(coll::busy("the store is busy; retry later"));
  CHECK(busy.result() == Status::service_unavailable);
  CHECK(busy[bhttp::field::retry_after] == "1");
  const auto wrong_method = coll::respond(Refusal{Status::method_not_allowed, {"use GET"}, "GET"});
  CHECK(wrong_method[bhttp::field::allow] == "GET");
  const auto bad = coll::respond(coll::bad_request("no tile 12", "/tile"));
  CHECK(bad.count(bhttp::field::allow) == 0);
  CHECK(bad.count(bhttp::field::retry_after) == 0);
  auto body = protocol::decode_error_body(bad.body());
  REQUIRE(body.ok());
  CHECK(body.value() == protocol::ErrorBody{"no tile 12", "/tile"});
  CHECK(coll::job_not_found(42) == Refusal{Status::not_found, {"no such job: 42"}, {}});
}

// ---- submissions and cancellation -----------------------------------------------------------------

TEST_CASE("a submission needs a free job slot, room for its pixels and a running store", "[collector][checks]") {
  coll::CollectorConfig config;
  config.max_unfinished_jobs = 2;
  config.max_unfinished_pixels = 1000;
  coll::Load load{1, 600, true};
  CHECK(coll::check_job_slots(load, config).ok());
  load.unfinished_jobs = 2;
  const auto full = coll::check_job_slots(load, config);
  REQUIRE_FALSE(full.ok());
  CHECK(full.error() == coll::busy("too many unfinished jobs (limit 2); retry later"));

  load = {1, 600, true};
  CHECK(coll::check_job_room(20, 20, load, config).ok());  // 400 + 600 = the limit
  const auto larger_than_all = coll::check_job_room(40, 30, load, config);
  REQUIRE_FALSE(larger_than_all.ok());
  CHECK(larger_than_all.error().status == Status::payload_too_large);
  CHECK(larger_than_all.error().error.path == "/width");
  const auto no_room = coll::check_job_room(21, 20, load, config);
  REQUIRE_FALSE(no_room.ok());
  CHECK(no_room.error() == coll::busy("unfinished jobs already hold 600 of the limit of 1000 pixels; retry later"));
  load.accepting_writes = false;
  CHECK(coll::check_job_room(1, 1, load, config).error() == coll::busy("the collector is stopping"));
}

TEST_CASE("a cancellation: unknown 404, finished 409, cancelled again answered, stopping 503", "[collector][checks]") {
  CHECK(coll::check_cancel(9, nullptr, true).error() == coll::job_not_found(9));
  coll::JobRecord job = job_record();
  CHECK(coll::check_cancel(3, &job, true).value() == coll::CancelAction::kCancel);
  CHECK(coll::check_cancel(3, &job, false).error() == coll::busy("the collector is stopping"));
  job.finishing = true;
  CHECK(coll::check_cancel(3, &job, true).error().status == Status::conflict);
  job.finishing = false;
  job.state = protocol::JobState::kDone;
  CHECK(coll::check_cancel(3, &job, true).error().error.message == "job 3 is finished; nothing to cancel");
  job.state = protocol::JobState::kCancelled;
  CHECK(coll::check_cancel(3, &job, false).value() == coll::CancelAction::kAlreadyCancelled);
}

// ---- tile uploads -----------------------------------------------------------------------------------

TEST_CASE("a tile payload is refused for its format or a non-finite pixel, before its job is looked at",
          "[collector][checks]") {
  const std::string good = protocol::encode_tile_payload(tile_payload(5));
  auto checked = coll::check_tile_payload(good);
  REQUIRE(checked.ok());
  CHECK(checked.value() == tile_payload(5));

  const auto truncated = coll::check_tile_payload(std::string_view(good).substr(0, good.size() - 1));
  REQUIRE_FALSE(truncated.ok());
  CHECK(truncated.error().status == Status::bad_request);
  CHECK(truncated.error().error.message.starts_with("tile payload: "));
  CHECK(truncated.error().error.path == "");

  protocol::TilePayload nan = tile_payload(5);  // tile 5: x 8..15, y 8..15
  nan.rgb[3 * 9 + 1] = std::numeric_limits<float>::infinity();
  const auto non_finite = coll::check_tile_payload(protocol::encode_tile_payload(nan));
  REQUIRE_FALSE(non_finite.ok());
  CHECK(non_finite.error() == coll::bad_request("pixel (9, 9) holds a non-finite value", "/pixels"));
}

TEST_CASE("a tile payload with a negative pixel is refused, naming the pixel, but minus zero passes",
          "[collector][checks]") {
  protocol::TilePayload negative = tile_payload(5);  // tile 5: x 8..15, y 8..15
  negative.rgb[3 * (8 * 2 + 3) + 2] = -0.25f;
  const auto refused = coll::check_tile_payload(protocol::encode_tile_payload(negative));
  REQUIRE_FALSE(refused.ok());
  CHECK(refused.error() == coll::bad_request("pixel (11, 10) holds a negative value (-0.25 in blue); radiance "
                                             "is never below 0",
                                             "/pixels"));

  // -0.0 compares equal to 0: a renderer may produce it, and it is not negative radiance.
  protocol::TilePayload minus_zero = tile_payload(5);
  minus_zero.rgb[0] = -0.0f;
  CHECK(coll::check_tile_payload(protocol::encode_tile_payload(minus_zero)).ok());
}

TEST_CASE("a tile's pixels pass exactly when finite and not below zero, wherever the bad one is",
          "[collector][checks]") {
  // The check looks at bit patterns; every edge of the rule, as the first, a middle and the last value.
  constexpr float kMax = std::numeric_limits<float>::max();
  constexpr float kInf = std::numeric_limits<float>::infinity();
  const float passing[] = {0.0f, -0.0f, std::numeric_limits<float>::denorm_min(), std::numeric_limits<float>::min(),
                           1.0f, kMax};
  const float failing[] = {kInf,
                           -kInf,
                           std::numeric_limits<float>::quiet_NaN(),
                           -std::numeric_limits<float>::quiet_NaN(),
                           std::numeric_limits<float>::signaling_NaN(),
                           -std::numeric_limits<float>::denorm_min(),
                           -std::numeric_limits<float>::min(),
                           -1.0f,
                           -kMax};
  const protocol::TilePayload base = tile_payload(5);
  for (const std::size_t at : {std::size_t{0}, base.rgb.size() / 2 + 1, base.rgb.size() - 1}) {
    for (const float v : passing) {
      protocol::TilePayload p = base;
      p.rgb[at] = v;
      INFO("value " << v << " at " << at);
      CHECK(coll::check_tile_payload(protocol::encode_tile_payload(p)).ok());
    }
    for (const float v : failing) {
      protocol::TilePayload p = base;
      p.rgb[at] = v;
      INFO("value " << v << " at " << at);
      const auto refused = coll::check_tile_payload(protocol::encode_tile_payload(p));
      REQUIRE_FALSE(refused.ok());
      CHECK(refused.error().error.path == "/pixels");
    }
  }
}

TEST_CASE("a tile upload is checked against its URL, then its job: range, rectangle, sample counts",
          "[collector][checks]") {
  coll::JobRecord job = job_record();
  const protocol::TilePayload p = tile_payload(5);
  CHECK(coll::check_tile(tile_route(3, 5), &job, p).value() == coll::TileAction::kStore);

  // The URL and the payload must agree, whether or not the job exists.
  CHECK(coll::check_tile(tile_route(4, 5), nullptr, p).error() ==
        coll::bad_request("the payload is for job 3 but the URL names job 4", "/job"));
  CHECK(coll::check_tile(tile_route(3, 6), &job, p).error() ==
        coll::bad_request("the payload is tile 5 but the URL names tile 6", "/tile"));

  // An unknown or cancelled job: job_gone, whatever the payload.
  CHECK(coll::check_tile(tile_route(3, 5), nullptr, p).value() == coll::TileAction::kJobGone);
  job.state = protocol::JobState::kCancelled;
  CHECK(coll::check_tile(tile_route(3, 5), &job, p).value() == coll::TileAction::kJobGone);
  job.state = protocol::JobState::kDone;  // a done job's duplicates go to the store to be compared
  CHECK(coll::check_tile(tile_route(3, 5), &job, p).value() == coll::TileAction::kStore);

  protocol::TilePayload past = p;
  past.tile = 12;
  CHECK(coll::check_tile(tile_route(3, 12), &job, past).error() ==
        coll::bad_request("job 3 has 12 tiles; there is no tile 12", "/tile"));

  protocol::TilePayload moved = p;
  moved.rect.x0 = 0;
  const auto wrong_rect = coll::check_tile(tile_route(3, 5), &job, moved);
  REQUIRE_FALSE(wrong_rect.ok());
  CHECK(wrong_rect.error().error.path == "/rect");
  CHECK(wrong_rect.error().error.message ==
        "the payload's rectangle 8x8 at (0, 8) is not tile 5 of job 3: 8x8 at (8, 8)");

  protocol::TilePayload counted = p;
  counted.spp.assign(64, 4);
  const auto uniform = coll::check_tile(tile_route(3, 5), &job, counted);
  REQUIRE_FALSE(uniform.ok());
  CHECK(uniform.error().error.path == "/spp");
  job.settings.error_target = 0.1;
  job.settings.min_samples = 1;
  CHECK(coll::check_tile(tile_route(3, 5), &job, counted).value() == coll::TileAction::kStore);
  CHECK(coll::check_tile(tile_route(3, 5), &job, p).error().error.path == "/spp");  // adaptive needs counts
}

TEST_CASE("sample counts are checked against the job's settings", "[collector][jobs]") {
  dtraced::scene::RenderSettings s;
  s.samples = 100;
  s.min_samples = 8;
  const dtraced::scene::TileRect rect{10, 20, 2, 1};
  const std::vector<std::uint32_t> good = {8, 100};
  CHECK(coll::check_sample_counts(s, rect, {}).ok());
  const auto uniform = coll::check_sample_counts(s, rect, good);
  REQUIRE_FALSE(uniform.ok());
  CHECK(uniform.error().message.find("uniformly") != std::string::npos);
  CHECK(uniform.error().path == "/spp");
  s.error_target = 0.05;
  CHECK(coll::check_sample_counts(s, rect, {}).error().message.find("no sample counts") != std::string::npos);
  for (const std::uint32_t n : {8u, 16u, 32u, 64u, 100u}) {
    const std::vector<std::uint32_t> counts = {n, 100};
    CHECK(coll::check_sample_counts(s, rect, counts).ok());
  }
  for (const std::uint32_t n : {0u, 1u, 4u, 24u, 128u, 101u}) {
    INFO(n);
    const std::vector<std::uint32_t> counts = {100, n};
    const auto why = coll::check_sample_counts(s, rect, counts);
    REQUIRE_FALSE(why.ok());
    CHECK(why.error().message.find("pixel (11, 20)") != std::string::npos);
  }
}

// ---- submissions: body, row, record ----------------------------------------------------------------

TEST_CASE("a submission becomes a queued row, and a stored row a record, and bad rows are named",
          "[collector][submission]") {
  const std::string body = R"({"scene": {
    "camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 40},
    "render": {"width": 32, "height": 24, "samples": 1, "max_depth": 2, "seed": 7},
    "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"color": [0.8, 0.2, 0.2]}}],
    "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 50}]}, "tile_size": 8, "priority": 2})";
  auto prepared = coll::prepare_job(body);
  REQUIRE(prepared.ok());
  CHECK(prepared->tile_size == 8);
  CHECK(prepared->digest.size() == 64);
  const dtraced::store::StoredJob row = coll::job_row(prepared.value(), 1'700'000'000);
  CHECK(row.state == "queued");
  CHECK(row.priority == 2);
  CHECK(row.output.empty());
  CHECK(row.created_unix == 1'700'000'000);

  dtraced::store::StoredJob stored = row;
  stored.id = 7;
  auto rec = coll::record_from_row(stored);
  REQUIRE(rec.ok());
  CHECK(rec->output == "job-7.png");
  CHECK(rec->tiles_total == 12);
  CHECK(rec->state == protocol::JobState::kQueued);

  stored.state = "suspended";
  CHECK(coll::record_from_row(stored).error().message == "job 7: unknown state 'suspended'");
  stored = row;
  stored.id = 7;
  stored.tile_size = 0;
  CHECK(coll::record_from_row(stored).error().message == "job 7: tile size 0 is out of range");
  stored = row;
  stored.id = 0;
  CHECK(coll::record_from_row(stored).error().message == "job id 0 is out of range");

  auto refused = coll::prepare_job(R"({"tile_size": 8})");
  REQUIRE_FALSE(refused.ok());
  CHECK_FALSE(refused.error().empty());
}

TEST_CASE("tile blobs: floats alone (as stored before counts existed) or floats then counts", "[collector][jobs]") {
  const std::vector<float> rgb = {1, 2, 3, 4, 5, 6};
  const std::vector<std::uint32_t> spp = {7, 65536};
  const dtraced::store::Blob plain = coll::pixels_to_blob(rgb);
  CHECK(plain.size() == 24);
  auto t = coll::blob_to_tile(plain, 2);
  REQUIRE(t);
  CHECK(t->rgb == rgb);
  CHECK(t->spp.empty());
  const dtraced::store::Blob with = coll::pixels_to_blob(rgb, spp);
  CHECK(with.size() == 32);
  t = coll::blob_to_tile(with, 2);
  REQUIRE(t);
  CHECK(t->rgb == rgb);
  CHECK(t->spp == spp);
  for (const std::size_t bad : {0u, 23u, 28u, 33u}) {
    CHECK_FALSE(coll::blob_to_tile(dtraced::store::Blob(bad), 2).has_value());
  }
}
