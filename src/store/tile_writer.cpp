#include "store/tile_writer.h"

#include <pthread.h>

#include <algorithm>
#include <cassert>
#include <chrono>
#include <exception>
#include <string_view>
#include <utility>

#include "util/log.h"

namespace dtraced::store {

namespace {

// Callbacks and tasks belong to the caller; one that throws must not take the writer down.
template <typename F>
void call_guarded(std::string_view what, F&& f) {
  try {
    std::forward<F>(f)();
  } catch (const std::exception& e) {
    util::log_error("store writer: a {} threw: {}", what, e.what());
  } catch (...) {
    util::log_error("store writer: a {} threw a non-standard exception", what);
  }
}

// The counter of each TileOutcome, in the enum's order.
constexpr std::uint64_t WriterStats::*kOutcomeCounters[] = {&WriterStats::tiles_stored,
                                                            &WriterStats::tiles_already_present,
                                                            &WriterStats::tiles_rejected, &WriterStats::tiles_failed};

// A finished background checkpoint leaves the frames committed while it ran. When they are at most
// this fraction of the bound (1 MiB of 16), the writer copies them itself; the wait is short (a
// few dozen pages and two fsyncs) and lets the WAL start over. More, and another background
// checkpoint copies them first.
constexpr std::uint64_t kCatchUpFraction = 16;

// Names the calling thread, so that top, perf and /proc tell the writer's threads apart from the
// event loop's (at most 15 characters; a failure only loses the name).
void name_thread(const char* name) { ::pthread_setname_np(::pthread_self(), name); }

}  // namespace

TileWriter::TileWriter(Store store, WriterLimits limits) : store_(std::move(store)), limits_(limits) {
  // Pixel files of jobs whose delete_job committed but whose unlink a crash prevented.
  if (auto removed = store_.remove_orphan_pixel_files(); !removed) {
    util::log_warn("store writer: {} (pixel files of deleted jobs stay)", removed.error().message);
  }
  // Without the hook SQLite keeps checkpointing inside COMMIT (every 4 MiB): slower, still bounded.
  if (auto st = store_.manage_checkpoints(); !st) {
    util::log_warn("store writer: {} (SQLite's own checkpoints stay on)", st.error().message);
  }
  if (auto connection = store_.open_checkpoint_connection(); connection) {
    background_ = true;
    checkpointer_ = std::thread([this, c = std::move(connection).value()]() mutable { run_checkpoints(c); });
  } else {
    // Still bounded: the writer checkpoints on its own connection when the WAL reaches its bound.
    util::log_warn("store writer: {} (checkpoints run on the writer thread; commits wait for them)",
                   connection.error().message);
  }
  thread_ = std::thread([this] { run(); });
}

TileWriter::~TileWriter() { stop(); }

SubmitStatus TileWriter::submit(TileWrite write, Done done) {
  assert(done);
  const std::uint64_t bytes = cost_bytes(write);
  bool wake = false;
  {
    std::lock_guard lock(mu_);
    if (stopping_) return SubmitStatus::kStopped;
    if (bytes > limits_.max_pending_bytes) {
      ++stats_.busy_refusals;
      return SubmitStatus::kTooLarge;
    }
    if (stats_.pending_tiles >= limits_.max_pending_tiles || stats_.pending_bytes + bytes > limits_.max_pending_bytes) {
      ++stats_.busy_refusals;
      return SubmitStatus::kBusy;
    }
    ++stats_.pending_tiles;
    stats_.pending_bytes += bytes;
    queue_.push_back(Item{std::move(write), std::move(done), {}});
    // A writer gathering a batch wakes once, when it is complete, not once per tile.
    wake = gather_target_ == 0 || stats_.pending_tiles >= gather_target_;
  }
  if (wake) wake_.notify_one();
  return SubmitStatus::kAccepted;
}

SubmitStatus TileWriter::post(Task task) {
  assert(task);
  {
    std::lock_guard lock(mu_);
    if (stopping_) return SubmitStatus::kStopped;
    if (stats_.pending_tasks >= limits_.max_pending_tasks) {
      ++stats_.busy_refusals;
      return SubmitStatus::kBusy;
    }
    ++stats_.pending_tasks;
    queue_.push_back(Item{{}, {}, std::move(task)});
  }
  wake_.notify_one();
  return SubmitStatus::kAccepted;
}

void TileWriter::stop() {
  std::lock_guard stop_lock(stop_mu_);
  {
    std::lock_guard lock(mu_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) {
    assert(std::this_thread::get_id() != thread_.get_id() && "stop() called from a writer callback");
    thread_.join();
  }
  // The writer's last checkpoint waited for any background one; nothing can ask for another now.
  {
    std::lock_guard lock(checkpoint_mu_);
    checkpointer_stopping_ = true;
  }
  checkpoint_cv_.notify_all();
  if (checkpointer_.joinable()) checkpointer_.join();
}

WriterStats TileWriter::stats() const {
  std::lock_guard lock(mu_);
  return stats_;
}

void TileWriter::run() {
  name_thread("dtraced-writer");
  std::vector<Item> batch;
  const auto has_work = [this] { return stopping_ || !queue_.empty(); };
  for (;;) {
    // Under load the WAL file is kept for the next writes; once idle (or stopping) it is emptied.
    if (truncate_owed_) bound_wal();
    if (truncate_owed_) {
      std::unique_lock lock(mu_);
      // The queue stayed empty for checkpoint_when_idle, or a stop left nothing to write.
      const bool idle = !wake_.wait_for(lock, limits_.checkpoint_when_idle, has_work) || queue_.empty();
      lock.unlock();
      if (idle) checkpoint(CheckpointMode::kTruncate);
      if (idle && truncate_owed_) {
        // Not emptied (a reader was in the way): another idle wait and another try, unless work
        // came meanwhile or the writer is stopping.
        std::lock_guard retry(mu_);
        if (!stopping_ && queue_.empty()) continue;
      }
    }
    {
      std::unique_lock lock(mu_);
      wake_.wait(lock, has_work);
      if (queue_.empty()) return;  // stopping, and everything accepted has been handled
      const std::size_t max_tiles = std::max<std::size_t>(limits_.max_batch_tiles, 1);
      gather(lock, std::min(last_batch_tiles_, max_tiles));
      // Everything pending, up to max_batch_tiles tiles (tasks come along in their places).
      std::size_t tiles = 0;
      while (!queue_.empty() && (queue_.front().task || tiles < max_tiles)) {
        if (!queue_.front().task) ++tiles;
        batch.push_back(std::move(queue_.front()));
        queue_.pop_front();
      }
      last_batch_tiles_ = tiles;
    }
    // Submission order is kept: tasks run where they were posted, and each run of tiles between
    // them is one transaction.
    for (std::size_t i = 0; i < batch.size();) {
      truncate_owed_ = true;
      if (batch[i].task) {
        run_task(batch[i]);
        ++i;
        continue;
      }
      std::size_t j = i + 1;
      while (j < batch.size() && !batch[j].task) ++j;
      write_tiles(batch, i, j);
      i = j;
    }
    batch.clear();
  }
}

void TileWriter::gather(std::unique_lock<std::mutex>& lock, std::size_t target) {
  // Nothing is being written now, so pending_tiles and pending_tasks are what is queued.
  const auto enough = [&] { return stopping_ || stats_.pending_tasks > 0 || stats_.pending_tiles >= target; };
  if (limits_.gather_wait.count() <= 0 || target <= 1 || enough()) return;
  ++stats_.gather_waits;
  gather_target_ = target;
  if (!wake_.wait_for(lock, limits_.gather_wait, enough)) ++stats_.gather_timeouts;
  gather_target_ = 0;
}

void TileWriter::write_tiles(std::vector<Item>& items, std::size_t begin, std::size_t end) {
  std::vector<TileWrite> writes;
  writes.reserve(end - begin);
  std::uint64_t bytes = 0;
  for (std::size_t k = begin; k < end; ++k) {
    bytes += cost_bytes(items[k].write);
    writes.push_back(std::move(items[k].write));
  }
  const auto start = std::chrono::steady_clock::now();
  auto result = store_.insert_tiles(writes);
  const std::chrono::duration<double> took = std::chrono::steady_clock::now() - start;
  writes = {};  // the pixels are on disk (or not); release them before counting them out

  if (!result)
    util::log_error("store writer: a batch of {} tiles was not stored: {}", end - begin, result.error().message);
  {
    std::lock_guard lock(mu_);
    ++stats_.batches;
    stats_.largest_batch = std::max<std::uint64_t>(stats_.largest_batch, end - begin);
    stats_.write_seconds += took.count();
    stats_.pending_tiles -= end - begin;
    stats_.pending_bytes -= bytes;
    if (!result) {
      stats_.tiles_failed += end - begin;
    } else {
      for (const CommitResult& r : result.value()) ++(stats_.*kOutcomeCounters[static_cast<std::size_t>(r.outcome)]);
    }
  }
  for (std::size_t k = begin; k < end; ++k) {
    CommitResult r = result ? std::move(result.value()[k - begin])
                            : CommitResult{TileOutcome::kFailed, false, result.error().message};
    call_guarded("tile callback", [&] { items[k].done(std::move(r)); });
    items[k].done = nullptr;
  }
}

void TileWriter::bound_wal() {
  const std::uint64_t wal = store_.wal_bytes();
  const std::uint64_t bound = limits_.checkpoint_wal_bytes;
  bool finished = false;  // the background checkpoint asked for last has finished since
  if (background_asked_) {
    std::lock_guard lock(checkpoint_mu_);
    finished = !checkpoint_wanted_;
  }
  if (finished) background_asked_ = false;
  if (wal >= bound) {
    checkpoint(CheckpointMode::kReuse);
    return;
  }
  if (!background_ || background_asked_ || wal < bound / 2) return;
  // The background checkpoint copied at least what was committed when it was asked for; while it
  // ran, commits went on, so the WAL cannot start over yet. When little came in meanwhile, the
  // writer copies that now (a short wait), after which its next commit starts the WAL over;
  // otherwise another background checkpoint chases it, copying less each time.
  if (finished && wal <= background_asked_at_ + bound / kCatchUpFraction) {
    checkpoint(CheckpointMode::kReuse);
    return;
  }
  background_asked_at_ = wal;
  background_asked_ = true;
  {
    std::lock_guard lock(checkpoint_mu_);
    checkpoint_wanted_ = true;
  }
  checkpoint_cv_.notify_all();
}

void TileWriter::checkpoint(CheckpointMode mode) {
  const auto start = std::chrono::steady_clock::now();
  // One checkpoint at a time: a second one would find the WAL's checkpoint lock taken and do
  // nothing, and TRUNCATE could not empty the file.
  {
    std::unique_lock lock(checkpoint_mu_);
    checkpoint_cv_.wait(lock, [this] { return !checkpoint_wanted_; });
  }
  background_asked_ = false;
  // Only a TRUNCATE empties the file: after the copies that keep the WAL under its bound (kReuse),
  // the writer still owes the idle one.
  if (mode == CheckpointMode::kTruncate) truncate_owed_ = false;
  auto result = store_.checkpoint(mode);
  const std::chrono::duration<double> took = std::chrono::steady_clock::now() - start;
  // A TRUNCATE that could not empty the WAL (a reader in the way for the moment: the busy timeout
  // is zero here) is tried again after the next idle wait, not only after the next writes.
  if (mode == CheckpointMode::kTruncate && (!result || !result.value().complete)) truncate_owed_ = true;
  count_checkpoint(result, false, took.count());
}

void TileWriter::run_checkpoints(Store& connection) {
  name_thread("dtraced-ckpt");
  std::unique_lock lock(checkpoint_mu_);
  for (;;) {
    checkpoint_cv_.wait(lock, [this] { return checkpoint_wanted_ || checkpointer_stopping_; });
    if (!checkpoint_wanted_) return;
    lock.unlock();
    count_checkpoint(connection.checkpoint(CheckpointMode::kReuse), true, 0);
    lock.lock();
    checkpoint_wanted_ = false;
    checkpoint_cv_.notify_all();  // the writer may be waiting to checkpoint itself
  }
}

void TileWriter::count_checkpoint(const util::Result<CheckpointResult>& result, bool background,
                                  double writer_seconds) {
  bool log = false;
  {
    std::lock_guard lock(mu_);
    ++stats_.checkpoints;
    if (background) ++stats_.checkpoints_background;
    stats_.checkpoint_seconds += writer_seconds;
    if (!result) {
      ++stats_.checkpoints_failed;
    } else if (!result.value().complete) {
      ++stats_.checkpoints_partial;
    }
    log = !result && !checkpoint_failing_;
    checkpoint_failing_ = !result;
  }
  if (log) {
    util::log_warn("store writer: {} (retried after the next writes; logged once until one succeeds)",
                   result.error().message);
  }
}

void TileWriter::run_task(Item& item) {
  call_guarded("task", [&] { item.task(store_); });
  item.task = nullptr;
  std::lock_guard lock(mu_);
  --stats_.pending_tasks;
  ++stats_.tasks_run;
}

}  // namespace dtraced::store
