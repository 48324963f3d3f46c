#include "store/store.h"

#include <fcntl.h>
#include <sqlite3.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <system_error>
#include <tuple>
#include <unordered_map>
#include <utility>

#include <fmt/format.h>

#include "store/coalescing_vfs.h"
#include "store/pixel_files.h"
#include "store/store_impl.h"
#include "util/log.h"

namespace dtraced::store {

using util::Error;
using util::Result;
using util::Status;

namespace {

namespace fs = std::filesystem;

// Drops the database file's clean pages from the kernel's page cache. A checkpoint's copies are
// on disk once it returns (it syncs the file), and the collector reads stored tiles back only on
// a restart or to write an image it no longer holds; so under a steady stream of tiles the file's
// cached pages are dead weight, and page cache reused, rather than ever new memory, is what the
// next checkpoint copies into (on a virtual machine, the first touch of memory the host has not
// backed yet made that copy the checkpoint's main cost). Advice only: nothing fails without it.
void release_cached_pages(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return;
  (void)::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED);
  ::close(fd);
}

// The page size of a new database file (an existing file keeps its own). A 32-px tile (12,360
// bytes of pixels) fits in one 16 KiB page: one WAL frame, two writes into the WAL and one page
// copy at a checkpoint per tile, where 4 KiB pages need a row and three overflow pages (about
// seven writes and four copies). With the WAL-size checkpoints that cut the collector's CPU per
// stored tile by ~11 % (issue 16: tests/bench/collector_capacity.sh, 64 TLS workers, median of 12
// A/B ratios 0.89 on a busy machine, every one below 1). Bytes
// on disk stay about the same for tiles of 12 to 49 KB (+9 % for a 32-px tile with sample
// counts: one overflow page and 2 KB of row on a shared leaf); an empty database is ~200 KiB.
// Earlier measurements of 16 KiB under a heavy load average showed no gain above the noise.
constexpr int kPageSizeBytes = 16384;

// The jobs table's columns, shared by the schema and the upgrade that rebuilds the table.
constexpr std::string_view kJobsColumnsSql = R"sql(
  id INTEGER PRIMARY KEY,
  digest TEXT NOT NULL REFERENCES scenes(digest),
  settings_json TEXT NOT NULL,
  output TEXT NOT NULL,
  priority INTEGER NOT NULL CHECK (priority BETWEEN -2147483648 AND 2147483647),
  tile_size INTEGER NOT NULL CHECK (tile_size BETWEEN 1 AND 4294967295),
  state TEXT NOT NULL CHECK (state IN ('queued', 'rendering', 'done', 'cancelled', 'paused')),
  created_unix INTEGER NOT NULL,
  finished_unix INTEGER NOT NULL,
  client_key TEXT UNIQUE
)sql";

// Every table is STRICT so a wrong type is an error instead of a silent conversion. The CHECKs
// keep the values in the ranges of the C++ types that read them back.
constexpr std::string_view kCreateSchemaSql = R"sql(
CREATE TABLE meta(
  key TEXT PRIMARY KEY NOT NULL,
  value ANY
) STRICT;
CREATE TABLE scenes(
  digest TEXT PRIMARY KEY NOT NULL,
  json TEXT NOT NULL
) STRICT;
CREATE TABLE jobs({}) STRICT;
CREATE TABLE tiles(
  job INTEGER NOT NULL REFERENCES jobs(id),
  tile INTEGER NOT NULL CHECK (tile BETWEEN 0 AND 4294967295),
  pixels BLOB NOT NULL,
  worker TEXT NOT NULL,
  stored_unix INTEGER NOT NULL,
  pixels_offset INTEGER CHECK (pixels_offset >= 0),
  pixels_length INTEGER CHECK (pixels_length >= 0),
  pixels_crc INTEGER CHECK (pixels_crc BETWEEN 0 AND 4294967295),
  PRIMARY KEY (job, tile)
) STRICT;
{}
{}
INSERT INTO meta(key, value) VALUES ('schema_version', 4);
INSERT INTO meta(key, value) VALUES ('last_job_id', 0);
)sql";

// The tables of version 3: credentials and join codes (digests only, never a token or secret).
constexpr std::string_view kCredentialTablesSql = R"sql(
CREATE TABLE credentials(
  name TEXT PRIMARY KEY NOT NULL,
  role TEXT NOT NULL CHECK (role IN ('viewer', 'client', 'worker')),
  token_sha256 BLOB NOT NULL UNIQUE CHECK (length(token_sha256) = 32),
  created_unix INTEGER NOT NULL,
  revoked_unix INTEGER
) STRICT;
CREATE TABLE join_codes(
  secret_sha256 BLOB PRIMARY KEY NOT NULL CHECK (length(secret_sha256) = 32),
  name_hint TEXT,
  created_unix INTEGER NOT NULL,
  expires_unix INTEGER NOT NULL,
  used_unix INTEGER,
  used_by TEXT
) STRICT;
)sql";

// Version 4: tile pixels in files of their own (pixel_files.h). A tile row whose pixels_offset is
// NULL keeps its pixels in the row (every tile of an older file, and OpenOptions::pixels_in_rows);
// otherwise its pixels column is empty and the bytes lie in the job's pixel file. pixel_files
// holds each job's file's committed length: bytes past it belong to no row.
constexpr std::string_view kPixelFilesTableSql = R"sql(
CREATE TABLE pixel_files(
  job INTEGER PRIMARY KEY NOT NULL,
  bytes INTEGER NOT NULL CHECK (bytes >= 0)
) STRICT;
)sql";

// Version 3 -> 4: three columns (NULL in every existing row: its pixels stay in the row, and are
// read from there) and the table of committed lengths. No row is rewritten.
constexpr std::string_view kMigrateV3Sql = R"sql(
ALTER TABLE tiles ADD COLUMN pixels_offset INTEGER CHECK (pixels_offset >= 0);
ALTER TABLE tiles ADD COLUMN pixels_length INTEGER CHECK (pixels_length >= 0);
ALTER TABLE tiles ADD COLUMN pixels_crc INTEGER CHECK (pixels_crc BETWEEN 0 AND 4294967295);
{}
UPDATE meta SET value = 4 WHERE key = 'schema_version';
)sql";

// Version 2 -> 3: the two new tables; nothing else changes.
constexpr std::string_view kMigrateV2Sql = R"sql(
{}
UPDATE meta SET value = 3 WHERE key = 'schema_version';
)sql";

// Version 1 -> 2: the jobs table gains the state 'paused' (its CHECK changes, so the table is
// rebuilt, the way SQLite's documentation describes for any change ALTER TABLE cannot make), and
// meta records the highest job id ever given, so ids of deleted jobs are never handed out again.
// Runs in one transaction with foreign keys off (dropping the old table must not touch tiles).
constexpr std::string_view kMigrateV1Sql = R"sql(
CREATE TABLE jobs_v2({}) STRICT;
INSERT INTO jobs_v2 SELECT id, digest, settings_json, output, priority, tile_size, state, created_unix,
  finished_unix, client_key FROM jobs;
DROP TABLE jobs;
ALTER TABLE jobs_v2 RENAME TO jobs;
INSERT INTO meta(key, value) VALUES ('last_job_id', (SELECT coalesce(max(id), 0) FROM jobs));
UPDATE meta SET value = 2 WHERE key = 'schema_version';
)sql";

// What check_schema expects of an existing file: each table and its columns, in order.
struct TableSpec {
  std::string_view name;
  std::string_view columns;                     // comma-separated, as joined by check_schema
  std::int64_t since_version = 1;               // older files lack the table (their upgrade creates it)
  std::int64_t until_version = kSchemaVersion;  // newer files have other columns (another entry)
};
constexpr TableSpec kTables[] = {
    {"meta", "key,value"},
    {"scenes", "digest,json"},
    {"jobs", "id,digest,settings_json,output,priority,tile_size,state,created_unix,finished_unix,client_key"},
    {"tiles", "job,tile,pixels,worker,stored_unix", 1, 3},
    {"tiles", "job,tile,pixels,worker,stored_unix,pixels_offset,pixels_length,pixels_crc", 4},
    {"pixel_files", "job,bytes", 4},
    {"credentials", "name,role,token_sha256,created_unix,revoked_unix", 3},
    {"join_codes", "secret_sha256,name_hint,created_unix,expires_unix,used_unix,used_by", 3},
};

constexpr std::string_view kRefuse =
    "refusing to open it; the file was left untouched (move it away or restore a backup to start afresh)";

}  // namespace

std::string_view to_string(TileOutcome outcome) {
  constexpr std::string_view kNames[] = {"stored", "already_present", "rejected", "failed"};  // the enum's order
  const auto i = static_cast<std::size_t>(outcome);
  return i < std::size(kNames) ? kNames[i] : "unknown";
}

Store::Store(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Store::Store(Store&&) noexcept = default;
Store& Store::operator=(Store&&) noexcept = default;
Store::~Store() = default;

const std::string& Store::path() const { return impl_->path; }

Status Store::Impl::verify_integrity() {
  auto check = exec_rows("PRAGMA quick_check", kMaxIntegrityLinesReported);
  if (!check) {
    return Error{
        fmt::format("{}: the database is corrupt or unreadable: {}; {}", path, detail(check.error().message), kRefuse)};
  }
  const auto& lines = check.value();
  if (lines.size() != 1 || lines[0] != "ok") {
    std::string report;
    for (const auto& line : lines) report += fmt::format("\n  {}", line);
    return Error{fmt::format("{}: the database is corrupt (PRAGMA quick_check reports):{}\n{}", path, report, kRefuse)};
  }
  auto fk = exec_rows("PRAGMA foreign_key_check", kMaxIntegrityLinesReported);
  if (!fk) {
    return Error{
        fmt::format("{}: the database is corrupt or unreadable: {}; {}", path, detail(fk.error().message), kRefuse)};
  }
  if (!fk.value().empty()) {
    return Error{
        fmt::format("{}: the database has rows whose references are missing (PRAGMA foreign_key_check, "
                    "first table: {}); {}",
                    path, fk.value().front(), kRefuse)};
  }
  return {};
}

Status Store::Impl::check_schema() {
  constexpr std::string_view kSql =
      "SELECT name FROM sqlite_schema WHERE type = 'table' AND name NOT LIKE 'sqlite\\_%' ESCAPE '\\'";
  auto tables = exec_rows(kSql);
  if (!tables)
    return Error{fmt::format("{}: cannot list tables: {}; {}", path, detail(tables.error().message), kRefuse)};
  auto has_table = [&](std::string_view name) {
    for (const auto& t : tables.value()) {
      if (t == name) return true;
    }
    return false;
  };
  if (!has_table("meta")) {
    return Error{
        fmt::format("{}: the database has tables but no meta table: not a dtraced database; {}", path, kRefuse)};
  }
  {
    constexpr std::string_view kSql = "SELECT value FROM meta WHERE key = 'schema_version'";
    auto q = query(kSql);
    if (!q) return q.error();
    const int rc = q.value().step();
    if (rc == SQLITE_DONE) {
      return Error{fmt::format("{}: the meta table has no schema_version; {}", path, kRefuse)};
    }
    if (rc != SQLITE_ROW) return error("reading the schema version", rc);
    sqlite3_stmt* s = q.value().get();
    if (sqlite3_column_type(s, 0) != SQLITE_INTEGER) {
      return Error{fmt::format("{}: schema_version is not an integer ('{}'); {}", path, column_text(s, 0), kRefuse)};
    }
    const std::int64_t version = sqlite3_column_int64(s, 0);
    if (version < kOldestMigratedVersion || version > kSchemaVersion) {
      return Error{
          fmt::format("{}: schema version {} is not a version this dtraced uses ({}) or upgrades ({} to {}); {}", path,
                      version, kSchemaVersion, kOldestMigratedVersion, kSchemaVersion - 1, kRefuse)};
    }
    found_version = version;
  }
  for (const TableSpec& spec : kTables) {
    if (spec.since_version > found_version || spec.until_version < found_version) continue;
    if (!has_table(spec.name)) {
      return Error{
          fmt::format("{}: schema version {} but table '{}' is missing; {}", path, found_version, spec.name, kRefuse)};
    }
    constexpr std::string_view kSql = "SELECT name FROM pragma_table_info(?1) ORDER BY cid";
    auto q = query(kSql);
    if (!q) return q.error();
    q.value().bind(spec.name);
    std::string columns;
    int rc;
    while ((rc = q.value().step()) == SQLITE_ROW) {
      if (!columns.empty()) columns += ',';
      columns += column_text(q.value().get(), 0);
    }
    if (rc != SQLITE_DONE) return error(fmt::format("reading the columns of table '{}'", spec.name), rc);
    if (columns != spec.columns) {
      return Error{fmt::format("{}: table '{}' has columns ({}) where schema version {} has ({}); {}", path, spec.name,
                               columns, found_version, spec.columns, kRefuse)};
    }
  }
  return {};
}

Status Store::Impl::create_schema() {
  if (auto st = exec(kSqlBegin); !st) return st;
  char* message = nullptr;
  const std::string sql =
      fmt::format(fmt::runtime(kCreateSchemaSql), kJobsColumnsSql, kCredentialTablesSql, kPixelFilesTableSql);
  const int rc = sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &message);
  if (rc != SQLITE_OK) {
    Error e{fmt::format("{}: creating the schema: {} (code {})", path, message != nullptr ? message : "?", rc)};
    sqlite3_free(message);
    rollback();
    return e;
  }
  if (auto st = exec(kSqlCommit); !st) {
    rollback();
    return st;
  }
  return {};
}

Status Store::Impl::migrate_v1() {
  // Outside any transaction (SQLite ignores the pragma inside one); back on at the end, whatever
  // happened.
  if (auto st = exec_rows("PRAGMA foreign_keys = OFF"); !st) return st.error();
  Status result = [&]() -> Status {
    if (auto st = exec(kSqlBegin); !st) return st;
    char* message = nullptr;
    const std::string sql = fmt::format(fmt::runtime(kMigrateV1Sql), kJobsColumnsSql);
    const int rc = sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &message);
    if (rc != SQLITE_OK) {
      Error e{fmt::format("{}: upgrading the schema from version 1 to 2: {} (code {}); the database is unchanged", path,
                          message != nullptr ? message : "?", rc)};
      sqlite3_free(message);
      rollback();
      return e;
    }
    auto fk = exec_rows("PRAGMA foreign_key_check", kMaxIntegrityLinesReported);
    if (!fk || !fk.value().empty()) {
      rollback();
      return Error{
          fmt::format("{}: upgrading the schema from version 1 to 2 broke a reference; the database is "
                      "unchanged",
                      path)};
    }
    if (auto st = exec(kSqlCommit); !st) {
      rollback();
      return st;
    }
    return {};
  }();
  if (auto st = exec_rows("PRAGMA foreign_keys = ON"); !st && result) return st.error();
  if (!result) return result;
  util::log_info("{}: upgraded the schema from version 1 to 2 (jobs may be paused; ids are never reused)", path);
  // Space of deleted jobs goes back to the file system only with incremental auto-vacuum, which an
  // existing file gets by a VACUUM (a copy of the whole file: it needs that much free space, and
  // time). A large file is left as it is, so that start-up stays within a service manager's start
  // timeout; then, and when the VACUUM fails, freed pages are reused for new tiles instead.
  const auto size = exec_rows("SELECT page_count * page_size FROM pragma_page_count, pragma_page_size");
  if (!size) return size.error();
  const std::uint64_t bytes = size.value().empty() ? 0 : std::stoull(size.value()[0]);
  if (bytes > kMaxUpgradeVacuumBytes) {
    util::log_warn(
        "{}: {} MiB is too large to convert to incremental vacuum at start-up; space of deleted jobs is "
        "reused, not released (with the collector stopped, sqlite3 {} 'PRAGMA auto_vacuum = 2; VACUUM' "
        "converts it)",
        path, bytes >> 20, path);
    return {};
  }
  if (auto st = exec_rows("PRAGMA auto_vacuum = INCREMENTAL"); !st) return st.error();
  if (auto st = exec_rows("VACUUM"); !st) {
    util::log_warn("{}: could not switch to incremental vacuum ({}); space of deleted jobs is reused, not released",
                   path, detail(st.error().message));
  }
  return {};
}

Status Store::Impl::migrate(int from, std::string_view sql, std::string_view what) {
  if (auto st = exec(kSqlBegin); !st) return st;
  char* message = nullptr;
  const int rc = sqlite3_exec(db, std::string(sql).c_str(), nullptr, nullptr, &message);
  if (rc != SQLITE_OK) {
    Error e{fmt::format("{}: upgrading the schema from version {} to {}: {} (code {}); the database is unchanged", path,
                        from, from + 1, message != nullptr ? message : "?", rc)};
    sqlite3_free(message);
    rollback();
    return e;
  }
  if (auto st = exec(kSqlCommit); !st) {
    rollback();
    return st;
  }
  util::log_info("{}: upgraded the schema from version {} to {} ({})", path, from, from + 1, what);
  return {};
}

Status Store::Impl::migrate_v2() {
  return migrate(2, fmt::format(fmt::runtime(kMigrateV2Sql), kCredentialTablesSql), "credentials and join codes");
}

Status Store::Impl::migrate_v3() {
  return migrate(3, fmt::format(fmt::runtime(kMigrateV3Sql), kPixelFilesTableSql),
                 "new tiles' pixels in files of their own");
}

Result<Store> Store::open(const std::string& state_dir, const OpenOptions& options) {
  std::error_code ec;
  fs::create_directories(state_dir, ec);
  if (ec) return Error{fmt::format("{}: cannot create the state directory: {}", state_dir, ec.message())};
  if (!fs::is_directory(state_dir, ec)) return Error{fmt::format("{}: not a directory", state_dir)};

  auto impl = std::make_unique<Impl>();
  impl->path = (fs::path(state_dir) / kDatabaseFileName).string();
  impl->pixel_dir = (fs::path(state_dir) / kPixelDirName).string();
  impl->pixels_in_rows = options.pixels_in_rows;
  impl->max_database_bytes = options.max_database_bytes;
  const std::string& path = impl->path;
  const fs::file_status status = fs::status(path, ec);
  if (ec && ec != std::errc::no_such_file_or_directory) {
    return Error{fmt::format("{}: cannot inspect: {}", path, ec.message())};
  }
  const bool exists = fs::exists(status);
  if (exists && !fs::is_regular_file(status)) {
    return Error{fmt::format("{}: exists but is not a regular file; {}", path, kRefuse)};
  }

  // Never SQLITE_OPEN_CREATE on an existing file: whatever is there gets inspected, not replaced.
  // The coalescing VFS (coalescing_vfs.h) turns a commit's and a checkpoint's many writes into few.
  int flags = SQLITE_OPEN_READWRITE | SQLITE_OPEN_NOMUTEX | SQLITE_OPEN_EXRESCODE;
  if (!exists) flags |= SQLITE_OPEN_CREATE;
  const int rc = sqlite3_open_v2(path.c_str(), &impl->db, flags, coalescing_vfs_name());
  if (rc != SQLITE_OK) {
    return Error{
        fmt::format("{}: cannot open: {}", path, impl->db != nullptr ? sqlite3_errmsg(impl->db) : sqlite3_errstr(rc))};
  }
  sqlite3* db = impl->db;

  // Until the file is known to be ours and sound, nothing may write to it: query_only refuses
  // writes, and without a checkpoint on close a WAL left by a crash stays where it is.
  // Defensive mode and an untrusted schema: a hostile file cannot make SQL do more than read it.
  for (const auto& [op, value, name] : {std::tuple{SQLITE_DBCONFIG_NO_CKPT_ON_CLOSE, 1, "no checkpoint on close"},
                                        std::tuple{SQLITE_DBCONFIG_DEFENSIVE, 1, "defensive mode"},
                                        std::tuple{SQLITE_DBCONFIG_TRUSTED_SCHEMA, 0, "untrusted schema"}}) {
    if (auto st = impl->set_config(op, value, name); !st) return st.error();
  }
  if (auto st = impl->exec_rows("PRAGMA query_only = ON"); !st) return st.error();
  impl->busy_timeout_ms = static_cast<int>(options.busy_timeout.count());
  if (const int brc = sqlite3_busy_timeout(db, impl->busy_timeout_ms); brc != SQLITE_OK) {
    return impl->error("setting the busy timeout", brc);
  }
  if (sqlite3_db_readonly(db, "main") == 1) {
    return Error{fmt::format("{}: the file is not writable; {}", path, kRefuse)};
  }

  // The first read parses the header: "file is not a database" shows up here (at prepare time).
  constexpr std::string_view kSql = "SELECT count(*) FROM sqlite_schema";
  auto count = impl->exec_rows(kSql);
  if (!count) {
    if ((sqlite3_extended_errcode(db) & 0xff) == SQLITE_NOTADB) {
      return Error{fmt::format("{}: not an SQLite database ({}); {}", path, sqlite3_errmsg(db), kRefuse)};
    }
    return Error{
        fmt::format("{}: cannot read the database: {}; {}", path, impl->detail(count.error().message), kRefuse)};
  }
  const std::int64_t objects = count.value().empty() ? 0 : std::stoll(count.value()[0]);
  if (options.verify_integrity) {
    if (auto st = impl->verify_integrity(); !st) return st.error();
  }
  const bool fresh = objects == 0;
  if (!fresh) {
    if (auto st = impl->check_schema(); !st) return st.error();
  }

  // From here on the file is ours to write. synchronous = FULL: every COMMIT syncs the WAL, which
  // is also what makes the coalescing VFS's buffered writes visible to other connections.
  for (const char* pragma : {"PRAGMA query_only = OFF", "PRAGMA synchronous = FULL", "PRAGMA foreign_keys = ON"}) {
    if (auto st = impl->exec_rows(pragma); !st) return st.error();
  }
  if (fresh) {
    // The page size and auto-vacuum mode only take effect before the first table exists (and the
    // page size before WAL mode). Incremental auto-vacuum lets delete_job return space to the file
    // system.
    if (auto st = impl->exec_rows(fmt::format("PRAGMA page_size = {}", kPageSizeBytes)); !st) return st.error();
    if (auto st = impl->exec_rows("PRAGMA auto_vacuum = INCREMENTAL"); !st) return st.error();
  }
  auto mode = impl->exec_rows("PRAGMA journal_mode = WAL");
  if (!mode) return mode.error();
  if (mode.value().size() != 1 || mode.value()[0] != "wal") {
    return Error{fmt::format("{}: cannot switch to WAL journaling (journal mode is '{}')", path,
                             mode.value().empty() ? "?" : mode.value()[0])};
  }
  if (auto st = impl->exec_rows(fmt::format("PRAGMA journal_size_limit = {}", kJournalSizeLimitBytes)); !st) {
    return st.error();
  }
  if (auto st = impl->keep_wal_files(); !st) return st.error();
  if (fresh) {
    if (auto st = impl->create_schema(); !st) return st.error();
    util::log_info("{}: created a new database (schema version {})", path, kSchemaVersion);
  } else {
    if (impl->found_version == 1) {
      if (auto st = impl->migrate_v1(); !st) return st.error();
    }
    if (impl->found_version <= 2) {
      if (auto st = impl->migrate_v2(); !st) return st.error();
    }
    if (impl->found_version <= 3) {
      if (auto st = impl->migrate_v3(); !st) return st.error();
    }
  }
  // Optional in every version (store.h): a file made before it existed gets it now, unchanged
  // otherwise; no foreign key, so a dtraced that does not know it can still delete jobs.
  if (auto st = impl->exec_rows(
          "CREATE TABLE IF NOT EXISTS job_tile_costs(job INTEGER PRIMARY KEY NOT NULL, costs BLOB NOT NULL) STRICT");
      !st) {
    return st.error();
  }
  if (options.max_database_bytes > 0) {
    const Result<std::uint64_t> page = impl->page_size();
    if (!page) return page.error();
    const std::uint64_t pages = (options.max_database_bytes + page.value() - 1) / page.value();
    if (auto st = impl->exec_rows(fmt::format("PRAGMA max_page_count = {}", pages)); !st) return st.error();
  }
  if (auto st = impl->set_config(SQLITE_DBCONFIG_NO_CKPT_ON_CLOSE, 0, "checkpoint on close"); !st) {
    return st.error();
  }
  return Store(std::move(impl));
}

Status Store::transaction(const std::function<Status()>& body) {
  if (sqlite3_get_autocommit(impl_->db) == 0) {
    return Error{fmt::format("{}: transaction() called inside a transaction", impl_->path)};
  }
  if (auto st = impl_->exec(kSqlBegin); !st) return st;
  Status st;
  try {
    st = body();
  } catch (...) {
    impl_->rollback();
    throw;
  }
  if (!st) {
    impl_->rollback();
    return st;
  }
  if (auto cst = impl_->exec(kSqlCommit); !cst) {
    impl_->rollback();
    return cst;
  }
  return {};
}

Status Store::Impl::keep_wal_files() {
  int persist = 1;
  const int rc = sqlite3_file_control(db, "main", SQLITE_FCNTL_PERSIST_WAL, &persist);
  if (rc != SQLITE_OK) return error("keeping the WAL files", rc);
  return {};
}

Status Store::manage_checkpoints() {
  if (impl_->wal_hook_installed) return {};
  const Result<std::uint64_t> page = impl_->page_size();
  if (!page) return page.error();
  constexpr std::uint64_t kWalFrameHeaderBytes = 24;
  impl_->wal_frame_bytes = page.value() + kWalFrameHeaderBytes;
  // The hook remembers the WAL's length after each commit. Installing it replaces SQLite's own
  // automatic checkpoints (which use the same hook), so nothing is checkpointed inside a COMMIT.
  constexpr auto note_wal_frames = [](void* impl, sqlite3*, const char*, int frames) {
    static_cast<Impl*>(impl)->wal_frames = frames > 0 ? static_cast<std::uint64_t>(frames) : 0;
    return SQLITE_OK;
  };
  sqlite3_wal_hook(impl_->db, note_wal_frames, impl_.get());
  impl_->wal_hook_installed = true;
  return {};
}

Result<Store> Store::open_checkpoint_connection() const {
  auto impl = std::make_unique<Impl>();
  impl->path = impl_->path;
  impl->pixel_dir = impl_->pixel_dir;
  impl->busy_timeout_ms = impl_->busy_timeout_ms;
  const int flags = SQLITE_OPEN_READWRITE | SQLITE_OPEN_NOMUTEX | SQLITE_OPEN_EXRESCODE;
  if (const int rc = sqlite3_open_v2(impl->path.c_str(), &impl->db, flags, coalescing_vfs_name()); rc != SQLITE_OK) {
    return Error{fmt::format("{}: cannot open a checkpoint connection: {}", impl->path,
                             impl->db != nullptr ? sqlite3_errmsg(impl->db) : sqlite3_errstr(rc))};
  }
  if (auto st = impl->set_config(SQLITE_DBCONFIG_NO_CKPT_ON_CLOSE, 1, "no checkpoint on close"); !st) {
    return st.error();
  }
  if (const int rc = sqlite3_busy_timeout(impl->db, impl->busy_timeout_ms); rc != SQLITE_OK) {
    return impl->error("setting the busy timeout", rc);
  }
  for (const char* pragma : {"PRAGMA query_only = ON", "PRAGMA synchronous = FULL"}) {
    if (auto st = impl->exec_rows(pragma); !st) return st.error();
  }
  if (auto st = impl->exec_rows(fmt::format("PRAGMA journal_size_limit = {}", kJournalSizeLimitBytes)); !st) {
    return st.error();
  }
  // Should this connection close last, the -wal and -shm files stay, as with the writer's.
  if (auto st = impl->keep_wal_files(); !st) return st.error();
  // Reading the journal mode opens the database and its WAL, which a checkpoint needs.
  auto mode = impl->exec_rows("PRAGMA journal_mode");
  if (!mode) return mode.error();
  if (mode.value().size() != 1 || mode.value()[0] != "wal") {
    return Error{fmt::format("{}: a checkpoint connection needs WAL journaling (journal mode is '{}')", impl->path,
                             mode.value().empty() ? "?" : mode.value()[0])};
  }
  return Store(std::move(impl));
}

std::uint64_t Store::wal_bytes() const { return impl_->wal_frames * impl_->wal_frame_bytes; }

Result<CheckpointResult> Store::checkpoint(CheckpointMode mode) {
  // A zero busy timeout: a reader in the way makes the checkpoint partial, never a wait on the
  // writer thread (acknowledgements would wait with it).
  sqlite3_busy_timeout(impl_->db, 0);
  CheckpointResult result;
  const int how = mode == CheckpointMode::kTruncate ? SQLITE_CHECKPOINT_TRUNCATE : SQLITE_CHECKPOINT_PASSIVE;
  const int rc = sqlite3_wal_checkpoint_v2(impl_->db, "main", how, &result.wal_frames, &result.copied_frames);
  sqlite3_busy_timeout(impl_->db, impl_->busy_timeout_ms);
  if (rc == SQLITE_BUSY) return result;
  if (rc != SQLITE_OK) return impl_->error("checkpointing the WAL", rc);
  // After a TRUNCATE checkpoint that succeeded, SQLite reports an empty log; a PASSIVE one that
  // copied every frame reports as many copied as there are.
  if (mode == CheckpointMode::kTruncate) {
    result.truncated = result.wal_frames == 0 && result.copied_frames == 0;
    result.complete = result.truncated;
  } else {
    result.complete = result.copied_frames == result.wal_frames;
  }
  // Every frame is in the database file: the next commit starts the WAL over.
  if (result.complete) impl_->wal_frames = 0;
  if (result.copied_frames > 0 || result.truncated) release_cached_pages(impl_->path);
  return result;
}

}  // namespace dtraced::store
