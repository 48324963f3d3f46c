// POST /v1/lease, and the next lease of a tile upload: the next tile to render, or when to ask again.
#include <algorithm>
#include <chrono>
#include <cstdint>
#include <string>
#include <utility>

#include <boost/json/serialize.hpp>
#include <boost/json/string_view.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "collector/handlers.h"
#include "collector/stop.h"
#include "jsonio/write.h"
#include "protocol/worker_messages.h"
#include "scene/scene_json.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// The queue's suggestion, within what the protocol carries (at least 1 ms).
protocol::LeaseReply retry_after(std::chrono::milliseconds suggested) {
  const auto ms = std::min<std::int64_t>(std::max<std::int64_t>(suggested.count(), 1), protocol::kMaxRetryAfterMs);
  return protocol::LeaseReply{protocol::RetryAfter{static_cast<std::uint32_t>(ms)}};
}

// A reply that is not a lease, encoded.
LeaseAnswer answer(protocol::LeaseReply reply, bool finished) {
  std::string text = protocol::encode(reply);
  return LeaseAnswer{std::move(reply), finished, std::move(text)};
}

// A finished collector's answer: "retry after" (all an older worker reads) with kFinishedHeader.
// The longest retry-after, so that a worker without exit_when_done does not hurry back to a
// collector that is going away.
LeaseAnswer finished(Context& c, const http::Request& req, std::string name) {
  linger_told(c, worker_id(req, std::move(name)));
  return answer(retry_after(std::chrono::duration_cast<std::chrono::milliseconds>(c.config.queue.max_retry_after)),
                /*finished=*/true);
}

// How much sooner than the queue's hint an idle worker may ask again: each worker the registry
// knows adds this to the wait, so that all idle workers together ask about 1 / kIdlePollPerWorker
// times a second (200/s, ~1 % of a core at ~30-60 us a lease) while the farm has more than
// min_retry_after / kIdlePollPerWorker workers, and a small farm's idle worker notices a new job
// within tens of milliseconds. The wait stops growing at max_retry_after (--max-idle-wait-ms,
// 5 s by default: reached at 1,000 workers; past that the farm asks more often than 200/s, at
// N / (1.25 x max_retry_after), the price of noticing a new job within 1.5 x max_retry_after).
constexpr std::chrono::milliseconds kIdlePollPerWorker{5};

std::chrono::milliseconds idle_wait(const Context& c, std::chrono::milliseconds queue_hint) {
  const auto floor = std::chrono::duration_cast<std::chrono::milliseconds>(c.config.queue.min_retry_after);
  const auto fair = std::max(floor, kIdlePollPerWorker * static_cast<std::int64_t>(c.workers.size()));
  return std::min(queue_hint, fair);
}

// The lease's settings as text, from the job's cache (JobRecord::lease_settings_text): encoding
// them was a JSON object of a dozen keys built and serialised for every lease.
const std::string& settings_text(JobRecord& job, const scene::RenderSettings& settings) {
  auto& cached = job.lease_settings_text;
  if (!cached || !(cached->settings == settings)) {
    std::string text = jsonio::to_text(boost::json::value(scene::render_settings_object(settings)));
    cached = JobRecord::LeaseSettingsText{settings, std::move(text)};
  }
  return cached->text;
}

// protocol::encode of a LeaseReply holding `lease`, byte for byte (a test compares the two), with
// the settings' text given.
std::string encode_lease(const protocol::Lease& lease, std::string_view settings) {
  return fmt::format(
      R"({{"lease":{{"job":{},"digest":{},"tile":{},"x":{},"y":{},"width":{},"height":{},"settings":{}}}}})", lease.job,
      boost::json::serialize(boost::json::string_view(lease.digest.data(), lease.digest.size())), lease.tile,
      lease.rect.x0, lease.rect.y0, lease.rect.width, lease.rect.height, settings);
}

// The queue's next tile for `who` (recorded as `name`), or when to ask again.
LeaseAnswer pick_tile(Context& c, const Principal& who, const std::string& name) {
  const TimePoint now = c.clock.now();
  // Leases of a worker credential name it, so revoking it re-offers them at once.
  const LeaseResult result = c.queue.lease(now, who.role == Role::kWorker ? std::string_view(who.name) : "");
  JobRecord* job = result.grant ? c.find_job(result.grant->job) : nullptr;
  if (!result.grant || job == nullptr || !job->unfinished()) {
    if (result.grant) {
      util::log_error("collector: the queue leased tile {} of job {}, which is not unfinished", result.grant->tile,
                      result.grant->job);
    }
    ++c.counters.lease_retries;
    return answer(retry_after(idle_wait(c, result.retry_after)), /*finished=*/false);
  }
  const TileIndex tile = result.grant->tile;
  if (!job->restored.empty() && job->restored[tile]) {
    // Impossible by construction (the queue was told these are stored); counted to prove it.
    ++c.counters.restored_tile_leases;
    util::log_error("collector: tile {} of job {} was stored before this start and is being leased again", tile,
                    job->id);
  }
  if (!job->first_lease) job->first_lease = now;
  note_page_lease(*job, tile, name);
  note_job_served(c, job->id);
  if (job->state == protocol::JobState::kQueued) job->state = protocol::JobState::kRendering;
  protocol::Lease lease;
  lease.job = job->id;
  lease.digest = job->digest;
  lease.tile = tile;
  // One frame of the job's range: its number in the settings, its tile's rectangle.
  const TilePlace place = tile_place(*job, tile);
  lease.rect = place.rect;
  lease.settings = frame_settings(job->settings, place.frame_index);
  std::string text = encode_lease(lease, settings_text(*job, lease.settings));
  return LeaseAnswer{protocol::LeaseReply{std::move(lease)}, /*finished=*/false, std::move(text)};
}

}  // namespace

util::Result<LeaseAnswer, Refusal> grant_lease(Context& c, const http::Request& req, const Principal& who,
                                               const protocol::LeaseRequest& request) {
  // A worker credential is its own name, whatever the body says.
  const std::string name = recorded_worker_name(who, request.worker);
  note_lease_request(c, req, name, request);
  // Lingering before the stop: nothing is leased any more (whatever else is queued resumes after
  // a restart), and every worker hears that this collector is going away.
  if (c.linger) return finished(c, req, name);
  // A worker of another pixel version gets no tile: its pixels would not match the others'.
  if (auto refused = pixel_version_refusal(c, req, /*required=*/true)) return std::move(*refused);
  return pick_tile(c, who, name);
}

http::Response lease_answer(const LeaseAnswer& grant) {
  http::Response res = json_answer(http::Status::ok, grant.text.empty() ? protocol::encode(grant.reply) : grant.text);
  if (grant.finished) res.set(protocol::kFinishedHeader, "1");
  return res;
}

http::Response lease_tile(Context& c, const http::Request& req, const Principal& who) {
  auto request = protocol::decode_lease_request(req.body());
  if (!request) return respond(decode_failure(request.error()));
  auto grant = grant_lease(c, req, who, request.value());
  if (!grant) return respond(grant.error());
  return lease_answer(grant.value());
}

}  // namespace dtraced::collector
