#include "store/tile_writer.h"

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

}  // namespace

TileWriter::TileWriter(Store store, WriterLimits limits) : store_(std::move(store)), limits_(limits) {
  // Without the hook SQLite keeps checkpointing inside COMMIT (every 4 MiB): slower, still bounded.
  if (auto st = store_.manage_checkpoints(); !st) {
    util::log_warn("store writer: {} (SQLite's own checkpoints stay on)", st.error().message);
  }
  thread_ = std::thread([this] { run(); });
}

TileWriter::~TileWriter() { stop(); }

SubmitStatus TileWriter::submit(TileWrite write, Done done) {
  assert(done);
  const std::uint64_t bytes = cost_bytes(write);
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
  }
  wake_.notify_one();
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
}

WriterStats TileWriter::stats() const {
  std::lock_guard lock(mu_);
  return stats_;
}

void TileWriter::run() {
  std::vector<Item> batch;
  const auto has_work = [this] { return stopping_ || !queue_.empty(); };
  for (;;) {
    // Under load the WAL file is kept for the next writes; once idle (or stopping) it is emptied.
    if (writes_since_checkpoint_ > 0 && store_.wal_bytes() >= limits_.checkpoint_wal_bytes) {
      checkpoint(CheckpointMode::kReuse);
    }
    if (writes_since_checkpoint_ > 0) {
      std::unique_lock lock(mu_);
      // The queue stayed empty for checkpoint_when_idle, or a stop left nothing to write.
      const bool idle = !wake_.wait_for(lock, limits_.checkpoint_when_idle, has_work) || queue_.empty();
      lock.unlock();
      if (idle) checkpoint(CheckpointMode::kTruncate);
    }
    {
      std::unique_lock lock(mu_);
      wake_.wait(lock, has_work);
      if (queue_.empty()) return;  // stopping, and everything accepted has been handled
      // Everything pending, up to max_batch_tiles tiles (tasks come along in their places).
      std::size_t tiles = 0;
      while (!queue_.empty() && (queue_.front().task || tiles < std::max<std::size_t>(limits_.max_batch_tiles, 1))) {
        if (!queue_.front().task) ++tiles;
        batch.push_back(std::move(queue_.front()));
        queue_.pop_front();
      }
    }
    // Submission order is kept: tasks run where they were posted, and each run of tiles between
    // them is one transaction.
    for (std::size_t i = 0; i < batch.size();) {
      ++writes_since_checkpoint_;
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

void TileWriter::checkpoint(CheckpointMode mode) {
  writes_since_checkpoint_ = 0;
  auto result = store_.checkpoint(mode);
  {
    std::lock_guard lock(mu_);
    ++stats_.checkpoints;
    if (!result) {
      ++stats_.checkpoints_failed;
    } else if (!result.value().complete) {
      ++stats_.checkpoints_partial;
    }
  }
  if (!result && !checkpoint_failing_) {
    util::log_warn("store writer: {} (retried after the next writes; logged once until one succeeds)",
                   result.error().message);
  }
  checkpoint_failing_ = !result;
}

void TileWriter::run_task(Item& item) {
  call_guarded("task", [&] { item.task(store_); });
  item.task = nullptr;
  std::lock_guard lock(mu_);
  --stats_.pending_tasks;
  ++stats_.tasks_run;
}

}  // namespace dtraced::store
