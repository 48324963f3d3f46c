// POST /v1/jobs, GET /v1/jobs[?state=S&limit=N], GET /v1/jobs/{id}, POST /v1/jobs/{id}/cancel.
#include <algorithm>
#include <memory>
#include <string>
#include <utility>

#include <fmt/format.h>

#include "collector/checks.h"
#include "collector/handlers.h"
#include "collector/lifecycle.h"
#include "collector/output_files.h"
#include "collector/submission.h"
#include "collector/writer_bridge.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// The stored row becomes a queued job in memory.
http::Response enqueue_submitted(Context& c, store::StoredJob row, std::shared_ptr<const std::string> scene_json) {
  auto made = record_from_row(row);
  if (!made) {
    util::log_error("collector: {}", made.error().message);
    return http::make_error(http::Status::internal_server_error, "the stored job is unusable");
  }
  JobRecord rec = std::move(made).value();
  rec.scene_json = std::move(scene_json);
  if (!queue_job(c.queue, rec)) {
    util::log_error("collector: job {} could not be queued", rec.id);
    return http::make_error(http::Status::internal_server_error, "the job could not be queued");
  }
  ++c.counters.jobs_submitted;
  const std::string crop =
      rec.crop ? fmt::format(" (crop {}x{} at {},{})", rec.crop->width, rec.crop->height, rec.crop->x0, rec.crop->y0)
               : std::string();
  util::log_info("collector: job {} submitted: {}x{}{}, {} samples, {} tiles of {}, priority {}, -> {}", rec.id,
                 rec.settings.width, rec.settings.height, crop, rec.settings.samples, rec.tiles_total, rec.tile_size,
                 rec.priority, rec.output);
  const protocol::JobCreated created{rec.id, rec.digest};
  c.jobs.emplace(rec.id, std::move(rec));
  return json_answer(http::Status::created, protocol::encode(created));
}

Load load_of(const Context& c) { return Load{c.unfinished_jobs(), c.unfinished_pixels(), c.accepting_writes()}; }

}  // namespace

async::Awaitable<http::Response> submit_job(Context& c, http::Request req) {
  if (auto slots = check_job_slots(load_of(c), c.config); !slots) co_return respond(slots.error());
  // In an optional: on_pool needs a default-constructible result.
  auto prepare = [body = std::move(req.body())] { return std::optional(prepare_job(body)); };
  std::optional<util::Result<PreparedJob, util::Errors>> prepared = co_await async::on_pool(c.pool, std::move(prepare));
  if (!prepared->ok()) co_return respond(decode_failure(prepared->error()));
  PreparedJob& p = prepared->value();
  if (auto room = check_job_room(p.settings.width, p.settings.height, load_of(c), c.config); !room) {
    co_return respond(room.error());
  }
  if (auto free = check_output_free(p.submit.output, c.jobs, c.output_dir); !free) co_return respond(free.error());

  // Durable first: the job and its scene are stored (one transaction) before the 201.
  store::StoredJob row = job_row(p, c.clock.unix_seconds());
  std::shared_ptr<const std::string> scene_json = c.intern_scene(p.digest, std::move(p.scene_json));
  auto insert = [row, scene_json](store::Store& s) { return insert_scene_and_job(s, row, *scene_json); };
  auto reply = co_await on_writer(*c.writer, std::move(insert));
  if (reply.status != store::SubmitStatus::kAccepted) {
    ++c.counters.store_busy;
    co_return respond(busy("the store is busy; retry later"));
  }
  if (!reply.value || !reply.value->ok()) {
    ++c.counters.store_busy;
    const std::string why = reply.value ? reply.value->error().message : std::string("the store task failed");
    util::log_error("collector: a job could not be stored: {}", why);
    co_return respond(busy("the job could not be stored; retry later"));
  }
  row.id = reply.value->value();
  co_return enqueue_submitted(c, std::move(row), std::move(scene_json));
}

http::Response list_jobs(const Context& c, const Route& route) {
  protocol::JobList list;
  const std::int64_t unix_now = c.clock.unix_seconds();
  const TimePoint now = c.clock.now();
  const std::size_t limit = std::min(route.list_limit, protocol::kMaxListedJobs);
  // The newest ones when there are more than the limit.
  for (auto it = c.jobs.rbegin(); it != c.jobs.rend() && list.jobs.size() < limit; ++it) {
    protocol::JobStatus status = job_status(it->second, unix_now, now);
    if (route.list_state && status.state != *route.list_state) continue;
    list.jobs.push_back(with_worker_gap(c, std::move(status)));
  }
  std::reverse(list.jobs.begin(), list.jobs.end());
  return json_answer(http::Status::ok, protocol::encode(list));
}

http::Response get_job(const Context& c, JobId id) {
  const JobRecord* job = c.find_job(id);
  if (job == nullptr) return respond(job_not_found(id));
  return json_answer(http::Status::ok,
                     protocol::encode(with_worker_gap(c, job_status(*job, c.clock.unix_seconds(), c.clock.now()))));
}

async::Awaitable<http::Response> cancel_job(Context& c, JobId id) {
  auto checked = check_cancel(id, c.find_job(id), c.accepting_writes());
  if (!checked) co_return respond(checked.error());
  if (checked.value() == CancelAction::kAlreadyCancelled) co_return get_job(c, id);

  // Durable first: a cancellation that is answered must survive a crash.
  const std::int64_t when = c.clock.unix_seconds();
  auto record = [id, when](store::Store& s) { return record_state(s, id, StateWrite::kCancelled, when); };
  auto reply = co_await on_writer(*c.writer, std::move(record));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: job {}: cannot record the cancellation: {}", id, reply.value->error().message);
    }
    co_return respond(busy("the cancellation could not be stored; retry later"));
  }
  if (const store::StateChange& change = reply.value->value();
      !change.changed && change.state != store::kJobCancelled) {
    // The store's state wins over memory's: only a store that was changed behind our back gets here.
    util::log_error("collector: job {}: the store has it as {}; the cancellation was not recorded", id, change.state);
    co_return respond(Refusal{
        http::Status::conflict, util::Error(fmt::format("job {} is {}; nothing to cancel", id, change.state)), {}});
  }
  JobRecord* job = c.find_job(id);
  // While the store wrote, the last tile may have arrived: then the job finishes after all, and
  // its "done" reaches the store after this "cancelled".
  if (job->unfinished() && !job->finishing) apply_cancel(c, *job, when);
  co_return get_job(c, id);
}

}  // namespace dtraced::collector
