// POST /v1/jobs/{id}/priority, .../requeue, .../pause, .../resume: changing a job after its
// submission.
// Each change is stored (through the store writer, in order with every other write) before it is
// applied in memory and answered, so an answered change survives a restart.
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "collector/handlers.h"
#include "collector/lifecycle.h"
#include "collector/manage_checks.h"
#include "collector/writer_bridge.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// What the store writer read back for a requeued job.
struct Requeued {
  util::Status status;                       // the change and the reads; an error is logged, answered 503
  std::optional<std::string> refused_state;  // the job's stored state when the change was refused
  std::optional<std::string> scene_json;
  JobRecord record;  // the per-frame counts, sample tally and restored flags from the stored tiles
  std::vector<TileIndex> stored;
};

// On the writer's thread: cancelled -> queued (compare-and-set), then the job's scene and stored
// tiles read back, all before the answer.
Requeued requeue_in_store(store::Store& s, JobRecord rec) {
  Requeued out;
  auto changed = record_state(s, rec.id, StateWrite::kRequeued, /*when=*/0);
  if (!changed) {
    out.status = std::move(changed).error();
    return out;
  }
  if (!changed.value().changed) {
    out.refused_state = changed.value().state;
    return out;
  }
  auto scene_json = s.get_scene(rec.digest);
  if (!scene_json || !scene_json.value()) {
    out.status = scene_json
                     ? util::Error(fmt::format("{}: job {}: its scene {} is missing", s.path(), rec.id, rec.digest))
                     : std::move(scene_json).error();
    return out;
  }
  out.scene_json = std::move(*scene_json.value());
  auto stored = load_stored_tiles(s, rec);
  if (!stored) {
    out.status = std::move(stored).error();
    return out;
  }
  out.stored = std::move(stored).value();
  out.record = std::move(rec);
  return out;
}

Load load_now(const Context& c) { return Load{c.unfinished_jobs(), c.unfinished_pixels(), c.accepting_writes()}; }

// What pause and resume share: the check (a repeat is answered with the job's status), the
// compare-and-set in the store through the writer, and the store's state when it was not changed.
// nullopt when the change is recorded and the job still known: the caller applies it in memory.
async::Awaitable<std::optional<http::Response>> record_pause(Context& c, JobId id, StateWrite write) {
  const bool pause = write == StateWrite::kPaused;
  auto checked = pause ? check_pause(id, c.find_job(id), c.accepting_writes())
                       : check_resume(id, c.find_job(id), c.accepting_writes());
  if (!checked) co_return respond(checked.error());
  if (checked.value() == ChangeAction::kAlready) co_return get_job(c, id);
  auto record = [id, write](store::Store& s) { return record_state(s, id, write, /*when=*/0); };
  auto reply = co_await on_writer(*c.writer, std::move(record));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: job {}: cannot record the {}: {}", id, pause ? "pause" : "resumption",
                      reply.value->error().message);
    }
    co_return respond(busy(fmt::format("the {} could not be stored; retry later", pause ? "pause" : "resumption")));
  }
  const store::StateChange& change = reply.value->value();
  if (change.changed || change.state == target_state(write)) {
    if (c.find_job(id) == nullptr) co_return respond(job_not_found(id));
    co_return std::nullopt;
  }
  // Finished while the store worked (the last tiles out were stored): the store's state wins.
  co_return respond(wrong_state(
      id, change.state, pause ? "only a queued or rendering job can be paused" : "only a paused job can be resumed"));
}

}  // namespace

async::Awaitable<http::Response> set_job_priority(Context& c, JobId id, http::Request req) {
  auto decoded = protocol::decode_job_priority(req.body());
  if (!decoded.ok()) co_return respond(decode_failure(decoded.error()));
  if (auto checked = check_priority(id, c.find_job(id), c.accepting_writes()); !checked) {
    co_return respond(checked.error());
  }
  const std::int32_t priority = decoded.value().priority;
  auto record = [id, priority](store::Store& s) { return s.set_job_priority(static_cast<std::int64_t>(id), priority); };
  auto reply = co_await on_writer(*c.writer, std::move(record));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: job {}: cannot record its priority: {}", id, reply.value->error().message);
    }
    co_return respond(busy("the priority could not be stored; retry later"));
  }
  JobRecord* job = c.find_job(id);
  if (job == nullptr) co_return respond(job_not_found(id));
  job->priority = priority;
  c.queue.set_priority(id, priority);  // a finished or cancelled job is out of the order anyway
  util::log_info("collector: job {}: priority {}", id, priority);
  co_return get_job(c, id);
}

async::Awaitable<http::Response> requeue_job(Context& c, JobId id) {
  const JobRecord* job = c.find_job(id);
  if (auto checked = check_requeue(id, job, load_now(c), c.config); !checked) co_return respond(checked.error());
  // Cancelled while a frame of it was being written: that write ends first.
  if (job->writing) co_return respond(busy("a frame of the job is still being written; retry shortly"));
  // A copy without the counts of its stored tiles (a cancelled job has released them): the writer
  // counts them again.
  JobRecord copy = *job;
  copy.tile_seq = {};  // given again to the stored tiles, after last_seq
  copy.spp = {};       // counted again from the stored tiles
  copy.spp_pending = false;
  auto requeue = [copy = std::move(copy)](store::Store& s) mutable { return requeue_in_store(s, std::move(copy)); };
  auto reply = co_await on_writer(*c.writer, std::move(requeue));
  if (!reply.ok() || !reply.value->status.ok()) {
    ++c.counters.store_busy;
    if (reply.value) {
      util::log_error("collector: job {}: cannot requeue: {}", id, reply.value->status.error().message);
    }
    co_return respond(busy("the requeue could not be stored; retry later"));
  }
  Requeued& done = *reply.value;
  if (done.refused_state)
    co_return respond(wrong_state(id, *done.refused_state, "only a cancelled job can be requeued"));

  JobRecord* rec = c.find_job(id);
  if (rec == nullptr) co_return respond(job_not_found(id));
  const std::int32_t priority = rec->priority;  // a priority set while the store worked wins
  *rec = std::move(done.record);
  rec->priority = priority;
  rec->tiles_done = static_cast<TileIndex>(done.stored.size());
  rec->state = rec->tiles_done > 0 ? protocol::JobState::kRendering : protocol::JobState::kQueued;
  rec->finished_unix = 0;
  rec->finish_failed = false;
  rec->writing = rec->finishing = false;
  rec->frames_written = 0;           // complete frames are written again (same bytes: already written)
  rec->rendering_persisted = false;  // the store says "queued" now
  rec->scene_json = c.intern_scene(rec->digest, std::move(*done.scene_json));
  c.queue.remove_job(id);
  if (!queue_job(c.queue, *rec, done.stored)) {
    util::log_error("collector: job {} could not be queued again", id);
    co_return http::make_error(http::Status::internal_server_error, "the job could not be queued");
  }
  util::log_info("collector: job {} requeued: {}/{} tiles stored", id, rec->tiles_done, rec->tiles_total);
  if (frame_complete(*rec, 0)) start_finish(c, id);
  co_return get_job(c, id);
}

async::Awaitable<http::Response> pause_job(Context& c, JobId id) {
  if (auto answered = co_await record_pause(c, id, StateWrite::kPaused)) co_return std::move(*answered);
  JobRecord* job = c.find_job(id);
  // Tiles out now are still accepted, and may finish the job: then it is done, not paused.
  if (job->unfinished() && !job->finishing && job->state != protocol::JobState::kPaused) {
    job->state = protocol::JobState::kPaused;
    c.queue.set_paused(id, true);
    const auto out = c.queue.progress(id, c.clock.now());
    util::log_info("collector: job {} paused at {}/{} tiles; {} lease(s) still out are accepted", id, job->tiles_done,
                   job->tiles_total, out ? out->leases_outstanding : 0);
  }
  co_return get_job(c, id);
}

async::Awaitable<http::Response> resume_job(Context& c, JobId id) {
  if (auto answered = co_await record_pause(c, id, StateWrite::kResumed)) co_return std::move(*answered);
  JobRecord* job = c.find_job(id);
  if (job->state == protocol::JobState::kPaused && !job->finishing) {
    job->state = job->tiles_done > 0 ? protocol::JobState::kRendering : protocol::JobState::kQueued;
    job->rendering_persisted = false;  // the store says "queued" now
    // The ETA and the no-worker gap count from now, not across the pause.
    job->first_lease.reset();
    job->stored_this_run = 0;
    note_job_served(c, id);
    c.queue.set_paused(id, false);
    util::log_info("collector: job {} resumed at {}/{} tiles", id, job->tiles_done, job->tiles_total);
  }
  co_return get_job(c, id);
}

}  // namespace dtraced::collector
