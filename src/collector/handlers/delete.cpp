// DELETE /v1/jobs/{id}[?image=keep|delete]: forgetting a done or cancelled job.
//
// The job's row, its stored tiles and (when no other job uses it) its scene leave the database in
// one transaction on the store writer; then the freed pages go back to the file system (an
// incremental vacuum and a checkpoint, on the same thread, after the answer's transaction). Only
// then is the job forgotten in memory and, when asked, its image file removed: a crash in between
// leaves the file, never a job without its tiles.
#include <filesystem>
#include <string>
#include <system_error>
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

namespace fs = std::filesystem;

constexpr std::string_view kEnded[] = {store::kJobDone, store::kJobCancelled};

struct Deleted {
  util::Result<store::Deletion> deletion = store::Deletion{};
  std::optional<store::SpaceUse> space;  // after the space was given back; none if that failed
};

Deleted delete_in_store(store::Store& s, JobId id) {
  Deleted out;
  out.deletion = s.delete_job(static_cast<std::int64_t>(id), kEnded);
  if (!out.deletion || !out.deletion.value().deleted) return out;
  // The deletion is committed: a failure here only delays the space (the next checkpoint or
  // deletion gives it back), so it is logged and not answered as a failure.
  if (auto space = s.reclaim_space(); space) {
    out.space = space.value();
  } else {
    util::log_warn("collector: job {} deleted, but its space was not given back yet: {}", id, space.error().message);
  }
  return out;
}

// Removes the finished image files of a deleted job (one, or a sequence's every frame): "deleted"
// when any was there, "none" when none was, or "failed" with the first reason.
protocol::JobDeleted remove_images(const std::vector<std::string>& paths, protocol::JobDeleted answer) {
  bool removed = false;
  for (const std::string& path : paths) {
    std::error_code ec;
    removed = fs::remove(path, ec) || removed;
    if (ec) {
      answer.image = "failed";
      answer.image_error = fmt::format("{}: {}", path, ec.message());
      return answer;
    }
  }
  answer.image = removed ? "deleted" : "none";
  return answer;
}

}  // namespace

async::Awaitable<http::Response> delete_job(Context& c, JobId id, bool delete_image) {
  const JobRecord* job = c.find_job(id);
  if (auto checked = check_delete(id, job, c.accepting_writes()); !checked) co_return respond(checked.error());
  const bool had_image = job->state == protocol::JobState::kDone;
  // A GIF sequence has one file; any other sequence a file per frame (at most scene::kMaxFrames).
  std::vector<std::string> image_paths;
  for (std::uint32_t f = 0; f < job->frames_total; ++f) {
    std::string path = (fs::path(c.output_dir) / frame_output_name(*job, f)).string();
    if (image_paths.empty() || image_paths.back() != path) image_paths.push_back(std::move(path));
  }

  auto remove = [id](store::Store& s) { return delete_in_store(s, id); };
  auto reply = co_await on_writer(*c.writer, std::move(remove));
  if (!reply.ok() || !reply.value->deletion.ok()) {
    ++c.counters.store_busy;
    if (reply.value) {
      util::log_error("collector: job {}: cannot delete: {}", id, reply.value->deletion.error().message);
    }
    co_return respond(busy("the deletion could not be stored; retry later"));
  }
  const store::Deletion& deletion = reply.value->deletion.value();
  if (!deletion.deleted) {
    // Only a requeue that reached the store first gets here.
    co_return respond(wrong_state(id, deletion.state, "only a done or cancelled job can be deleted (cancel it first)"));
  }
  c.queue.remove_job(id);
  c.jobs.erase(id);
  c.job_served.erase(id);

  protocol::JobDeleted answer;
  answer.id = id;
  answer.tiles = deletion.tiles;
  answer.image = had_image ? "kept" : "none";
  if (delete_image && had_image) {
    auto unlink = [paths = std::move(image_paths), answer] { return remove_images(paths, answer); };
    answer = co_await async::on_pool(c.pool, std::move(unlink));
  }
  const auto& space = reply.value->space;
  util::log_info(
      "collector: job {} deleted: {} tile(s){}; image {}{}", id, deletion.tiles,
      deletion.scene_deleted ? " and its scene" : "", answer.image,
      space ? fmt::format("; the database now holds {:.1f} MiB", double(space->pages * space->page_size) / (1 << 20))
            : "");
  if (!answer.image_error.empty()) util::log_warn("collector: job {}: image not removed: {}", id, answer.image_error);
  co_return json_answer(http::Status::ok, protocol::encode(answer));
}

}  // namespace dtraced::collector
