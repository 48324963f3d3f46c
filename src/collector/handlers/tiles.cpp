// PUT /v1/jobs/{id}/tiles/{tile}: a worker's result, acknowledged "stored" only once durable; with
// protocol::kNextLeaseHeader, the answer carries the worker's next lease too (after the commit).
#include <bit>
#include <chrono>
#include <optional>
#include <string>
#include <utility>

#include <boost/beast/core/string.hpp>
#include <fmt/format.h>

#include "collector/checks.h"
#include "collector/handlers.h"
#include "collector/lifecycle.h"
#include "collector/writer_bridge.h"
#include "protocol/tile_payload.h"
#include "protocol/worker_messages.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// Tile payloads larger than this are checksummed and checked on the thread pool rather than on
// the loop (SHA-256 of 256 KiB is a fraction of a millisecond; of the largest payload, tens).
constexpr std::size_t kInlinePayloadBytes = 256 << 10;

// The worker's name as it gave it in kWorkerHeader: printable ASCII, bounded; "unknown" if none.
std::string worker_name(const http::Request& req) {
  const auto it = req.find(boost::beast::string_view(kWorkerHeader.data(), kWorkerHeader.size()));
  std::string name;
  if (it != req.end()) {
    for (const char c : it->value()) {
      if (name.size() == protocol::kMaxWorkerNameBytes) break;
      name += (c >= 0x20 && c <= 0x7e) ? c : '?';
    }
  }
  return name.empty() ? std::string("unknown") : name;
}

// check_tile_payload, on the pool for a large body. `body` stays the caller's (it may become the
// stored blob); a large one goes to the pool and comes back.
async::Awaitable<util::Result<protocol::TilePayload, Refusal>> checked_payload(Context& c, std::string& body) {
  if (body.size() <= kInlinePayloadBytes) co_return check_tile_payload(body);
  // In an optional: on_pool needs a default-constructible result. The pool owns the body while it
  // reads it, so nothing it reads can go away under it.
  auto check = [owned = std::move(body)]() mutable {
    auto result = check_tile_payload(owned);
    return std::optional(std::pair(std::move(result), std::move(owned)));
  };
  auto checked = *co_await async::on_pool(c.pool, std::move(check));
  body = std::move(checked.second);
  co_return std::move(checked.first);
}

// The tile's blob as the store keeps it (pixels_to_blob's bytes): on a little-endian host these
// are the payload's own bytes between its header and its checksum, so the body itself is stored.
void set_stored_pixels(store::TileWrite& write, const protocol::TilePayload& p, std::string body) {
  const std::size_t bytes = (p.rgb.size() + p.spp.size()) * 4;
  if constexpr (std::endian::native == std::endian::little) {
    if (body.size() == protocol::kTileHeaderBytes + bytes + protocol::kTileChecksumBytes) {
      write.pixels = store::TilePixels(std::move(body), protocol::kTileHeaderBytes, bytes);
      return;
    }
  }
  write.pixels = pixels_to_blob(p.rgb, p.spp);
}

// An upload's outcome: a verdict on the tile (stored, already_done, job_gone), which may carry the
// next lease, or any other answer (a refusal, busy, an error), which never does.
struct Outcome {
  std::optional<protocol::SubmitResult> verdict;
  http::Response other;
};
Outcome verdict(protocol::SubmitResult result) { return Outcome{result, {}}; }
Outcome other(http::Response res) { return Outcome{std::nullopt, std::move(res)}; }

// The lease request a tile upload makes with protocol::kNextLeaseHeader, nullopt without one (or
// with a garbled one, which counts as none).
std::optional<protocol::LeaseRequest> next_lease_request(const http::Request& req, const WorkerId& worker) {
  const auto it =
      req.find(boost::beast::string_view(protocol::kNextLeaseHeader.data(), protocol::kNextLeaseHeader.size()));
  if (it == req.end()) return std::nullopt;
  const auto threads = protocol::parse_next_lease_header(std::string_view(it->value().data(), it->value().size()));
  if (!threads) return std::nullopt;
  return protocol::LeaseRequest{worker.name, *threads};
}

Outcome duplicate(Context& c, bool identical, JobId job, TileIndex tile, const WorkerId& worker) {
  ++c.counters.tile_duplicates;
  note_tile_upload(c, worker, identical ? TileOutcome::kDuplicate : TileOutcome::kFaultyDuplicate, 0);
  if (!identical) {
    ++c.counters.faulty_results;
    util::log_warn("collector: tile {} of job {} from worker '{}' ({}) differs from the stored result: faulty worker?",
                   tile, job, worker.name, peer_text(worker));
  }
  return verdict(protocol::SubmitResult::kAlreadyDone);
}

// Camera rays (one per sample) of a stored tile, for the registry's recent counts.
std::uint64_t tile_rays(const protocol::TilePayload& p, std::uint32_t samples) {
  if (p.spp.empty()) return std::uint64_t{p.rect.width} * p.rect.height * samples;
  std::uint64_t sum = 0;
  for (const std::uint32_t n : p.spp) sum += n;
  return sum;
}

// What the worker says the tile took to render (protocol::kRenderMsHeader), into the histogram.
void observe_render_time(Context& c, const http::Request& req) {
  const auto it =
      req.find(boost::beast::string_view(protocol::kRenderMsHeader.data(), protocol::kRenderMsHeader.size()));
  if (it == req.end()) return;
  const auto ms = protocol::parse_render_ms_header(std::string_view(it->value().data(), it->value().size()));
  if (ms) c.counters.tile_render_seconds.observe(double(*ms) / 1000.0);
}

// The store committed the tile: it leaves the queue (its pixels stay in the store only).
Outcome on_tile_stored(Context& c, JobId id, const protocol::TilePayload& payload, const WorkerId& worker) {
  const CompleteResult completed = c.queue.complete(id, payload.tile, c.clock.now());
  JobRecord* job = c.find_job(id);
  if (completed == CompleteResult::kJobGone || job == nullptr || !job->unfinished()) {
    // Cancelled while the store wrote: the pixels are stored, and nobody wants them.
    ++c.counters.tiles_job_gone;
    note_tile_upload(c, worker, TileOutcome::kJobGone, 0);
    return verdict(protocol::SubmitResult::kJobGone);
  }
  if (completed == CompleteResult::kAlreadyDone) {
    util::log_error("collector: the store stored tile {} of job {}, which the queue had as done", payload.tile, id);
    ++c.counters.tile_duplicates;
    note_tile_upload(c, worker, TileOutcome::kDuplicate, 0);
    return verdict(protocol::SubmitResult::kAlreadyDone);
  }
  note_tile_upload(c, worker, TileOutcome::kStored, tile_rays(payload, job->settings.samples));
  note_job_served(c, id);
  const std::uint32_t frame_index = tile_place(*job, payload.tile).frame_index;
  note_page_stored(*job, payload.tile, worker.name);
  ++job->frame_tiles_done[frame_index];
  count_samples(*job, payload.spp);
  ++job->tiles_done;
  ++job->stored_this_run;
  ++c.counters.tiles_stored;
  if (job->state == protocol::JobState::kQueued) job->state = protocol::JobState::kRendering;
  persist_rendering(c, *job);
  // The next frame to write may be complete now (frames are written in order, each as soon as it
  // and those before it are).
  if (!job->writing && frame_complete(*job, job->frames_written)) start_finish(c, id);
  return verdict(protocol::SubmitResult::kStored);
}

// The store decides (INSERT OR IGNORE: the first result wins, and a duplicate is compared with it).
async::Awaitable<Outcome> store_tile(Context& c, JobId id, const protocol::TilePayload& p, std::string body,
                                     const WorkerId& worker) {
  store::TileWrite write;
  write.job = static_cast<std::int64_t>(id);
  write.tile = p.tile;
  set_stored_pixels(write, p, std::move(body));
  write.worker = fmt::format("epoch={} worker={}", c.epoch, worker.name);
  write.stored_unix = c.clock.unix_seconds();
  auto reply = co_await commit_tile(*c.writer, std::move(write));
  if (reply.status != store::SubmitStatus::kAccepted) {
    ++c.counters.store_busy;
    co_return other(respond(busy("the store's queue is full; retry later")));
  }
  const store::CommitResult& result = *reply.value;
  switch (result.outcome) {
    case store::TileOutcome::kStored:
      co_return on_tile_stored(c, id, p, worker);
    case store::TileOutcome::kAlreadyPresent:
      co_return duplicate(c, result.identical, id, p.tile, worker);
    case store::TileOutcome::kRejected:
      util::log_error("collector: the store refused tile {} of job {}: {}", p.tile, id, result.error);
      co_return other(http::make_error(http::Status::internal_server_error, "the store refused the tile"));
    case store::TileOutcome::kFailed:
      break;
  }
  ++c.counters.store_busy;
  util::log_warn("collector: tile {} of job {} was not stored: {}", p.tile, id, result.error);
  co_return other(respond(busy("the tile could not be stored; retry later")));
}

// The upload's checks and its store round trip. Reads only the body of `req` (moved from); its
// headers stay for the next lease.
async::Awaitable<Outcome> upload(Context& c, const Route& route, http::Request& req, const WorkerId& worker) {
  c.counters.tile_upload_bytes.observe(double(req.body().size()));
  observe_render_time(c, req);
  // A tile leased before an upgrade and rendered by the old renderer must not be stored.
  if (const auto refused = pixel_version_refusal(c, req, /*required=*/false)) {
    note_tile_upload(c, worker, TileOutcome::kRefused, 0);
    co_return other(respond(*refused));
  }
  std::string body = std::move(req.body());
  const util::Result<protocol::TilePayload, Refusal> checked = co_await checked_payload(c, body);
  if (!checked) {
    ++c.counters.tiles_refused;
    note_tile_upload(c, worker, TileOutcome::kRefused, 0);
    co_return other(respond(checked.error()));
  }
  const protocol::TilePayload& p = checked.value();
  JobRecord* job = c.find_job(route.job);
  const auto action = check_tile(route, job, p);
  if (!action) {
    ++c.counters.tiles_refused;
    note_tile_upload(c, worker, TileOutcome::kRefused, 0);
    co_return other(respond(action.error()));
  }
  if (action.value() == TileAction::kJobGone) {
    ++c.counters.tiles_job_gone;
    note_tile_upload(c, worker, TileOutcome::kJobGone, 0);
    co_return verdict(protocol::SubmitResult::kJobGone);
  }
  if (!job->restored.empty() && job->restored[p.tile]) ++c.counters.restored_tile_submissions;
  // The store decides whether it is new, and compares a duplicate with the stored result.
  if (!c.accepting_writes()) co_return other(respond(busy("the collector is stopping; retry later")));
  co_return co_await store_tile(c, route.job, p, std::move(body), worker);
}

}  // namespace

async::Awaitable<http::Response> put_tile(Context& c, Route route, http::Request req, const Principal& who) {
  const WorkerId worker = worker_id(req, who.role == Role::kWorker ? who.name : worker_name(req));
  const std::optional<protocol::LeaseRequest> next = next_lease_request(req, worker);
  Outcome outcome = co_await upload(c, route, req, worker);
  if (!outcome.verdict) co_return std::move(outcome.other);
  if (!next) co_return submit_answer(*outcome.verdict);
  // The verdict is final (a stored tile is durable by now): the next lease, as POST /v1/lease
  // would answer it; none when that would be a refusal (the worker then asks POST /v1/lease).
  ++c.counters.upload_leases;
  const TimePoint start = c.clock.now();
  auto grant = grant_lease(c, req, who, *next);
  std::optional<LeaseAnswer> given;
  if (grant) given = std::move(grant).value();
  http::Response res = upload_answer(*outcome.verdict, given);
  c.counters.lease_seconds.observe(std::chrono::duration<double>(c.clock.now() - start).count());
  co_return res;
}

}  // namespace dtraced::collector
