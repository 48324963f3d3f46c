// dtraced::store internals: the connection, its cache of prepared statements and the helpers
// that read rows, shared by store.cpp (open, schema, transactions, checkpoints) and
// store_rows.cpp (scenes, jobs and tiles). Private to the store module: nothing outside
// src/store includes it. Thread safety: as Store's (one thread at a time).
#pragma once

#include <sqlite3.h>

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "store/pixel_files.h"
#include "store/store.h"
#include "util/log.h"

namespace dtraced::store {

using util::Error;
using util::Result;
using util::Status;

// Statements used in several places. The others stand in the function that runs them; the cache
// of prepared statements is keyed by their text.
inline constexpr std::string_view kSqlBegin = "BEGIN IMMEDIATE";
inline constexpr std::string_view kSqlCommit = "COMMIT";
inline constexpr std::string_view kSqlRollback = "ROLLBACK";
// The job queries select the columns in the order read_job expects.
inline constexpr std::string_view kSelectJobs =
    "SELECT id, digest, settings_json, output, priority, tile_size, state, created_unix, finished_unix, client_key, "
    "(SELECT costs FROM job_tile_costs WHERE job_tile_costs.job = jobs.id) "
    "FROM jobs ";

inline std::string column_text(sqlite3_stmt* s, int i) {
  const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(s, i));
  const int n = sqlite3_column_bytes(s, i);
  return p != nullptr ? std::string(p, static_cast<std::size_t>(n)) : std::string();
}

inline Blob column_blob(sqlite3_stmt* s, int i) {
  const auto* p = static_cast<const std::uint8_t*>(sqlite3_column_blob(s, i));
  const int n = sqlite3_column_bytes(s, i);
  return p != nullptr ? Blob(p, p + n) : Blob();
}

// Column order of kSelectJobs. The schema's CHECKs keep the casts exact.
inline StoredJob read_job(sqlite3_stmt* s) {
  StoredJob job;
  job.id = sqlite3_column_int64(s, 0);
  job.digest = column_text(s, 1);
  job.settings_json = column_text(s, 2);
  job.output = column_text(s, 3);
  job.priority = static_cast<std::int32_t>(sqlite3_column_int64(s, 4));
  job.tile_size = static_cast<std::uint32_t>(sqlite3_column_int64(s, 5));
  job.state = column_text(s, 6);
  job.created_unix = sqlite3_column_int64(s, 7);
  job.finished_unix = sqlite3_column_int64(s, 8);
  if (sqlite3_column_type(s, 9) != SQLITE_NULL) job.client_key = column_text(s, 9);
  if (sqlite3_column_type(s, 10) != SQLITE_NULL) job.tile_costs = column_blob(s, 10);
  return job;
}

// The tile queries select the columns in the order Impl::read_tile expects.
inline constexpr std::string_view kSelectTiles =
    "SELECT tile, pixels, worker, stored_unix, pixels_offset, pixels_length, pixels_crc FROM tiles ";

// Where a tile's pixels lie in its job's pixel file (pixel_files.h); for a row that holds them
// itself, nothing.
struct PixelExtent {
  std::uint64_t offset = 0;
  std::uint64_t length = 0;
  std::uint32_t crc = 0;
};
inline std::optional<PixelExtent> read_extent(sqlite3_stmt* s, int first) {
  if (sqlite3_column_type(s, first) == SQLITE_NULL) return std::nullopt;
  return PixelExtent{static_cast<std::uint64_t>(sqlite3_column_int64(s, first)),
                     static_cast<std::uint64_t>(sqlite3_column_int64(s, first + 1)),
                     static_cast<std::uint32_t>(sqlite3_column_int64(s, first + 2))};
}

// What one insert_tiles call appends to one job's pixel file: the file's committed length (read
// in the call's transaction) and the pieces after it, in order.
struct PendingAppend {
  std::int64_t job = 0;
  std::uint64_t committed = 0;
  std::uint64_t bytes = 0;
  std::vector<iovec> pieces;
  std::vector<std::uint64_t> offsets;  // of each piece in the file
};

// A cached statement in use: binds parameters in order and resets the statement (releasing its
// read snapshot) when it goes out of scope. The first failing bind is reported by step().
class Query {
 public:
  explicit Query(sqlite3_stmt* s) : s_(s) {}
  Query(Query&& other) noexcept : s_(std::exchange(other.s_, nullptr)), next_(other.next_), rc_(other.rc_) {}
  Query& operator=(Query&&) = delete;
  ~Query() {
    if (s_ != nullptr) {
      sqlite3_reset(s_);
      sqlite3_clear_bindings(s_);
    }
  }

  Query& bind(std::int64_t v) { return check(sqlite3_bind_int64(s_, next_++, v)); }
  // An empty view may have a null data(), which SQLite would store as NULL: bind "" instead.
  Query& bind(std::string_view v) {
    return check(sqlite3_bind_text64(s_, next_++, v.empty() ? "" : v.data(), v.size(), SQLITE_STATIC, SQLITE_UTF8));
  }
  Query& bind_optional(const std::optional<std::int64_t>& v) {
    if (!v) return check(sqlite3_bind_null(s_, next_++));
    return bind(*v);
  }
  Query& bind_optional(const std::optional<std::string>& v) {
    if (!v) return check(sqlite3_bind_null(s_, next_++));
    return bind(std::string_view(*v));
  }
  Query& bind_blob(std::span<const std::uint8_t> v) {
    static constexpr std::uint8_t kEmpty = 0;
    return check(sqlite3_bind_blob64(s_, next_++, v.empty() ? &kEmpty : v.data(), v.size(), SQLITE_STATIC));
  }

  int step() { return rc_ != SQLITE_OK ? rc_ : sqlite3_step(s_); }
  sqlite3_stmt* get() const { return s_; }

 private:
  Query& check(int rc) {
    if (rc_ == SQLITE_OK) rc_ = rc;
    return *this;
  }
  sqlite3_stmt* s_;
  int next_ = 1;
  int rc_ = SQLITE_OK;
};

struct Store::Impl {
  sqlite3* db = nullptr;
  std::string path;
  std::unordered_map<std::string_view, sqlite3_stmt*> statements;  // keys: the statements' text
  int busy_timeout_ms = 0;                      // OpenOptions::busy_timeout, restored after a checkpoint
  std::int64_t found_version = kSchemaVersion;  // of an existing file, read by check_schema
  // Set by manage_checkpoints: the WAL's frames after the last commit (the hook's count) and the
  // bytes of one frame (the page and its 24-byte header).
  bool wal_hook_installed = false;
  // Pixel files (pixel_files.h): their directory, whether tiles go there, the size cap
  // (OpenOptions), and the files insert_tiles appends to, kept open between batches.
  std::string pixel_dir;
  bool pixels_in_rows = false;
  std::uint64_t max_database_bytes = 0;
  bool pixel_dir_ready = false;
  std::unordered_map<std::int64_t, util::FileHandle> append_files;
  std::uint64_t wal_frames = 0;
  std::uint64_t wal_frame_bytes = 0;

  Impl() = default;
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;
  ~Impl() {
    for (auto& [sql, stmt] : statements) sqlite3_finalize(stmt);
    if (db != nullptr) {
      const int rc = sqlite3_close(db);
      if (rc != SQLITE_OK) util::log_error("{}: closing the database: {}", path, sqlite3_errstr(rc));
    }
  }

  // "<path>: <what>: <sqlite message> (code N)", read while the connection still holds the
  // failing call's message.
  Error error(std::string_view what, int rc) const {
    // A failed bind or step has set the connection's message; SQLITE_MISUSE and friends may not.
    const char* msg = sqlite3_extended_errcode(db) == rc ? sqlite3_errmsg(db) : sqlite3_errstr(rc);
    return Error{fmt::format("{}: {}: {} (code {})", path, what, msg, rc)};
  }

  Result<Query> query(std::string_view sql) {
    auto it = statements.find(sql);
    if (it == statements.end()) {
      sqlite3_stmt* stmt = nullptr;
      const int rc =
          sqlite3_prepare_v3(db, sql.data(), static_cast<int>(sql.size()), SQLITE_PREPARE_PERSISTENT, &stmt, nullptr);
      if (rc != SQLITE_OK) {
        sqlite3_finalize(stmt);
        return error(fmt::format("preparing \"{}\"", sql), rc);
      }
      it = statements.emplace(sql, stmt).first;
    }
    return Query(it->second);
  }

  // Runs a statement without parameters or results.
  Status exec(std::string_view sql) {
    auto q = query(sql);
    if (!q) return q.error();
    const int rc = q.value().step();
    if (rc != SQLITE_DONE) return error(sql, rc);
    return {};
  }

  // Runs an uncached statement (pragmas, DDL at open) and collects the first column of each row
  // as text, at most max_rows of them.
  Result<std::vector<std::string>> exec_rows(std::string_view sql, std::size_t max_rows = SIZE_MAX) {
    sqlite3_stmt* stmt = nullptr;
    int rc = sqlite3_prepare_v2(db, sql.data(), static_cast<int>(sql.size()), &stmt, nullptr);
    if (rc != SQLITE_OK) {
      sqlite3_finalize(stmt);
      return error(sql, rc);
    }
    std::vector<std::string> rows;
    while ((rc = sqlite3_step(stmt)) == SQLITE_ROW) {
      if (rows.size() < max_rows) rows.push_back(column_text(stmt, 0));
    }
    Result<std::vector<std::string>> result = rc == SQLITE_DONE ? Result<std::vector<std::string>>(std::move(rows))
                                                                : Result<std::vector<std::string>>(error(sql, rc));
    sqlite3_finalize(stmt);
    return result;
  }

  // The database file's page size in bytes (never 0).
  Result<std::uint64_t> page_size() {
    auto page = exec_rows("PRAGMA page_size");
    if (!page) return page.error();
    const std::uint64_t bytes = page.value().empty() ? 0 : std::stoull(page.value()[0]);
    if (bytes == 0) return Error{fmt::format("{}: cannot read the page size", path)};
    return bytes;
  }

  // Ends an open transaction after a failure. SQLite may already have rolled it back itself
  // (on SQLITE_FULL, SQLITE_IOERR, SQLITE_NOMEM), in which case there is nothing to do.
  void rollback() {
    if (sqlite3_get_autocommit(db) != 0) return;
    if (Status st = exec(kSqlRollback); !st) util::log_error("{}", st.error().message);
  }

  Status set_config(int op, int value, std::string_view name) {
    const int rc = sqlite3_db_config(db, op, value, nullptr);
    if (rc != SQLITE_OK) return error(fmt::format("setting {}", name), rc);
    return {};
  }

  // An error() message without its leading "<path>: ", for wrapping in a longer message.
  std::string_view detail(const std::string& message) const {
    std::string_view m = message;
    if (m.starts_with(path) && m.substr(path.size()).starts_with(": ")) m.remove_prefix(path.size() + 2);
    return m;
  }

  // The one job `sql` selects with `key` bound, if any; `what` names the lookup in an error.
  template <typename Key>
  Result<std::optional<StoredJob>> select_job(std::string_view sql, const Key& key, std::string_view what) {
    auto q = query(sql);
    if (!q) return q.error();
    const int rc = q.value().bind(key).step();
    if (rc == SQLITE_DONE) return std::optional<StoredJob>();
    if (rc != SQLITE_ROW) return error(what, rc);
    return std::optional<StoredJob>(read_job(q.value().get()));
  }

  Result<CommitResult> insert_tile(const TileWrite& w, std::vector<PendingAppend>& appends);
  Result<PendingAppend*> pending_for(std::vector<PendingAppend>& appends, std::int64_t job);
  // Writes and syncs every pending append and records the files' new committed lengths, inside the
  // caller's transaction, before its COMMIT.
  Status flush_appends(std::vector<PendingAppend>& appends);
  // The job's pixel file, opened (and created) on first use and kept open; bytes past `committed`
  // (a commit that did not finish) are truncated when it is opened.
  Result<int> append_file(std::int64_t job, std::uint64_t committed);
  // A row of kSelectTiles; the pixels read from `file` (opened on first use) when the row points
  // into the job's pixel file.
  Result<StoredTile> read_tile(sqlite3_stmt* s, std::int64_t job, util::FileHandle& file);
  Result<Blob> read_file_pixels(std::int64_t job, std::uint32_t tile, const PixelExtent& extent,
                                util::FileHandle& file);
  Status keep_wal_files();
  Status check_schema();
  Status verify_integrity();
  Status create_schema();
  Status migrate_v1();  // schema version 1 -> 2, on a verified file of version 1
  // Runs `sql` in one transaction: schema version `from` -> from + 1 (`what`, for the log); on a
  // failure the database is unchanged and the error says so.
  Status migrate(int from, std::string_view sql, std::string_view what);
  Status migrate_v2();  // schema version 2 -> 3: the credentials and join_codes tables
  Status migrate_v3();  // schema version 3 -> 4: tile pixels in files
  Result<std::optional<StoredJoinCode>> find_join_code(std::span<const std::uint8_t> secret_sha256);
  Result<bool> name_taken(std::string_view name);
};

}  // namespace dtraced::store
