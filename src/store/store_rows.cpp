// Scenes, jobs and tiles: the row accessors of Store (store.h), on the connection and statement
// cache of store_impl.h. Opening, the schema, transactions and checkpoints are in store.cpp.
#include <sqlite3.h>

#include <algorithm>
#include <cassert>
#include <string>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "store/store.h"
#include "store/store_impl.h"

namespace dtraced::store {

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
  // The id is one more than both the highest id present and the highest ever given (meta), so a
  // client holding the id of a deleted job never reaches another job with it.
  constexpr std::string_view kSql =
      "INSERT INTO jobs(id, digest, settings_json, output, priority, tile_size, state, created_unix, finished_unix, "
      "client_key) VALUES (1 + max(coalesce((SELECT max(id) FROM jobs), 0), "
      "coalesce((SELECT value FROM meta WHERE key = 'last_job_id'), 0)), ?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9)";
  {
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
  }
  const std::int64_t id = sqlite3_last_insert_rowid(impl_->db);
  if (!job.tile_costs.empty()) {
    // Like last_job_id below, in the caller's transaction if it has one; without, a crash between
    // the two leaves a job without costs, which the collector leases in row order.
    constexpr std::string_view kCosts = "INSERT INTO job_tile_costs(job, costs) VALUES (?1, ?2)";
    auto q = impl_->query(kCosts);
    if (!q) return q.error();
    if (const int rc = q.value().bind(id).bind_blob(job.tile_costs).step(); rc != SQLITE_DONE) {
      return impl_->error("storing a job's tile costs", rc);
    }
  }
  // Not in the insert's transaction unless the caller has one: a crash between the two leaves the
  // job itself as the highest id, which the insert above also looks at.
  constexpr std::string_view kRemember =
      "INSERT INTO meta(key, value) VALUES ('last_job_id', ?1) ON CONFLICT(key) DO UPDATE SET value = excluded.value";
  auto q = impl_->query(kRemember);
  if (!q) return q.error();
  if (const int rc = q.value().bind(id).step(); rc != SQLITE_DONE) return impl_->error("recording the last job id", rc);
  return id;
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

Result<Deletion> Store::delete_job(std::int64_t id, std::span<const std::string_view> allowed) {
  if (allowed.empty() || allowed.size() > kMaxStateChangeSources) {
    return Error{fmt::format("{}: deleting job {}: {} allowed states (1 to {})", impl_->path, id, allowed.size(),
                             kMaxStateChangeSources)};
  }
  Deletion out;
  Status st = transaction([&]() -> Status {
    auto job = get_job(id);
    if (!job) return job.error();
    if (!job.value()) return Error{fmt::format("{}: no job {}", impl_->path, id)};
    out.state = job.value()->state;
    if (std::find(allowed.begin(), allowed.end(), std::string_view(out.state)) == allowed.end()) return {};
    {
      constexpr std::string_view kSql = "DELETE FROM tiles WHERE job = ?1";
      auto q = impl_->query(kSql);
      if (!q) return q.error();
      if (const int rc = q.value().bind(id).step(); rc != SQLITE_DONE) {
        return impl_->error(fmt::format("deleting the tiles of job {}", id), rc);
      }
      out.tiles = static_cast<std::uint64_t>(sqlite3_changes64(impl_->db));
    }
    {
      constexpr std::string_view kSql = "DELETE FROM job_tile_costs WHERE job = ?1";
      auto q = impl_->query(kSql);
      if (!q) return q.error();
      if (const int rc = q.value().bind(id).step(); rc != SQLITE_DONE) {
        return impl_->error(fmt::format("deleting the tile costs of job {}", id), rc);
      }
    }
    {
      constexpr std::string_view kSql = "DELETE FROM jobs WHERE id = ?1";
      auto q = impl_->query(kSql);
      if (!q) return q.error();
      if (const int rc = q.value().bind(id).step(); rc != SQLITE_DONE) {
        return impl_->error(fmt::format("deleting job {}", id), rc);
      }
    }
    constexpr std::string_view kSql =
        "DELETE FROM scenes WHERE digest = ?1 AND NOT EXISTS (SELECT 1 FROM jobs WHERE digest = ?1)";
    auto q = impl_->query(kSql);
    if (!q) return q.error();
    if (const int rc = q.value().bind(job.value()->digest).step(); rc != SQLITE_DONE) {
      return impl_->error(fmt::format("deleting the scene of job {}", id), rc);
    }
    out.scene_deleted = sqlite3_changes64(impl_->db) == 1;
    out.deleted = true;
    return {};
  });
  if (!st) return st.error();
  return out;
}

Result<SpaceUse> Store::space_use() {
  SpaceUse use;
  for (auto [pragma, field] :
       {std::pair{"PRAGMA page_size", &use.page_size}, std::pair{"PRAGMA page_count", &use.pages},
        std::pair{"PRAGMA freelist_count", &use.free_pages}}) {
    auto rows = impl_->exec_rows(pragma);
    if (!rows) return rows.error();
    if (rows.value().size() != 1) return Error{fmt::format("{}: {} returned no value", impl_->path, pragma)};
    *field = std::stoull(rows.value()[0]);
  }
  return use;
}

Result<SpaceUse> Store::reclaim_space() {
  // Without incremental auto-vacuum (a version 1 file that could not be converted) this does
  // nothing, and the free pages are reused by later tiles.
  if (auto st = impl_->exec_rows("PRAGMA incremental_vacuum"); !st) return st.error();
  if (auto cp = checkpoint(); !cp) return cp.error();
  return space_use();
}

TilePixels::TilePixels(std::string payload, std::size_t offset, std::size_t size)
    : payload_(std::move(payload)), offset_(offset), size_(size) {
  assert(offset <= payload_.size() && size <= payload_.size() - offset);
}

Result<CommitResult> Store::Impl::insert_tile(const TileWrite& w) {
  {
    constexpr std::string_view kSql =
        "INSERT OR IGNORE INTO tiles(job, tile, pixels, worker, stored_unix) VALUES (?1, ?2, ?3, ?4, ?5)";
    auto q = query(kSql);
    if (!q) return q.error();
    const int rc = q.value()
                       .bind(w.job)
                       .bind(std::int64_t{w.tile})
                       .bind_blob(w.pixels.bytes())
                       .bind(w.worker)
                       .bind(w.stored_unix)
                       .step();
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
  const std::span<const std::uint8_t> bytes = w.pixels.bytes();
  const bool identical = n == bytes.size() && (n == 0 || std::memcmp(stored, bytes.data(), n) == 0);
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
}  // namespace dtraced::store
