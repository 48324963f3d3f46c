#include "collector/restore.h"

#include <algorithm>
#include <cassert>
#include <charconv>
#include <filesystem>
#include <functional>
#include <limits>
#include <string>
#include <utility>
#include <vector>

#include <boost/asio/co_spawn.hpp>
#include <fmt/format.h>

#include "collector/lifecycle.h"
#include "collector/stop.h"
#include "collector/submission.h"
#include "scene/load.h"
#include "util/file.h"
#include "util/lock_file.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

namespace fs = std::filesystem;
using protocol::JobState;

// The epoch file holds one decimal number.
constexpr std::uint64_t kMaxEpochFileBytes = 64;

util::Status bump_epoch(Context& c) {
  const std::string path = (fs::path(c.config.state_dir) / kEpochFileName).string();
  std::int64_t previous = 0;
  std::error_code ec;
  if (fs::exists(path, ec)) {
    auto text = util::read_file_limited(path, kMaxEpochFileBytes);
    if (!text) return text.error();
    std::string_view digits = *text;
    while (!digits.empty() && (digits.back() == '\n' || digits.back() == ' ')) digits.remove_suffix(1);
    const auto [end, parse_error] = std::from_chars(digits.data(), digits.data() + digits.size(), previous);
    if (parse_error != std::errc() || end != digits.data() + digits.size() || previous < 0 ||
        previous == std::numeric_limits<std::int64_t>::max()) {
      return util::Error(fmt::format("{}: not a start counter; refusing to start (fix the file or remove it)", path));
    }
  }
  c.epoch = previous + 1;
  // The number only labels what this start stored (the tiles' `worker` column, a metric): when it
  // cannot be written (a full disk), starting anyway loses nothing; the next start may then reuse
  // the number. Refusing to start would keep every stored job from finishing until space frees.
  if (util::Status written = util::write_file_atomic(path, fmt::format("{}\n", c.epoch)); !written) {
    util::log_warn("collector: cannot record start {} (the next start may count it again): {}", c.epoch,
                   written.error().to_string());
  }
  return {};
}

// Temporary files of image (and start counter) writes that a kill interrupted: ours only (the
// names write_file_atomic gives to an output name or the start counter), in our two directories,
// and none a live writer holds. They are as large as the image, and nothing else removes them.
void remove_temporaries(const Context& c) {
  const auto clean = [](const std::string& dir, const std::function<bool(std::string_view)>& ours) {
    const util::TemporaryCleanup cleanup = util::remove_stale_temporaries(dir, ours);
    for (const std::string& path : cleanup.removed) {
      util::log_info("collector: removed {}, left by a write that was interrupted", path);
    }
    for (const util::Error& error : cleanup.failed) util::log_warn("collector: {}", error.to_string());
  };
  clean(c.config.state_dir, [](std::string_view target) { return target == kEpochFileName; });
  clean(c.output_dir, [](std::string_view target) { return protocol::check_output_name(target).ok(); });
}

// One collector per state directory: the lock comes before the database opens, so a second
// collector never reads (or writes) a database the first one is using.
util::Status lock_state_dir(Context& c) {
  const std::string& dir = c.config.state_dir;
  std::error_code ec;
  fs::create_directories(dir, ec);
  if (ec) return util::Error(fmt::format("state directory {}: cannot create it: {}", dir, ec.message()));
  const std::string path = (fs::path(dir) / kLockFileName).string();
  auto locked = util::LockFile::acquire(path);
  if (!locked) {
    const util::LockRefusal& refusal = locked.error();
    if (!refusal.held_by_another) {
      return util::Error(fmt::format("state directory {}: {}", dir, refusal.error.to_string()));
    }
    const std::string holder =
        refusal.holder_pid ? fmt::format("process {}", *refusal.holder_pid) : std::string("another process");
    return util::Error(fmt::format(
        "state directory {} is in use by another collector ({} holds the lock on {}); stop it first, or give this "
        "collector a state directory of its own",
        dir, holder, path));
  }
  c.state_lock.emplace(std::move(locked).value());
  return {};
}

// An unfinished job's scene and stored tiles, into its record and the queue.
util::Status restore_active(Context& c, store::Store& s, const store::StoredJob& row, JobRecord& rec) {
  auto scene_json = s.get_scene(row.digest);
  if (!scene_json) return std::move(scene_json).error();
  if (!scene_json.value()) {
    return util::Error(fmt::format("{}: job {}: its scene {} is missing", s.path(), rec.id, row.digest));
  }
  auto loaded = load_stored_tiles(s, rec);
  if (!loaded) return std::move(loaded).error();
  const std::vector<TileIndex>& stored = loaded.value();
  if (!queue_job(c.queue, rec, stored)) {
    return util::Error(fmt::format("{}: job {}: cannot be queued (duplicate tiles?)", s.path(), rec.id));
  }
  rec.tiles_done = static_cast<TileIndex>(stored.size());
  c.restored_tiles += stored.size();
  rec.state = rec.tiles_done > 0 ? JobState::kRendering : JobState::kQueued;
  if (row.state == store::kJobPaused) {
    // Stays paused across the restart; if every tile is stored it is finished all the same.
    rec.state = JobState::kPaused;
    c.queue.set_paused(rec.id, true);
  }
  rec.rendering_persisted = row.state == store::kJobRendering;
  rec.scene_json = c.intern_scene(row.digest, std::move(*scene_json.value()));
  // Frames complete before the restart are written (again: a file already there with the same
  // bytes counts as written), in order, and the job resumes with the first unfinished one.
  rec.frames_written = 0;
  if (frame_complete(rec, 0)) c.to_finish.push_back(rec.id);
  util::log_info("collector: job {} restored{}: {}/{} tiles stored", rec.id,
                 rec.state == JobState::kPaused ? " (paused)" : "", rec.tiles_done, rec.tiles_total);
  return {};
}

util::Status restore(Context& c, store::Store& s) {
  auto rows = s.list_jobs();
  if (!rows) return std::move(rows).error();
  for (const store::StoredJob& row : rows.value()) {
    auto made = record_from_row(row);
    if (!made) return util::Error(fmt::format("{}: {}", s.path(), made.error().message));
    JobRecord rec = std::move(made).value();
    if (rec.unfinished()) {
      if (auto restored = restore_active(c, s, row, rec); !restored) return restored;
    } else if (rec.state == JobState::kCancelled) {
      // Its status still says how far it got.
      auto count = s.count_tiles(row.id);
      if (!count) return std::move(count).error();
      rec.tiles_done = static_cast<TileIndex>(std::min<std::uint64_t>(count.value(), rec.tiles_total));
    }
    if (!rec.unfinished() && rec.settings.error_target > 0) {
      // Its mean spp needs every stored tile read: done after start-up, off the loop, so that
      // start-up time does not grow with the job history (see restore_sample_counts).
      rec.spp_pending = true;
      c.to_count.push_back(rec.id);
    }
    c.jobs.emplace(rec.id, std::move(rec));
  }
  return {};
}

// The one-shot job stored before with the same arguments, picked up where it was.
util::Status resume_one_shot(Context& c, store::Store& s, const store::StoredJob& row) {
  const JobId id = static_cast<JobId>(row.id);
  c.one_shot_id = id;
  JobRecord* rec = c.find_job(id);
  assert(rec != nullptr);
  if (rec->unfinished()) {
    util::log_info("collector: one-shot job {} resumed: {}/{} tiles stored", id, rec->tiles_done, rec->tiles_total);
  } else if (rec->state == JobState::kCancelled) {
    util::log_error("collector: one-shot job {} was cancelled; nothing to do", id);
    if (c.config.exit_when_done) begin_stop(c, 1);
  } else {
    // A sequence is whole when its every frame is (bounded: at most kMaxFrames names).
    fs::path path;
    std::error_code ec;
    bool present = true;
    for (std::uint32_t f = 0; f < rec->frames_total && present; ++f) {
      path = fs::path(c.output_dir) / frame_output_name(*rec, f);
      present = fs::exists(path, ec);
    }
    if (present) {
      util::log_info("collector: one-shot job {} is done; {} is written", id, path.string());
      if (c.config.exit_when_done) begin_stop(c, 0);
    } else {
      // Done, but the image is gone: assemble it again from the stored tiles.
      util::log_info("collector: one-shot job {} is done but {} is missing; writing it again", id, path.string());
      JobRecord again = *rec;
      again.state = JobState::kRendering;
      if (auto restored = restore_active(c, s, row, again); !restored) return restored;
      *rec = std::move(again);
    }
  }
  return {};
}

util::Status enqueue_one_shot(Context& c, store::Store& s) {
  const OneShotJob& one = *c.config.one_shot;
  scene::LoadResult loaded = scene::load_scene_file(one.scene_path);
  if (!loaded.ok()) return util::Error("scene: " + scene::format_errors(loaded.errors));

  protocol::JobSubmit submit;
  submit.scene = std::move(*loaded.scene);
  submit.output = one.output;
  submit.priority = one.priority;
  submit.overrides = one.overrides;
  // Through the wire format, so a one-shot job meets exactly the checks of a submitted one.
  auto prepared = prepare_job(protocol::encode(submit));
  if (!prepared) {
    const protocol::ErrorBody e = protocol::error_body(prepared.error());
    return util::Error(e.field.empty() ? "one-shot job: " + e.error : "one-shot job: " + e.field + ": " + e.error);
  }
  PreparedJob& p = prepared.value();

  const std::string key = one_shot_client_key(p.digest, job_settings(p), p.tile_size, p.submit.output);
  auto found = s.find_job_by_key(key);
  if (!found) return std::move(found).error();
  if (found.value()) return resume_one_shot(c, s, *found.value());

  store::StoredJob row = job_row(p, c.clock.unix_seconds());
  row.client_key = key;
  auto inserted = insert_scene_and_job(s, row, p.scene_json);
  if (!inserted) return std::move(inserted).error();
  row.id = inserted.value();
  auto made = record_from_row(row);
  if (!made) return std::move(made).error();
  JobRecord rec = std::move(made).value();
  rec.scene_json = c.intern_scene(p.digest, std::move(p.scene_json));
  if (!queue_job(c.queue, rec)) {
    return util::Error(fmt::format("job {}: cannot be queued", rec.id));
  }
  c.one_shot_id = rec.id;
  util::log_info("collector: one-shot job {} enqueued: {} -> {} ({}x{}, {} samples, {} tiles)", rec.id, one.scene_path,
                 rec.output, rec.settings.width, rec.settings.height, rec.settings.samples, rec.tiles_total);
  c.jobs.emplace(rec.id, std::move(rec));
  return {};
}

// Fills in a finished adaptive job's mean spp after start-up; until then its status reports the
// mean as unknown. A tile that cannot be read leaves it unknown for good (logged).
async::Awaitable<> restore_sample_counts(Context& c, JobId id) {
  const JobRecord* job = c.find_job(id);
  if (job == nullptr || c.stopping) co_return;
  // In an optional: on_pool needs a default-constructible result.
  auto read = [&reader = c.reader, id, settings = job->settings, tile_size = job->tile_size,
               total = job->tile_indices] {
    return std::optional(reader.sample_counts(id, settings, tile_size, total));
  };
  const std::optional<util::Result<SampleTally>> counted = co_await async::on_pool(c.pool, std::move(read));
  JobRecord* rec = c.find_job(id);
  if (rec == nullptr) co_return;
  rec->spp_pending = false;
  if (counted->ok()) {
    rec->spp.add(counted->value());
  } else {
    rec->spp.known = false;
  }
  if (!rec->spp.known) {
    util::log_warn(
        "collector: job {}: mean spp unknown: {}", id,
        counted->ok() ? std::string("a stored tile's sample counts do not parse") : counted->error().message);
  }
}

// Every credential, revoked ones too (a revoked token keeps getting "revoked").
util::Status load_credentials(Context& c, store::Store& s) {
  auto rows = s.list_credentials();
  if (!rows) return std::move(rows).error();
  for (store::StoredCredential& row : rows.value()) {
    const std::optional<Role> role = credential_role(row.role);
    util::Sha256Digest digest{};
    if (!role || row.token_sha256.size() != digest.size()) {
      return util::Error(
          fmt::format("{}: credential '{}' has role '{}' or a token digest of {} bytes; expected "
                      "viewer, client or worker and {} bytes",
                      s.path(), row.name, row.role, row.token_sha256.size(), digest.size()));
    }
    std::copy(row.token_sha256.begin(), row.token_sha256.end(), digest.begin());
    if (!c.credentials.add(Credential{std::move(row.name), *role, row.created_unix, row.revoked_unix}, digest)) {
      return util::Error(fmt::format("{}: two credentials share a token digest", s.path()));
    }
  }
  return {};
}

}  // namespace

util::Status open_collector(Context& c) {
  if (c.opened) return util::Error("the collector is already open");
  if (!c.state_lock) {
    if (auto locked = lock_state_dir(c); !locked) return locked;
  }
  auto opened = store::Store::open(c.config.state_dir);
  if (!opened) return std::move(opened).error();
  store::Store s = std::move(opened).value();

  c.output_dir = c.config.effective_output_dir();
  std::error_code ec;
  fs::create_directories(c.output_dir, ec);
  if (ec) {
    return util::Error(fmt::format("output directory {}: cannot create it: {}", c.output_dir, ec.message()));
  }

  remove_temporaries(c);
  if (auto bumped = bump_epoch(c); !bumped) return bumped;
  if (auto restored = restore(c, s); !restored) return restored;
  if (auto loaded = load_credentials(c, s); !loaded) return loaded;
  if (c.config.one_shot) {
    if (auto enqueued = enqueue_one_shot(c, s); !enqueued) return enqueued;
  }

  c.writer = std::make_unique<store::TileWriter>(std::move(s), c.config.writer);
  c.opened = true;
  for (const JobId id : c.to_finish) start_finish(c, id);
  c.to_finish.clear();
  for (const JobId id : c.to_count) {
    async::net::co_spawn(*c.ioc, restore_sample_counts(c, id),
                         async::log_failure(fmt::format("collector: reading the sample counts of job {}", id)));
  }
  c.to_count.clear();
  util::log_info("collector: start {} on {}; {} unfinished job(s), {} tile(s) already stored, {} credential(s)",
                 c.epoch, c.config.state_dir, c.unfinished_jobs(), c.restored_tiles, c.credentials.size());
  return {};
}

}  // namespace dtraced::collector
