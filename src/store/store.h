// dtraced::store: the collector's durable state in one SQLite database, <state_dir>/dtraced.db.
// All SQL of dtraced lives in this module. The store knows nothing about HTTP, rendering or what
// the JSON means: it keeps strings and blobs and reports what happened to them.
//
// Owns: opening the database (and refusing a bad one), the schema, and every query.
//
// Schema (version 4, STRICT tables, documented in docs/http-api.md too):
//   meta(key TEXT PRIMARY KEY, value ANY)            -- ('schema_version', 4), ('last_job_id', N)
//   scenes(digest TEXT PRIMARY KEY, json TEXT)       -- immutable, content-addressed
//   jobs(id INTEGER PRIMARY KEY, digest -> scenes, settings_json, output, priority, tile_size,
//        state IN ('queued','rendering','done','cancelled','paused'), created_unix, finished_unix,
//        client_key TEXT UNIQUE NULL)
//   tiles(job -> jobs, tile, pixels BLOB, worker TEXT, stored_unix, pixels_offset NULL,
//        pixels_length NULL, pixels_crc NULL, PRIMARY KEY(job, tile))
//   (what a tile's pixels hold is the collector's business: collector/jobs.h, pixels_to_blob)
//   pixel_files(job INTEGER PRIMARY KEY, bytes)   -- committed length of each job's pixel file
//   job_tile_costs(job INTEGER PRIMARY KEY, costs BLOB)  -- optional per job (StoredJob::tile_costs);
//        created at open when missing, in any version: a file without it reads as "no costs",
//        and an older dtraced ignores it (no foreign key, so its delete_job still succeeds)
//   credentials(name TEXT PRIMARY KEY, role TEXT, token_sha256 BLOB UNIQUE, created_unix,
//        revoked_unix NULL)                       -- a revoked credential stays, revoked
//   join_codes(secret_sha256 BLOB PRIMARY KEY, name_hint NULL, created_unix, expires_unix,
//        used_unix NULL, used_by NULL)            -- single use: enroll() marks it used
//   (only digests of tokens and secrets are stored: the database never holds a usable one)
//
// Tile pixels (version 4): a tile's bytes are appended to its job's file
// <state_dir>/pixels/job-<id>.pixels, which is fdatasync'ed before the COMMIT of the tile's row
// (offset, length and CRC-32C there; its pixels column empty): they are written once, not into the
// WAL and again by a checkpoint. A row with pixels_offset NULL holds its pixels itself (every tile
// stored before version 4, and OpenOptions::pixels_in_rows). pixel_files.h has the file format,
// the commit order and what a crash leaves. Reads check each tile's length and checksum: a tile
// whose bytes are missing or damaged is an error naming the file, job and tile (get_tile), or is
// left out of get_all_tiles with that error logged, so the job's other tiles are restored and the
// damaged one is leased and rendered again (insert_tiles then replaces the damaged row). delete_job
// deletes the job's file after its COMMIT (a crash in between leaves a file of no job, which
// remove_orphan_pixel_files deletes); a cancelled or paused job keeps its file. On a full disk an
// append fails, its transaction is rolled back and its tiles are not acknowledged (kFailed).
//
// Failures: every call returns a util::Result or util::Status. An expected failure (a bad
// database file, a constraint violation, a full disk) is a util::Error whose message names the
// database file and, for SQLite failures, carries sqlite3_errmsg and the extended result code
// (its path and file fields stay empty). The store never throws for those; an exception out of it
// means a programming error or memory exhaustion.
//
// Durability: journal_mode=WAL with synchronous=FULL, so a transaction whose COMMIT returned
// survives a process kill and (given honest disks) a power loss. foreign_keys=ON.
//
// Disk space: the WAL is persistent (SQLITE_FCNTL_PERSIST_WAL: its -wal and -shm files stay when
// the last connection closes, emptied), so opening the database again needs no new disk space;
// on a full disk, start-up and reads work, and writes fail with a message until space frees.
// checkpoint() keeps the WAL short.
//
// Version 3 (tile pixels only in rows) is upgraded in place by adding the three columns and
// pixel_files; its tiles stay in their rows and are read from there, new tiles go to pixel files.
// Version 2 (no credentials, no join_codes) is upgraded in place by creating the two tables.
// Version 1 (no 'paused' state, no last_job_id) is upgraded in place, in one transaction, when
// opened (then on to version 3); the upgrade also switches the file to incremental auto-vacuum when there is room for
// the VACUUM that takes (new files have it from the start), so delete_job returns space.
//
// Opening never replaces, truncates or deletes an existing file. A file that is not an SQLite
// database, fails PRAGMA quick_check, has another schema version, or lacks tables or columns is
// refused with a message naming the file and the problem, and is left byte-for-byte as it was
// (verification runs with query_only=ON and with checkpoint-on-close disabled). Only a database
// with no schema objects at all (a new or zero-length file) gets the schema created.
//
// Thread safety: a Store is one SQLite connection with its own cache of prepared statements. Use
// it from one thread at a time (it may be moved to another thread between calls). Several Store
// objects opened on the same directory may be used concurrently from different threads: WAL lets
// readers proceed while one writer commits. Every call does disk I/O and may wait up to
// kBusyTimeout for another connection's write lock, so NEVER call a Store from the collector's
// event loop once it runs: at start-up (before the loop) it is fine; afterwards, writes go through
// TileWriter (tile_writer.h), which owns a Store on its own thread, and large reads (image
// assembly) belong on a worker thread with its own Store.
#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "util/result.h"

namespace dtraced::store {

inline constexpr std::int64_t kSchemaVersion = 4;
inline constexpr std::int64_t kOldestMigratedVersion = 1;  // opened and upgraded to kSchemaVersion
inline constexpr std::string_view kDatabaseFileName = "dtraced.db";
// How long a statement waits for another connection's lock before failing with SQLITE_BUSY.
inline constexpr std::chrono::milliseconds kBusyTimeout{5000};
// After a checkpoint the WAL file is truncated back to at most this size, so a burst of tiles
// does not leave a huge -wal file behind.
inline constexpr std::int64_t kJournalSizeLimitBytes = 64 << 20;
// The upgrade from schema version 1 converts a file up to this size to incremental auto-vacuum
// (a VACUUM copies the whole file: 8 s for 1 GiB of tiles measured on a busy 2-core host, well
// within systemd's default 90 s start timeout).
inline constexpr std::uint64_t kMaxUpgradeVacuumBytes = std::uint64_t{1} << 30;
// How many lines of a failed quick_check are quoted in the error message.
inline constexpr std::size_t kMaxIntegrityLinesReported = 8;

using Blob = std::vector<std::uint8_t>;

// The only states the schema accepts (a CHECK constraint); their meaning belongs to the collector.
inline constexpr std::string_view kJobQueued = "queued";
inline constexpr std::string_view kJobRendering = "rendering";
inline constexpr std::string_view kJobDone = "done";
inline constexpr std::string_view kJobCancelled = "cancelled";
inline constexpr std::string_view kJobPaused = "paused";

struct StoredJob {
  std::int64_t id = 0;  // assigned by insert_job; ignored on input
  std::string digest;   // must name a stored scene (foreign key)
  std::string settings_json;
  std::string output;
  std::int32_t priority = 0;
  std::uint32_t tile_size = 0;  // > 0
  std::string state{kJobQueued};
  std::int64_t created_unix = 0;
  std::int64_t finished_unix = 0;  // 0 while unfinished
  // Optional and unique: the one-shot collector stores a key derived from its command line so a
  // restart with the same command line finds the job instead of enqueueing a copy.
  std::optional<std::string> client_key;
  // Optional: the job's tile cost estimates, opaque to the store (collector/submission.h);
  // empty for none. Kept in job_tile_costs, written with the job and deleted with it.
  Blob tile_costs;

  bool operator==(const StoredJob&) const = default;
};

struct StoredTile {
  std::uint32_t tile = 0;
  Blob pixels;
  std::string worker;
  std::int64_t stored_unix = 0;
};

// A tile's pixels as the store is given them: bytes of their own, or a slice of a tile upload's
// body, kept whole so that the pixels reach the database without being copied out of it first (a
// 12 KB allocation and copy a tile on the collector's loop).
class TilePixels {
 public:
  TilePixels() = default;
  TilePixels(Blob bytes) : blob_(std::move(bytes)) {}  // implicit: a Blob is the plain case
  // payload[offset, offset + size); the slice must lie within the payload (asserted).
  TilePixels(std::string payload, std::size_t offset, std::size_t size);

  // The bytes stored.
  std::span<const std::uint8_t> bytes() const {
    if (payload_.empty()) return blob_;
    return std::span(reinterpret_cast<const std::uint8_t*>(payload_.data()) + offset_, size_);
  }
  std::size_t size() const { return payload_.empty() ? blob_.size() : size_; }
  // What it holds in memory (a payload's header and checksum too).
  std::uint64_t held_bytes() const { return blob_.size() + payload_.size(); }

 private:
  Blob blob_;
  std::string payload_;
  std::size_t offset_ = 0;
  std::size_t size_ = 0;
};

// One tile result to store. The first stored result for (job, tile) wins.
struct TileWrite {
  std::int64_t job = 0;
  std::uint32_t tile = 0;
  TilePixels pixels;
  std::string worker;
  std::int64_t stored_unix = 0;
};

// to_string and the writer's counters (WriterStats) follow this order.
enum class TileOutcome {
  kStored,          // newly stored by this transaction, which committed
  kAlreadyPresent,  // a row for (job, tile) existed (or came earlier in the same batch)
  kRejected,        // this tile broke a constraint (no such job); the rest of the batch is unaffected
  kFailed,          // the transaction failed: nothing of the batch was stored; may be retried
};

std::string_view to_string(TileOutcome outcome);

struct CommitResult {
  TileOutcome outcome = TileOutcome::kFailed;
  // For kAlreadyPresent: whether the stored pixels equal the submitted ones byte for byte (the
  // renderer is deterministic, so a difference points at a faulty worker).
  bool identical = false;
  std::string error;  // for kRejected and kFailed
};

// What a checkpoint did: the WAL's frames before it, how many of them are in the database file
// now, and whether the WAL file was emptied (every frame copied and no reader still using it).
// `complete`: every frame is in the database file (after kTruncate, the same as `truncated`;
// after kReuse, the next write starts the WAL over from its beginning).
struct CheckpointResult {
  int wal_frames = 0;
  int copied_frames = 0;
  bool truncated = false;
  bool complete = false;
};

// How Store::checkpoint leaves the WAL file. kTruncate empties it (wal_checkpoint(TRUNCATE): an
// ftruncate and, on the next writes, the file's blocks allocated again). kReuse copies the frames
// into the database and keeps the file (wal_checkpoint(PASSIVE)): once every frame is copied, the
// next write transaction overwrites the WAL from its start, so a busy writer reuses the same
// blocks instead of shrinking and regrowing the file; journal_size_limit still caps what stays.
enum class CheckpointMode { kTruncate, kReuse };

// What delete_job did: deleted (with how many tiles and whether the job's scene went with it),
// or refused because the job is in `state`, which was not one of the states allowed.
struct Deletion {
  bool deleted = false;
  std::string state;
  std::uint64_t tiles = 0;
  bool scene_deleted = false;
};

// The database file's pages: in use, free (reusable, or released by reclaim_space).
struct SpaceUse {
  std::uint64_t page_size = 0;
  std::uint64_t pages = 0;
  std::uint64_t free_pages = 0;
};

// What change_job_state did: changed, or left the job in `state` (not one of `from`).
struct StateChange {
  bool changed = false;
  std::string state;  // the stored state after the call
};
inline constexpr std::size_t kMaxStateChangeSources = 4;

// A credential (collector/credentials.h says what the roles mean). The token itself is never
// stored, only its SHA-256 digest.
struct StoredCredential {
  std::string name;
  std::string role;
  Blob token_sha256;  // 32 bytes
  std::int64_t created_unix = 0;
  std::optional<std::int64_t> revoked_unix;
  bool operator==(const StoredCredential&) const = default;
};

// A join code (enrollment); only the SHA-256 digest of its secret is stored.
struct StoredJoinCode {
  Blob secret_sha256;  // 32 bytes
  std::optional<std::string> name_hint;
  std::int64_t created_unix = 0;
  std::int64_t expires_unix = 0;
  std::optional<std::int64_t> used_unix;
  std::optional<std::string> used_by;  // the credential it enrolled
  bool operator==(const StoredJoinCode&) const = default;
};

// What enroll() did.
enum class EnrollOutcome {
  kEnrolled,  // the credential is stored and the code marked used, in one transaction
  kUnknown,   // no such code
  kUsed,      // the code was used before (code->used_by says by whom)
  kExpired,   // the code's expires_unix is not after now
  kNoName,    // every candidate name is taken (kMaxEnrollNameTries)
};
struct Enrollment {
  EnrollOutcome outcome = EnrollOutcome::kUnknown;
  std::string name;                    // kEnrolled: the credential's name
  std::optional<StoredJoinCode> code;  // as found (before it was marked used)
};
// enroll() tries `base`, then `base-2`, `base-3`, ... up to this many names.
inline constexpr int kMaxEnrollNameTries = 1000;

struct OpenOptions {
  // PRAGMA quick_check and foreign_key_check read the whole file. The first connection of a
  // process runs them; further connections to a file already verified may skip them.
  bool verify_integrity = true;
  std::chrono::milliseconds busy_timeout = kBusyTimeout;
  // A cap on the database's size (PRAGMA max_page_count), 0 for none. A write that would grow it
  // further fails with "database or disk is full" and changes nothing, like a full disk.
  // Also counts the bytes of the pixel files (pixel_files.bytes), so that it caps what the store
  // holds on disk whether tiles are in rows or in files.
  std::uint64_t max_database_bytes = 0;
  // Tiles inserted through this connection keep their pixels in their rows, as before version 4
  // (for tests of the WAL and its checkpoints under the weight of tiles). Reads handle both.
  bool pixels_in_rows = false;
};

class Store {
 public:
  // Creates `state_dir` (and parents) if missing, then opens or creates <state_dir>/dtraced.db as
  // described at the top of this file.
  static util::Result<Store> open(const std::string& state_dir, const OpenOptions& options = {});

  Store(Store&&) noexcept;
  Store& operator=(Store&&) noexcept;
  Store(const Store&) = delete;
  Store& operator=(const Store&) = delete;
  ~Store();

  // The database file's path.
  const std::string& path() const;

  // Runs `body` inside one BEGIN IMMEDIATE ... COMMIT: every store call made by `body` on this
  // Store is part of it. An error from `body` (or a failed COMMIT) rolls everything back. Not
  // reentrant.
  util::Status transaction(const std::function<util::Status()>& body);

  // Scenes are immutable and content-addressed: storing a digest that exists already is a no-op.
  util::Status put_scene(std::string_view digest, std::string_view json);
  util::Result<std::optional<std::string>> get_scene(std::string_view digest);

  // Inserts a job (job.id is ignored) and returns its id: one more than any id this database
  // ever gave, so the id of a deleted job is never reused. Fails when the scene is missing, the
  // client_key is taken, the state is unknown or tile_size is 0.
  util::Result<std::int64_t> insert_job(const StoredJob& job);
  // Fails when there is no such job or the state is unknown. Unconditional: the collector moves
  // jobs with change_job_state, which cannot undo a state that was answered.
  util::Status set_job_state(std::int64_t id, std::string_view state, std::int64_t finished_unix);
  // Compare-and-set: moves job `id` to `to` (with `finished_unix`) only if its stored state is one
  // of `from` (1 to kMaxStateChangeSources states), in one UPDATE. A write that lost a race (a
  // "rendering" posted before a cancellation committed, run after it) thus changes nothing.
  // Fails when there is no such job or `to` is unknown.
  util::Result<StateChange> change_job_state(std::int64_t id, std::span<const std::string_view> from,
                                             std::string_view to, std::int64_t finished_unix);
  // In one transaction: when job `id` is in one of `allowed` states (1 to kMaxStateChangeSources),
  // deletes its tiles, the job, and its scene if no other job uses it. Fails when there is no such
  // job. The space goes to the free list; reclaim_space() gives it back to the file system.
  util::Result<Deletion> delete_job(std::int64_t id, std::span<const std::string_view> allowed);
  // Releases free pages to the file system (PRAGMA incremental_vacuum, then a checkpoint so the
  // WAL does not keep them), as far as the file's auto-vacuum mode allows; returns the pages
  // afterwards.
  util::Result<SpaceUse> reclaim_space();
  util::Result<SpaceUse> space_use();
  // Fails when there is no such job or the priority is out of the int32 range.
  util::Status set_job_priority(std::int64_t id, std::int32_t priority);
  util::Result<std::vector<StoredJob>> list_jobs();  // ascending id
  util::Result<std::optional<StoredJob>> get_job(std::int64_t id);
  util::Result<std::optional<StoredJob>> find_job_by_key(std::string_view client_key);

  // Stores tile results in one transaction (or inside the caller's transaction()): INSERT OR
  // IGNORE, so the first stored result wins. Returns one CommitResult per write, in order:
  // kStored, kAlreadyPresent or kRejected. An error means the transaction failed and nothing
  // was stored. TileWriter calls this on its thread; tests and tools may call it directly.
  util::Result<std::vector<CommitResult>> insert_tiles(std::span<const TileWrite> writes);

  util::Result<std::vector<std::uint32_t>> stored_tiles(std::int64_t job);  // ascending tile index
  util::Result<std::uint64_t> count_tiles(std::int64_t job);
  util::Result<std::optional<StoredTile>> get_tile(std::int64_t job, std::uint32_t tile);
  // Ascending tile index. A tile whose pixel file is missing, short or fails its checksum is left
  // out, with an error logged that names the file, job and tile (see the top of this file).
  util::Result<std::vector<StoredTile>> get_all_tiles(std::int64_t job);
  // get_all_tiles one tile at a time (a large job's pixels are never all in memory): `visit` is
  // called with each readable tile in ascending index; its first error stops the walk and is the
  // result.
  util::Status visit_tiles(std::int64_t job, const std::function<util::Status(StoredTile&&)>& visit);

  // Deletes pixel files (<state_dir>/pixels/job-<id>.pixels) of jobs that no longer exist, left by
  // a crash between a delete_job's COMMIT and its unlink; logs each. Returns how many. TileWriter
  // calls it when it starts.
  util::Result<std::size_t> remove_orphan_pixel_files();

  // Credentials. insert_credential: false (changing nothing) when the name or the token digest is
  // taken. revoke_credential: false when there is no such credential or it is revoked already
  // (the first revocation time stays). list_credentials: every one, revoked ones too, by name.
  util::Result<bool> insert_credential(const StoredCredential& credential);
  util::Result<bool> revoke_credential(std::string_view name, std::int64_t revoked_unix);
  util::Result<std::vector<StoredCredential>> list_credentials();

  // Join codes. insert_join_code fails when the digest exists (16 random bytes: never by chance).
  util::Status insert_join_code(const StoredJoinCode& code);
  util::Result<std::optional<StoredJoinCode>> get_join_code(std::span<const std::uint8_t> secret_sha256);
  util::Result<std::vector<StoredJoinCode>> list_join_codes();  // by creation time
  // In one transaction: finds the code, refuses it when unknown, used or expired at `now_unix`;
  // else stores a credential of `role` with the first free name of `base`, `base-2`, ... and
  // marks the code used by it. Nothing changes unless the outcome is kEnrolled.
  util::Result<Enrollment> enroll(std::span<const std::uint8_t> secret_sha256, std::string_view base,
                                  std::string_view role, std::span<const std::uint8_t> token_sha256,
                                  std::int64_t now_unix);

  // Copies the WAL into the database file and, with kTruncate, empties the WAL file
  // (wal_checkpoint(TRUNCATE); kReuse keeps the file for the next writes, see CheckpointMode),
  // without waiting for other connections: while a reader still uses an older snapshot, it copies
  // what it can and reports truncated = complete = false, which is no error. Frames committed by
  // another connection after the checkpoint began are not counted in wal_frames: `complete` says
  // that what it saw was copied. TileWriter turns SQLite's own checkpoints off
  // (manage_checkpoints) and calls this as the WAL grows (WriterLimits::checkpoint_wal_bytes,
  // mostly on open_checkpoint_connection's connection), when idle and at stop, so the WAL stays
  // bounded instead of growing with the job. An error is an I/O failure (a full disk:
  // copying into the database may need to grow it), naming the file; nothing is lost by it.
  util::Result<CheckpointResult> checkpoint(CheckpointMode mode = CheckpointMode::kTruncate);

  // Opens another connection to this Store's file for checkpoint() only (TileWriter's checkpoint
  // thread): a PASSIVE checkpoint there copies committed frames while this connection goes on
  // committing, where on this connection every commit waits for it. The file was verified when
  // this Store opened it, so nothing is read but the journal mode (which must be WAL). The
  // connection is query_only (no SQL through it changes the file; checkpoints are not SQL), uses
  // this Store's busy timeout and synchronous=FULL (a checkpoint syncs the WAL before copying and
  // the database after), and never checkpoints on close: the writer's connection does that.
  util::Result<Store> open_checkpoint_connection() const;

  // Turns SQLite's own checkpoints off (they run inside a COMMIT every 1000 pages, 4 MiB) and
  // starts counting the WAL after each commit of this connection (sqlite3_wal_hook), so that the
  // caller checkpoints by wal_bytes() instead. Whoever calls this must checkpoint, or the WAL grows
  // without bound: TileWriter calls it on the Store it owns. Idempotent.
  util::Status manage_checkpoints();
  // The WAL's length after this connection's last commit (frames with their headers), as
  // reported to the hook manage_checkpoints() installed, or 0 after a complete checkpoint on this
  // connection since (the next commit starts the WAL over; one on another connection is seen at
  // the next commit); always 0 without manage_checkpoints().
  std::uint64_t wal_bytes() const;

 private:
  struct Impl;
  explicit Store(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace dtraced::store
