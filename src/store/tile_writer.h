// dtraced::store::TileWriter: the one thread that writes the collector's database, with group
// commit for tile results.
//
// Owns: a dedicated thread, the Store (connection) it was given, and a bounded queue of pending
// work; and a second thread with a second connection to the same file, for checkpoints only.
// The thread takes everything pending at once (up to WriterLimits::max_batch_tiles tiles) and
// processes it in submission order; each run of consecutive tile writes becomes ONE transaction
// (Store::insert_tiles: INSERT OR IGNORE, the first stored result wins), and only after its
// COMMIT returned are the callbacks of those tiles called. A fsync is paid per batch rather than
// per tile, so the commit rate grows with the load. If the transaction fails, every tile of the
// batch gets kFailed and none is acknowledged; the thread goes on with the next batch.
// The WAL is checkpointed by the writer (WriterLimits::checkpoint_wal_bytes and
// checkpoint_when_idle; SQLite's own checkpoints inside COMMIT are off), so the -wal file stays
// bounded and is empty soon after the writer goes idle. Under load, checkpoints run on the second
// thread with its own connection (Store::open_checkpoint_connection), PASSIVE, so commits and
// their acknowledgements go on while pages are copied; the file is kept (CheckpointMode::kReuse:
// the next batches overwrite its blocks instead of growing a truncated file again). The WAL
// starts over only at a commit that finds every frame copied, which commits made during the copy
// prevent; so the writer itself copies the last few frames (a short wait), or, should the WAL
// reach its bound, waits for the background checkpoint and copies what is left. The idle and
// stop checkpoints (TRUNCATE: the file is emptied) run on the writer's connection, with nothing
// else writing.
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
// stop() stops accepting work, drains and commits everything accepted, calls every callback,
// empties the WAL, and joins both threads. The destructor calls stop().
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
  std::uint64_t max_pending_bytes = std::uint64_t{256} << 20;  // pixels (TilePixels::held_bytes) + worker names
  std::size_t max_pending_tasks = 1024;
  // The WAL's bound. SQLite's own checkpoints are off (Store::manage_checkpoints). Once the WAL
  // has reached half this many bytes, a background checkpoint copies it into the database while
  // commits go on (Store::checkpoint, kReuse: the file is kept for reuse); then the writer copies
  // the frames committed meanwhile (see the top of this file). Should the WAL reach this many
  // bytes all the same, the writer stops committing until a checkpoint has copied every frame, so
  // the -wal file stays below this plus one batch's frames (a batch is at most max_batch_tiles
  // tiles and the tasks between them). A reader holding an old snapshot can keep frames from
  // being copied, and then the writer tries again after every batch. When the queue has stayed
  // empty for checkpoint_when_idle after a write, and at stop, the file is emptied. Each
  // checkpoint costs two fsyncs and copies every page once however often it changed in between,
  // so a larger bound means fewer, cheaper-per-tile checkpoints and more disk for the WAL.
  std::uint64_t checkpoint_wal_bytes = std::uint64_t{16} << 20;
  std::chrono::milliseconds checkpoint_when_idle{200};
  // Group commit under load. A commit costs more than its tiles' pages (an fsync, and the B-tree,
  // pointer-map and header pages written again each time), so fewer, larger commits store a tile
  // for less. When the writer finds fewer tiles pending than its last batch held, it waits up to
  // this long for as many before it writes (tasks and stop() do not wait): a steady load then
  // keeps its batch size instead of the writer starting on the first tile that arrives, and a
  // load that fell off costs each commit this much latency at most. 0: write what is pending.
  std::chrono::microseconds gather_wait{1500};
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
  std::uint64_t gather_waits = 0;            // batches the writer waited for (WriterLimits::gather_wait)
  std::uint64_t gather_timeouts = 0;         // of which ended before as many tiles as the last batch came
  std::uint64_t checkpoints = 0;             // attempted, on either thread
  std::uint64_t checkpoints_background = 0;  // of which on the checkpoint thread, beside commits
  std::uint64_t checkpoints_partial = 0;     // a reader kept some frames from being copied
  std::uint64_t checkpoints_failed = 0;      // an I/O error (a full disk)
  double write_seconds = 0;                  // total time inside tile transactions (inserts + COMMIT)
  // Time the writer thread spent checkpointing or waiting for a background checkpoint to end,
  // when no commit could run (idle and stop checkpoints included).
  double checkpoint_seconds = 0;
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
  static std::uint64_t cost_bytes(const TileWrite& w) { return w.pixels.held_bytes() + w.worker.size(); }

  void run();
  // Under mu_, with tiles queued and none being written: waits up to WriterLimits::gather_wait
  // until `target` tiles are queued (or a task, or stop()).
  void gather(std::unique_lock<std::mutex>& lock, std::size_t target);
  void write_tiles(std::vector<Item>& items, std::size_t begin, std::size_t end);
  void run_task(Item& item);
  // After writes: asks for a background checkpoint, or checkpoints on the writer's connection,
  // as WriterLimits::checkpoint_wal_bytes says.
  void bound_wal();
  // On the writer's connection, once no background checkpoint runs.
  void checkpoint(CheckpointMode mode);
  void run_checkpoints(Store& connection);  // checkpointer_'s loop
  void count_checkpoint(const util::Result<CheckpointResult>& result, bool background, double writer_seconds);

  Store store_;  // used by thread_ only
  const WriterLimits limits_;
  bool background_ = false;  // set before the threads start: checkpointer_ runs

  mutable std::mutex mu_;
  std::condition_variable wake_;  // signalled on new work and on stop
  // Guarded by mu_:
  std::deque<Item> queue_;
  bool stopping_ = false;
  WriterStats stats_;                // pending_* count queued work plus the batch being written
  bool checkpoint_failing_ = false;  // log a failure streak once (checkpoints on either thread)
  // While the writer gathers a batch: the tiles it waits for (submit() wakes it at this many);
  // 0 otherwise.
  std::size_t gather_target_ = 0;

  // thread_ only: whether it wrote since its last complete TRUNCATE (and so owes one when idle);
  // whether it asked for a background checkpoint it has not seen finish, and the WAL's bytes when
  // it asked.
  bool truncate_owed_ = false;
  std::size_t last_batch_tiles_ = 0;  // tiles of the last batch taken
  bool background_asked_ = false;
  std::uint64_t background_asked_at_ = 0;

  std::mutex checkpoint_mu_;
  std::condition_variable checkpoint_cv_;  // signalled when a checkpoint is wanted, done, or on stop
  // Guarded by checkpoint_mu_: a background checkpoint is asked for or running; stop() was called.
  bool checkpoint_wanted_ = false;
  bool checkpointer_stopping_ = false;

  std::mutex stop_mu_;        // serialises stop() so two callers do not both join
  std::thread checkpointer_;  // the background checkpoints, with a connection of its own
  std::thread thread_;        // declared last; started at the end of the constructor
};

}  // namespace dtraced::store
