#include "store/store.h"

#include <sqlite3.h>

#include <cstring>
#include <filesystem>
#include <system_error>
#include <tuple>
#include <unordered_map>
#include <utility>

#include <fmt/format.h>

#include "util/log.h"

namespace dtraced::store {

using util::Error;
using util::Result;
using util::Status;

namespace {

namespace fs = std::filesystem;

// The page size of a new database file: SQLite's default. Tiles of tens of kilobytes live mostly
// in overflow pages, but 16 and 64 KiB pages measured no faster for 49 KB tiles (the time goes
// to the WAL fsync and the checkpoint copy, not to per-page overhead), and small rows stay compact.
constexpr int kPageSizeBytes = 4096;

// Every table is STRICT so a wrong type is an error instead of a silent conversion. The CHECKs
// keep the values in the ranges of the C++ types that read them back.
constexpr const char* kCreateSchemaSql = R"sql(
CREATE TABLE meta(
  key TEXT PRIMARY KEY NOT NULL,
  value ANY
) STRICT;
CREATE TABLE scenes(
  digest TEXT PRIMARY KEY NOT NULL,
  json TEXT NOT NULL
) STRICT;
CREATE TABLE jobs(
  id INTEGER PRIMARY KEY,
  digest TEXT NOT NULL REFERENCES scenes(digest),
  settings_json TEXT NOT NULL,
  output TEXT NOT NULL,
  priority INTEGER NOT NULL CHECK (priority BETWEEN -2147483648 AND 2147483647),
  tile_size INTEGER NOT NULL CHECK (tile_size BETWEEN 1 AND 4294967295),
  state TEXT NOT NULL CHECK (state IN ('queued', 'rendering', 'done', 'cancelled')),
  created_unix INTEGER NOT NULL,
  finished_unix INTEGER NOT NULL,
  client_key TEXT UNIQUE
) STRICT;
CREATE TABLE tiles(
  job INTEGER NOT NULL REFERENCES jobs(id),
  tile INTEGER NOT NULL CHECK (tile BETWEEN 0 AND 4294967295),
  pixels BLOB NOT NULL,
  worker TEXT NOT NULL,
  stored_unix INTEGER NOT NULL,
  PRIMARY KEY (job, tile)
) STRICT;
INSERT INTO meta(key, value) VALUES ('schema_version', 1);
)sql";

// What check_schema expects of an existing file: each table and its columns, in order.
struct TableSpec {
  std::string_view name;
  std::string_view columns;  // comma-separated, as joined by check_schema
};
constexpr TableSpec kTables[] = {
    {"meta", "key,value"},
    {"scenes", "digest,json"},
    {"jobs", "id,digest,settings_json,output,priority,tile_size,state,created_unix,finished_unix,client_key"},
    {"tiles", "job,tile,pixels,worker,stored_unix"},
};

constexpr std::string_view kRefuse =
    "refusing to open it; the file was left untouched (move it away or restore a backup to start afresh)";

// Statements used in several places. The others stand in the function that runs them; the cache
// of prepared statements is keyed by their text.
constexpr std::string_view kSqlBegin = "BEGIN IMMEDIATE";
constexpr std::string_view kSqlCommit = "COMMIT";
constexpr std::string_view kSqlRollback = "ROLLBACK";
// The job queries select the columns in the order read_job expects.
constexpr std::string_view kSelectJobs =
    "SELECT id, digest, settings_json, output, priority, tile_size, state, created_unix, finished_unix, client_key "
    "FROM jobs ";

std::string column_text(sqlite3_stmt* s, int i) {
  const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(s, i));
  const int n = sqlite3_column_bytes(s, i);
  return p != nullptr ? std::string(p, static_cast<std::size_t>(n)) : std::string();
}

Blob column_blob(sqlite3_stmt* s, int i) {
  const auto* p = static_cast<const std::uint8_t*>(sqlite3_column_blob(s, i));
  const int n = sqlite3_column_bytes(s, i);
  return p != nullptr ? Blob(p, p + n) : Blob();
}

// Column order of kSelectJobs. The schema's CHECKs keep the casts exact.
StoredJob read_job(sqlite3_stmt* s) {
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
  return job;
}

StoredTile read_tile(sqlite3_stmt* s) {
  StoredTile t;
  t.tile = static_cast<std::uint32_t>(sqlite3_column_int64(s, 0));
  t.pixels = column_blob(s, 1);
  t.worker = column_text(s, 2);
  t.stored_unix = sqlite3_column_int64(s, 3);
  return t;
}

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

}  // namespace

std::string_view to_string(TileOutcome outcome) {
  constexpr std::string_view kNames[] = {"stored", "already_present", "rejected", "failed"};  // the enum's order
  const auto i = static_cast<std::size_t>(outcome);
  return i < std::size(kNames) ? kNames[i] : "unknown";
}

struct Store::Impl {
  sqlite3* db = nullptr;
  std::string path;
  std::unordered_map<std::string_view, sqlite3_stmt*> statements;  // keys: the statements' text
  int busy_timeout_ms = 0;  // OpenOptions::busy_timeout, restored after a checkpoint

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

  Result<CommitResult> insert_tile(const TileWrite& w);
  Status keep_wal_files();
  Status check_schema();
  Status verify_integrity();
  Status create_schema();
};

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
    if (version != kSchemaVersion) {
      return Error{fmt::format("{}: schema version {} is not the version this dtraced uses ({}); {}", path, version,
                               kSchemaVersion, kRefuse)};
    }
  }
  for (const TableSpec& spec : kTables) {
    if (!has_table(spec.name)) {
      return Error{
          fmt::format("{}: schema version {} but table '{}' is missing; {}", path, kSchemaVersion, spec.name, kRefuse)};
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
                               columns, kSchemaVersion, spec.columns, kRefuse)};
    }
  }
  return {};
}

Status Store::Impl::create_schema() {
  if (auto st = exec(kSqlBegin); !st) return st;
  char* message = nullptr;
  const int rc = sqlite3_exec(db, kCreateSchemaSql, nullptr, nullptr, &message);
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

Result<Store> Store::open(const std::string& state_dir, const OpenOptions& options) {
  std::error_code ec;
  fs::create_directories(state_dir, ec);
  if (ec) return Error{fmt::format("{}: cannot create the state directory: {}", state_dir, ec.message())};
  if (!fs::is_directory(state_dir, ec)) return Error{fmt::format("{}: not a directory", state_dir)};

  auto impl = std::make_unique<Impl>();
  impl->path = (fs::path(state_dir) / kDatabaseFileName).string();
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
  int flags = SQLITE_OPEN_READWRITE | SQLITE_OPEN_NOMUTEX | SQLITE_OPEN_EXRESCODE;
  if (!exists) flags |= SQLITE_OPEN_CREATE;
  const int rc = sqlite3_open_v2(path.c_str(), &impl->db, flags, nullptr);
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

  // From here on the file is ours to write.
  for (const char* pragma : {"PRAGMA query_only = OFF", "PRAGMA synchronous = FULL", "PRAGMA foreign_keys = ON"}) {
    if (auto st = impl->exec_rows(pragma); !st) return st.error();
  }
  if (fresh) {
    // The page size only takes effect before the first table exists and before WAL mode.
    if (auto st = impl->exec_rows(fmt::format("PRAGMA page_size = {}", kPageSizeBytes)); !st) return st.error();
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
  }
  if (options.max_database_bytes > 0) {
    auto page = impl->exec_rows("PRAGMA page_size");
    if (!page) return page.error();
    const std::uint64_t page_bytes = page.value().empty() ? 0 : std::stoull(page.value()[0]);
    if (page_bytes == 0) return Error{fmt::format("{}: cannot read the page size", path)};
    const std::uint64_t pages = (options.max_database_bytes + page_bytes - 1) / page_bytes;
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

Status Store::put_scene(std::string_view digest, std::string_view json) {
  constexpr std::string_view kSql = "INSERT INTO scenes(digest, json) VALUES (?1, ?2) ON CONFLICT DO NOTHING";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(digest).bind(json).step();
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("storing scene {}", digest), rc);
  return {};
}

Result<std::optional<std::string>> Store::get_scene(std::string_view digest) {
  constexpr std::string_view kSql = "SELECT json FROM scenes WHERE digest = ?1";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(digest).step();
  if (rc == SQLITE_DONE) return std::optional<std::string>();
  if (rc != SQLITE_ROW) return impl_->error(fmt::format("reading scene {}", digest), rc);
  return std::optional<std::string>(column_text(q.value().get(), 0));
}

Result<std::int64_t> Store::insert_job(const StoredJob& job) {
  constexpr std::string_view kSql =
      "INSERT INTO jobs(digest, settings_json, output, priority, tile_size, state, created_unix, finished_unix, "
      "client_key) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value()
                     .bind(job.digest)
                     .bind(job.settings_json)
                     .bind(job.output)
                     .bind(std::int64_t{job.priority})
                     .bind(std::int64_t{job.tile_size})
                     .bind(job.state)
                     .bind(job.created_unix)
                     .bind(job.finished_unix)
                     .bind_optional(job.client_key)
                     .step();
  if (rc != SQLITE_DONE) return impl_->error("inserting a job", rc);
  return std::int64_t{sqlite3_last_insert_rowid(impl_->db)};
}

Status Store::set_job_state(std::int64_t id, std::string_view state, std::int64_t finished_unix) {
  constexpr std::string_view kSql = "UPDATE jobs SET state = ?2, finished_unix = ?3 WHERE id = ?1";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(id).bind(state).bind(finished_unix).step();
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("setting the state of job {}", id), rc);
  if (sqlite3_changes64(impl_->db) != 1) return Error{fmt::format("{}: no job {}", impl_->path, id)};
  return {};
}

Result<StateChange> Store::change_job_state(std::int64_t id, std::span<const std::string_view> from,
                                            std::string_view to, std::int64_t finished_unix) {
  if (from.empty() || from.size() > kMaxStateChangeSources) {
    return Error{fmt::format("{}: changing the state of job {}: {} source states (1 to {})", impl_->path, id,
                             from.size(), kMaxStateChangeSources)};
  }
  {
    // Fixed text (the statement cache is keyed by it): unused slots repeat the first state.
    constexpr std::string_view kSql =
        "UPDATE jobs SET state = ?2, finished_unix = ?3 WHERE id = ?1 AND state IN (?4, ?5, ?6, ?7)";
    auto q = impl_->query(kSql);
    if (!q) return q.error();
    q.value().bind(id).bind(to).bind(finished_unix);
    for (std::size_t i = 0; i < kMaxStateChangeSources; ++i) q.value().bind(from[i < from.size() ? i : 0]);
    const int rc = q.value().step();
    if (rc != SQLITE_DONE) return impl_->error(fmt::format("changing the state of job {}", id), rc);
    if (sqlite3_changes64(impl_->db) == 1) return StateChange{true, std::string(to)};
  }
  constexpr std::string_view kSql = "SELECT state FROM jobs WHERE id = ?1";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(id).step();
  if (rc == SQLITE_DONE) return Error{fmt::format("{}: no job {}", impl_->path, id)};
  if (rc != SQLITE_ROW) return impl_->error(fmt::format("reading the state of job {}", id), rc);
  return StateChange{false, column_text(q.value().get(), 0)};
}

Status Store::set_job_priority(std::int64_t id, std::int32_t priority) {
  constexpr std::string_view kSql = "UPDATE jobs SET priority = ?2 WHERE id = ?1";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(id).bind(std::int64_t{priority}).step();
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("setting the priority of job {}", id), rc);
  if (sqlite3_changes64(impl_->db) != 1) return Error{fmt::format("{}: no job {}", impl_->path, id)};
  return {};
}

Result<std::vector<StoredJob>> Store::list_jobs() {
  static const std::string kSql = std::string(kSelectJobs) + "ORDER BY id";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  std::vector<StoredJob> jobs;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) jobs.push_back(read_job(q.value().get()));
  if (rc != SQLITE_DONE) return impl_->error("listing jobs", rc);
  return jobs;
}

Result<std::optional<StoredJob>> Store::get_job(std::int64_t id) {
  static const std::string kSql = std::string(kSelectJobs) + "WHERE id = ?1";
  return impl_->select_job(kSql, id, fmt::format("reading job {}", id));
}

Result<std::optional<StoredJob>> Store::find_job_by_key(std::string_view client_key) {
  static const std::string kSql = std::string(kSelectJobs) + "WHERE client_key = ?1";
  return impl_->select_job(kSql, client_key, "looking up a job by client key");
}

Result<CommitResult> Store::Impl::insert_tile(const TileWrite& w) {
  {
    constexpr std::string_view kSql =
        "INSERT OR IGNORE INTO tiles(job, tile, pixels, worker, stored_unix) VALUES (?1, ?2, ?3, ?4, ?5)";
    auto q = query(kSql);
    if (!q) return q.error();
    const int rc =
        q.value().bind(w.job).bind(std::int64_t{w.tile}).bind_blob(w.pixels).bind(w.worker).bind(w.stored_unix).step();
    if (rc == SQLITE_DONE) {
      if (sqlite3_changes64(db) == 1) return CommitResult{TileOutcome::kStored, false, {}};
    } else if ((rc & 0xff) == SQLITE_CONSTRAINT && sqlite3_get_autocommit(db) == 0) {
      // OR IGNORE covers the primary key; a missing job (foreign key) fails this statement only.
      return CommitResult{TileOutcome::kRejected, false,
                          error(fmt::format("storing tile {} of job {}", w.tile, w.job), rc).message};
    } else {
      return error(fmt::format("storing tile {} of job {}", w.tile, w.job), rc);
    }
  }
  // Already present: compare the bytes (duplicates are rare, so the extra read is cheap overall).
  constexpr std::string_view kSql = "SELECT pixels FROM tiles WHERE job = ?1 AND tile = ?2";
  auto q = query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(w.job).bind(std::int64_t{w.tile}).step();
  if (rc != SQLITE_ROW) return error(fmt::format("reading back tile {} of job {}", w.tile, w.job), rc);
  sqlite3_stmt* s = q.value().get();
  const void* stored = sqlite3_column_blob(s, 0);
  const auto n = static_cast<std::size_t>(sqlite3_column_bytes(s, 0));
  const bool identical = n == w.pixels.size() && (n == 0 || std::memcmp(stored, w.pixels.data(), n) == 0);
  return CommitResult{TileOutcome::kAlreadyPresent, identical, {}};
}

Result<std::vector<CommitResult>> Store::insert_tiles(std::span<const TileWrite> writes) {
  const bool own_transaction = sqlite3_get_autocommit(impl_->db) != 0;
  if (own_transaction) {
    if (auto st = impl_->exec(kSqlBegin); !st) return st.error();
  }
  std::vector<CommitResult> results;
  results.reserve(writes.size());
  for (const TileWrite& w : writes) {
    auto r = impl_->insert_tile(w);
    if (!r) {
      if (own_transaction) impl_->rollback();
      return r.error();
    }
    results.push_back(std::move(r).value());
  }
  if (own_transaction) {
    if (auto st = impl_->exec(kSqlCommit); !st) {
      impl_->rollback();
      return st.error();
    }
  }
  return results;
}

Result<std::vector<std::uint32_t>> Store::stored_tiles(std::int64_t job) {
  constexpr std::string_view kSql = "SELECT tile FROM tiles WHERE job = ?1 ORDER BY tile";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  q.value().bind(job);
  std::vector<std::uint32_t> tiles;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) {
    tiles.push_back(static_cast<std::uint32_t>(sqlite3_column_int64(q.value().get(), 0)));
  }
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("listing the tiles of job {}", job), rc);
  return tiles;
}

Result<std::uint64_t> Store::count_tiles(std::int64_t job) {
  constexpr std::string_view kSql = "SELECT count(*) FROM tiles WHERE job = ?1";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(job).step();
  if (rc != SQLITE_ROW) return impl_->error(fmt::format("counting the tiles of job {}", job), rc);
  return static_cast<std::uint64_t>(sqlite3_column_int64(q.value().get(), 0));
}

Result<std::optional<StoredTile>> Store::get_tile(std::int64_t job, std::uint32_t tile) {
  constexpr std::string_view kSql = "SELECT tile, pixels, worker, stored_unix FROM tiles WHERE job = ?1 AND tile = ?2";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(job).bind(std::int64_t{tile}).step();
  if (rc == SQLITE_DONE) return std::optional<StoredTile>();
  if (rc != SQLITE_ROW) return impl_->error(fmt::format("reading tile {} of job {}", tile, job), rc);
  return std::optional<StoredTile>(read_tile(q.value().get()));
}

Result<std::vector<StoredTile>> Store::get_all_tiles(std::int64_t job) {
  constexpr std::string_view kSql = "SELECT tile, pixels, worker, stored_unix FROM tiles WHERE job = ?1 ORDER BY tile";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  q.value().bind(job);
  std::vector<StoredTile> tiles;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) tiles.push_back(read_tile(q.value().get()));
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("reading the tiles of job {}", job), rc);
  return tiles;
}

// A clean close would otherwise delete the -wal and -shm files, and the next open would have to
// create them again: on a full disk, the -shm file's allocation fails and the collector could not
// start until space frees. Kept, they cost a few kilobytes (the WAL is emptied by checkpoints).
Status Store::Impl::keep_wal_files() {
  int persist = 1;
  const int rc = sqlite3_file_control(db, "main", SQLITE_FCNTL_PERSIST_WAL, &persist);
  if (rc != SQLITE_OK) return error("keeping the WAL files", rc);
  return {};
}

Result<CheckpointResult> Store::checkpoint() {
  // A zero busy timeout: a reader in the way makes the checkpoint partial, never a wait on the
  // writer thread (acknowledgements would wait with it).
  sqlite3_busy_timeout(impl_->db, 0);
  CheckpointResult result;
  const int rc = sqlite3_wal_checkpoint_v2(impl_->db, "main", SQLITE_CHECKPOINT_TRUNCATE, &result.wal_frames,
                                           &result.copied_frames);
  sqlite3_busy_timeout(impl_->db, impl_->busy_timeout_ms);
  if (rc == SQLITE_BUSY) return result;
  if (rc != SQLITE_OK) return impl_->error("checkpointing the WAL", rc);
  // After a TRUNCATE checkpoint that succeeded, SQLite reports an empty log.
  result.truncated = result.wal_frames == 0 && result.copied_frames == 0;
  return result;
}

}  // namespace dtraced::store
