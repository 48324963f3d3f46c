#include "collector/lifecycle.h"

#include <cassert>
#include <filesystem>
#include <memory>
#include <string>
#include <utility>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <fmt/format.h>

#include "collector/output_files.h"
#include "collector/stop.h"
#include "collector/writer_bridge.h"
#include "image/image_io.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

namespace net = async::net;
namespace fs = std::filesystem;

void finish_ended(Context& c) {
  assert(c.finishes_in_flight > 0);
  --c.finishes_in_flight;
  if (c.stopping && c.finish_ended_event != nullptr) c.finish_ended_event->set();
}

// Starts the images whose write failed again, once, after kFinishRetryDelay; a stop ends the wait.
async::Awaitable<> retry_finishes(Context& c) {
  co_await async::sleep_for(c.clock, kFinishRetryDelay, &*c.stop_begun);
  c.retry_armed = false;
  if (c.stopping) co_return;
  for (auto& [id, job] : c.jobs) {
    if (job.unfinished() && job.finish_failed && !job.writing) start_finish(c, id);
  }
}

void arm_finish_retry(Context& c) {
  if (c.retry_armed || c.stopping) return;
  c.retry_armed = true;
  net::co_spawn(*c.ioc, retry_finishes(c), async::log_failure("collector: retrying image writes"));
}

struct Written {
  bool ok = false;
  std::string error;
};

// After a write on the pool: the job, or null when it was cancelled or deleted meanwhile (then
// nothing more is written, and the run ends).
JobRecord* still_unfinished(Context& c, JobId id) {
  JobRecord* job = c.find_job(id);
  if (job != nullptr && job->unfinished()) return job;
  if (job != nullptr) job->writing = job->finishing = false;
  finish_ended(c);
  return nullptr;
}

// A failed write: logged, and tried again after kFinishRetryDelay; the run ends.
void write_failed(Context& c, JobRecord& job, const std::string& error) {
  ++c.counters.image_write_failures;
  util::log_error("collector: job {}: cannot write its image: {}; trying again in {} s", job.id, error,
                  kFinishRetryDelay.count());
  job.writing = job.finishing = false;
  job.finish_failed = true;
  finish_ended(c);
  arm_finish_retry(c);
}

// Writes the frame's image under its file name (a GIF sequence's frames have none: they are
// only counted, the pixels being in the store); false when the run must end.
async::Awaitable<bool> write_frame(Context& c, JobId id, std::uint32_t frame_index) {
  JobRecord* job = c.find_job(id);
  if (!is_gif_sequence(*job)) {
    const std::string path = (fs::path(c.output_dir) / frame_output_name(*job, frame_index)).string();
    const image::WriteOptions options{.png_bit_depth = static_cast<int>(job->png_bit_depth),
                                      .display = job->settings.display};
    // The frame's pixels from the store, one tile at a time, on the pool: the collector keeps no
    // framebuffer. Every tile of the frame is committed before frame_complete says so.
    auto write = [&reader = c.reader, id, settings = job->settings, tile_size = job->tile_size, crop = job->crop,
                  frame_index, path, options] {
      Written w;
      util::Result<HeldImage> held = reader.frame_image(id, settings, tile_size, crop, frame_index);
      const util::Status st = held ? write_output_image(path, held.value().image, options) : util::Status(held.error());
      w.ok = st.ok();
      if (!st) w.error = st.error().to_string();
      return w;
    };
    const Written written = co_await async::on_pool(c.pool, std::move(write));
    job = still_unfinished(c, id);
    if (job == nullptr) co_return false;
    if (!written.ok) {
      write_failed(c, *job, written.error);
      co_return false;
    }
    ++c.counters.images_written;
    if (job->frames_total > 1) {
      util::log_info("collector: job {}: frame {} written ({}/{}): {}", id,
                     protocol::frame_number(job->settings, frame_index), frame_index + 1, job->frames_total, path);
    }
  }
  ++job->frames_written;
  co_return true;
}

// A GIF sequence's file, once every frame is complete: assembled from the store on the pool.
async::Awaitable<bool> write_gif(Context& c, JobId id) {
  const JobRecord* job = c.find_job(id);
  const GifJob gif{id, job->settings, job->tile_size, job->frames_total, job->crop};
  const std::string path = (fs::path(c.output_dir) / job->output).string();
  auto write = [&reader = c.reader, gif, path] {
    Written w;
    util::Result<std::string> bytes = sequence_gif(reader, gif);
    const util::Status st = bytes ? write_output_file(path, *bytes) : util::Status(bytes.error());
    w.ok = st.ok();
    if (!st) w.error = st.error().to_string();
    return w;
  };
  const Written written = co_await async::on_pool(c.pool, std::move(write));
  JobRecord* rec = still_unfinished(c, id);
  if (rec == nullptr) co_return false;
  if (!written.ok) {
    write_failed(c, *rec, written.error);
    co_return false;
  }
  ++c.counters.images_written;
  co_return true;
}

// Writes every complete frame in order, from the first one not written; the job is done once
// the last one is. Tiles stored meanwhile complete later frames, which this loop picks up.
async::Awaitable<> finish_job(Context& c, JobId id) {
  for (;;) {
    JobRecord* job = c.find_job(id);
    if (job->frames_written == job->frames_total) break;
    if (!frame_complete(*job, job->frames_written)) {
      job->writing = job->finishing = false;
      finish_ended(c);
      co_return;
    }
    // Writing the last frame finishes the job: from here on it counts as done (no cancel).
    job->finishing = job->frames_written + 1 == job->frames_total;
    if (!co_await write_frame(c, id, job->frames_written)) co_return;
  }
  if (is_gif_sequence(*c.find_job(id)) && !co_await write_gif(c, id)) co_return;
  JobRecord* job = c.find_job(id);
  const std::string path = (fs::path(c.output_dir) / job->output).string();
  const std::int64_t when = c.clock.unix_seconds();
  if (c.writer) {
    auto mark_done = [id, when](store::Store& s) { return record_state(s, id, StateWrite::kDone, when); };
    auto reply = co_await on_writer(*c.writer, std::move(mark_done));
    if (!reply.ok() || !reply.value->ok()) {
      util::log_warn(
          "collector: job {}: the image is written but the store did not record it as done ({}); a "
          "restart writes it again",
          id, reply.value ? reply.value->error().message : std::string("store unavailable"));
    } else if (!reply.value->value().changed) {
      util::log_warn("collector: job {}: the image is written but the store has the job as {}", id,
                     reply.value->value().state);
    }
  }
  job = c.find_job(id);
  job->state = protocol::JobState::kDone;
  job->finished_unix = when;
  job->writing = job->finishing = false;
  job->tiles_done = job->tiles_total;
  release(*job);
  c.queue.remove_job(id);
  if (job->frames_total > 1) {
    util::log_info("collector: job {} done: {} frames written as {}", id, job->frames_total, path);
  } else {
    util::log_info("collector: job {} done: {} written", id, path);
  }
  finish_ended(c);
  if (c.one_shot_id == id && c.config.exit_when_done) begin_linger(c, 0);
}

}  // namespace

std::string_view target_state(StateWrite write) {
  switch (write) {
    case StateWrite::kRendering:
      return store::kJobRendering;
    case StateWrite::kCancelled:
      return store::kJobCancelled;
    case StateWrite::kDone:
      return store::kJobDone;
    case StateWrite::kRequeued:
    case StateWrite::kResumed:
      return store::kJobQueued;
    case StateWrite::kPaused:
      return store::kJobPaused;
  }
  return store::kJobQueued;
}

std::span<const std::string_view> source_states(StateWrite write) {
  static constexpr std::string_view kFromQueued[] = {store::kJobQueued};
  static constexpr std::string_view kFromRunnable[] = {store::kJobQueued, store::kJobRendering};
  static constexpr std::string_view kFromUnfinished[] = {store::kJobQueued, store::kJobRendering, store::kJobPaused};
  static constexpr std::string_view kFromUnfinishedOrCancelled[] = {store::kJobQueued, store::kJobRendering,
                                                                    store::kJobPaused, store::kJobCancelled};
  static constexpr std::string_view kFromCancelled[] = {store::kJobCancelled};
  static constexpr std::string_view kFromPaused[] = {store::kJobPaused};
  switch (write) {
    case StateWrite::kRendering:
      return kFromQueued;
    case StateWrite::kCancelled:
      return kFromUnfinished;
    case StateWrite::kDone:
      return kFromUnfinishedOrCancelled;
    case StateWrite::kRequeued:
      return kFromCancelled;
    case StateWrite::kPaused:
      return kFromRunnable;
    case StateWrite::kResumed:
      return kFromPaused;
  }
  return {};
}

util::Result<store::StateChange> record_state(store::Store& s, JobId id, StateWrite write, std::int64_t when) {
  return s.change_job_state(static_cast<std::int64_t>(id), source_states(write), target_state(write), when);
}

void persist_rendering(Context& c, JobRecord& job) {
  if (job.rendering_persisted || !c.writer) return;
  // Informational (a restart derives the state from the stored tiles), so not awaited; but the
  // loop counts it as outstanding work until the store thread has run it, so a test that runs
  // the loop until idle sees the state written.
  const auto id = static_cast<std::int64_t>(job.id);
  auto pending = std::make_shared<net::executor_work_guard<net::io_context::executor_type>>(c.ioc->get_executor());
  const store::SubmitStatus status = c.writer->post([id, pending](store::Store& s) {
    // A cancellation committed first stays: the compare-and-set leaves any state but "queued".
    if (auto changed = record_state(s, static_cast<JobId>(id), StateWrite::kRendering, 0); !changed) {
      util::log_warn("collector: job {}: cannot record the rendering state: {}", id, changed.error().message);
    }
  });
  job.rendering_persisted = status == store::SubmitStatus::kAccepted;
}

void start_finish(Context& c, JobId id) {
  JobRecord* job = c.find_job(id);
  assert(job != nullptr && job->unfinished() && !job->writing);
  job->writing = true;
  // Finishing: the last frame's write (or, for a GIF sequence, the file's) is what runs now.
  job->finishing = job->frames_written == job->frames_total ||
                   (job->frames_written + 1 == job->frames_total && frame_complete(*job, job->frames_written));
  job->finish_failed = false;
  ++c.finishes_in_flight;
  net::co_spawn(*c.ioc, finish_job(c, id),
                async::log_failure(fmt::format("collector: writing the image of job {}", id)));
}

void apply_cancel(Context& c, JobRecord& job, std::int64_t when) {
  c.queue.cancel(job.id);
  job.state = protocol::JobState::kCancelled;
  job.finished_unix = when;
  release(job);
  ++c.counters.jobs_cancelled;
  util::log_info("collector: job {} cancelled", job.id);
  if (c.one_shot_id == job.id && c.config.exit_when_done) begin_linger(c, 1);
}

void release(JobRecord& job) {
  job.scene_json.reset();
  job.restored = {};
  job.tile_seq = {};
  job.tile_worker = {};
  job.worker_names = {};
  job.leased_by = {};
}

}  // namespace dtraced::collector
