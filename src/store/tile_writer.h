// dtraced::store::TileWriter: the one thread that writes the collector's database, with group
// commit for tile results.
//
// Owns: a dedicated thread, the Store (connection) it was given, and a bounded queue of pending
// work. The thread takes everything pending at once (up to WriterLimits::max_batch_tiles tiles)
// and processes it in submission order; each run of consecutive tile writes becomes ONE
// transaction (Store::insert_tiles: INSERT OR IGNORE, the first stored result wins), and only
// after its COMMIT returned are the callbacks of those tiles called. A fsync is paid per batch
// rather than per tile, so the commit rate grows with the load. If the transaction fails, every
// tile of the batch gets kFailed and none is acknowledged; the thread goes on with the next batch.
// The thread also checkpoints the WAL (WriterLimits::checkpoint_wal_bytes and
// checkpoint_when_idle; SQLite's own checkpoints inside COMMIT are off), so the -wal file stays
// bounded and is empty soon after the writer goes idle. Under load the checkpoint keeps the file
// (CheckpointMode::kReuse: the next batches overwrite its blocks instead of growing a truncated
// file again); the idle one empties it.
//
// Other writes (scenes, jobs, state changes) are posted as tasks: a task runs on the writer thread
// with the Store, in order with the tiles submitted before and after it, each store call its own
// transaction unless the task uses Store::transaction. This keeps SQLite off the collector's event
// loop: the loop submits, and callbacks and tasks post their results back to its executor.
//
// Bounds: pending work (queued or in the batch being written) is limited in tiles, bytes and
// tasks (WriterLimits). Over a limit, submit()/post() return kBusy at once and do nothing, so the
// HTTP layer can answer 503 and the worker retries later.
//
// Thread safety: submit(), post(), stats() and stop() may be called from any thread, concurrently.
// Callbacks and tasks run on the writer thread, one at a time: they must be short (post to an
// executor and return), must not throw (an exception is logged and swallowed), and must not call
// stop() (it would join its own thread). They may call submit() and post().
// stop() stops accepting work, drains and commits everything accepted, calls every callback, and
// joins. The destructor calls stop().
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

#include "store/store.h"

namespace dtraced::store {

struct WriterLimits {
  // Tiles per transaction at most: bounds the acknowledgement latency of a batch and the WAL's
  // growth between checkpoints. Past a few hundred tiles, larger batches gain little.
  std::size_t max_batch_tiles = 512;
  std::size_t max_pending_tiles = 4096;
  std::uint64_t max_pending_bytes = std::uint64_t{256} << 20;  // pixels + worker names
  std::size_t max_pending_tasks = 1024;
  // The WAL's bound. SQLite's own checkpoints are off (Store::manage_checkpoints); the writer
  // checkpoints (Store::checkpoint: the WAL copied into the database, the file kept for reuse)
  // once the WAL has reached this many bytes, then when the queue has stayed empty for
  // checkpoint_when_idle after a write (the file is emptied), and at stop. The check follows each
  // batch, so the -wal file stays below this plus one batch's frames (a batch is at most
  // max_batch_tiles tiles and the tasks between them); a reader holding an old snapshot can keep
  // frames from being copied, and then the writer tries again after every batch. Each checkpoint
  // costs two fsyncs and copies every page once however often it changed in between, so a larger
  // bound means fewer, cheaper-per-tile checkpoints (a longer one now and then, during which
  // acknowledgements wait), and more disk for the WAL.
  std::uint64_t checkpoint_wal_bytes = std::uint64_t{16} << 20;
  std::chrono::milliseconds checkpoint_when_idle{200};
};

enum class SubmitStatus {
  kAccepted,  // the callback (or task) will run exactly once, on the writer thread
  kBusy,      // over a pending limit; nothing was queued, nothing will be called
  kTooLarge,  // this one tile alone exceeds max_pending_bytes; it can never be accepted
  kStopped,   // stop() was called; nothing was queued, nothing will be called
};

struct WriterStats {
  std::uint64_t batches = 0;  // tile transactions attempted
  std::uint64_t tiles_stored = 0;
  std::uint64_t tiles_already_present = 0;
  std::uint64_t tiles_rejected = 0;
  std::uint64_t tiles_failed = 0;
  std::uint64_t busy_refusals = 0;
  std::uint64_t tasks_run = 0;
  std::uint64_t largest_batch = 0;
  std::uint64_t checkpoints = 0;          // attempted
  std::uint64_t checkpoints_partial = 0;  // a reader kept some frames from being copied
  std::uint64_t checkpoints_failed = 0;   // an I/O error (a full disk)
  double write_seconds = 0;               // total time inside tile transactions (inserts + COMMIT)
  std::size_t pending_tiles = 0;
  std::uint64_t pending_bytes = 0;
  std::size_t pending_tasks = 0;
};

class TileWriter {
 public:
  using Done = std::function<void(CommitResult)>;
  using Task = std::function<void(Store&)>;

  // Starts the thread. The writer owns `store` from now on; nothing else may use it.
  explicit TileWriter(Store store, WriterLimits limits = {});
  TileWriter(const TileWriter&) = delete;
  TileWriter& operator=(const TileWriter&) = delete;
  ~TileWriter();

  // Queues a tile result. On kAccepted, `done` is called exactly once, after the transaction
  // holding the tile committed (kStored / kAlreadyPresent / kRejected) or failed (kFailed).
  SubmitStatus submit(TileWrite write, Done done);

  // Queues a task to run on the writer thread with the Store (see the top of this file).
  SubmitStatus post(Task task);

  // Idempotent. Returns once everything accepted has been written and called back.
  void stop();

  WriterStats stats() const;

 private:
  struct Item {
    TileWrite write;
    Done done;
    Task task;  // set for a task, empty for a tile
  };
  static std::uint64_t cost_bytes(const TileWrite& w) { return w.pixels.size() + w.worker.size(); }

  void run();
  void write_tiles(std::vector<Item>& items, std::size_t begin, std::size_t end);
  void run_task(Item& item);
  void checkpoint(CheckpointMode mode);

  Store store_;  // used by thread_ only
  const WriterLimits limits_;

  mutable std::mutex mu_;
  std::condition_variable wake_;  // signalled on new work and on stop
  // Guarded by mu_:
  std::deque<Item> queue_;
  bool stopping_ = false;
  WriterStats stats_;  // pending_* count queued work plus the batch being written

  std::size_t writes_since_checkpoint_ = 0;  // thread_ only: since the last checkpoint
  bool checkpoint_failing_ = false;          // thread_ only: log a failure streak once

  std::mutex stop_mu_;  // serialises stop() so two callers do not both join
  std::thread thread_;  // declared last; started at the end of the constructor
};

}  // namespace dtraced::store
