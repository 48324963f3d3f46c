// Scenes, jobs and tiles: the row accessors of Store (store.h), on the connection and statement
// cache of store_impl.h. Opening, the schema, transactions and checkpoints are in store.cpp.
#include <fcntl.h>
#include <sqlite3.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cassert>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "store/pixel_files.h"
#include "store/store.h"
#include "store/store_impl.h"
#include "util/crc32c.h"
#include "util/log.h"

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
      constexpr std::string_view kSql = "DELETE FROM pixel_files WHERE job = ?1";
      auto q = impl_->query(kSql);
      if (!q) return q.error();
      if (const int rc = q.value().bind(id).step(); rc != SQLITE_DONE) {
        return impl_->error(fmt::format("deleting the pixel file length of job {}", id), rc);
      }
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
  if (out.deleted) {
    // After the COMMIT: a crash before this leaves a file of no job (remove_orphan_pixel_files).
    impl_->append_files.erase(id);
    const std::string file = pixel_file_path(impl_->pixel_dir, id);
    if (::unlink(file.c_str()) != 0 && errno != ENOENT) {
      util::log_warn("{}: cannot remove the pixels of deleted job {}: {}", file, id, std::strerror(errno));
    }
  }
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

Result<PendingAppend*> Store::Impl::pending_for(std::vector<PendingAppend>& appends, std::int64_t job) {
  for (PendingAppend& a : appends) {
    if (a.job == job) return &a;
  }
  constexpr std::string_view kSql = "SELECT bytes FROM pixel_files WHERE job = ?1";
  auto q = query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(job).step();
  if (rc != SQLITE_ROW && rc != SQLITE_DONE)
    return error(fmt::format("reading the pixel file length of job {}", job), rc);
  PendingAppend a;
  a.job = job;
  if (rc == SQLITE_ROW) a.committed = static_cast<std::uint64_t>(sqlite3_column_int64(q.value().get(), 0));
  appends.push_back(std::move(a));
  return &appends.back();
}

Result<int> Store::Impl::append_file(std::int64_t job, std::uint64_t committed) {
  if (auto it = append_files.find(job); it != append_files.end()) {
    // Still the file at its path? (Someone may have removed it: then it is opened, created, again.)
    struct stat st {};
    if (::fstat(it->second.get(), &st) == 0 && st.st_nlink > 0) return it->second.get();
    append_files.erase(it);
  }
  // A collector appends to one or two jobs at a time; a store that wrote to many keeps few open.
  constexpr std::size_t kMaxOpenAppendFiles = 16;
  if (append_files.size() >= kMaxOpenAppendFiles) append_files.clear();
  if (::mkdir(pixel_dir.c_str(), 0755) != 0 && errno != EEXIST) {
    return Error{fmt::format("{}: cannot create the directory of tile pixels: {}", pixel_dir, std::strerror(errno))};
  }
  const std::string file = pixel_file_path(pixel_dir, job);
  util::FileHandle fd(::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644));
  if (fd.get() < 0)
    return Error{fmt::format("{}: cannot open for appending tile pixels: {}", file, std::strerror(errno))};
  struct stat st {};
  if (::fstat(fd.get(), &st) != 0) return Error{fmt::format("{}: cannot stat: {}", file, std::strerror(errno))};
  if (static_cast<std::uint64_t>(st.st_size) > committed) {
    // Appended but never committed: a kill or a failed commit between an append and its COMMIT.
    if (::ftruncate(fd.get(), static_cast<off_t>(committed)) != 0) {
      return Error{
          fmt::format("{}: cannot truncate to its committed {} bytes: {}", file, committed, std::strerror(errno))};
    }
    util::log_info("{}: dropped {} bytes past its committed length (appended by a commit that did not finish)", file,
                   static_cast<std::uint64_t>(st.st_size) - committed);
  }
  if (!pixel_dir_ready) {
    // The directory's entry (in the state directory) and the file's (in the directory) must be on
    // disk before a row points into the file: the state directory once, the pixel directory for
    // each file opened (it may have been created just now).
    const std::string state_dir = std::filesystem::path(pixel_dir).parent_path().string();
    util::FileHandle dir(::open(state_dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (dir.get() < 0 || ::fsync(dir.get()) != 0) {
      return Error{fmt::format("{}: cannot sync the directory: {}", state_dir, std::strerror(errno))};
    }
    pixel_dir_ready = true;
  }
  util::FileHandle dir(::open(pixel_dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
  if (dir.get() < 0 || ::fsync(dir.get()) != 0) {
    return Error{fmt::format("{}: cannot sync the directory: {}", pixel_dir, std::strerror(errno))};
  }
  const int raw = fd.get();
  append_files.emplace(job, std::move(fd));
  return raw;
}

Status Store::Impl::flush_appends(std::vector<PendingAppend>& appends) {
  std::uint64_t adding = 0;
  for (const PendingAppend& a : appends) adding += a.bytes;
  if (adding == 0) return {};
  if (max_database_bytes > 0) {
    auto held = exec_rows(
        "SELECT (SELECT coalesce(sum(bytes), 0) FROM pixel_files) + page_count * page_size "
        "FROM pragma_page_count, pragma_page_size");
    if (!held) return held.error();
    const std::uint64_t bytes = held.value().empty() ? 0 : std::stoull(held.value()[0]);
    if (bytes + adding > max_database_bytes) {
      return Error{
          fmt::format("{}: storing {} bytes of tile pixels would take the store past its cap of {} bytes "
                      "({} held): database or disk is full",
                      path, adding, max_database_bytes, bytes)};
    }
  }
  for (PendingAppend& a : appends) {
    if (a.bytes == 0) continue;
    auto fd = append_file(a.job, a.committed);
    if (!fd) return fd.error();
    const std::string file = pixel_file_path(pixel_dir, a.job);
    if (auto st = write_all(fd.value(), file, a.committed, a.pieces); !st) {
      append_files.erase(a.job);  // opened again, and truncated back, by the next append
      return st;
    }
    if (::fdatasync(fd.value()) != 0) {
      const int e = errno;
      append_files.erase(a.job);
      return Error{fmt::format("{}: syncing appended tile pixels: {}", file, std::strerror(e))};
    }
    constexpr std::string_view kSql =
        "INSERT INTO pixel_files(job, bytes) VALUES (?1, ?2) ON CONFLICT(job) DO UPDATE SET bytes = excluded.bytes";
    auto q = query(kSql);
    if (!q) return q.error();
    if (const int rc = q.value().bind(a.job).bind(static_cast<std::int64_t>(a.committed + a.bytes)).step();
        rc != SQLITE_DONE) {
      return error(fmt::format("recording the pixel file length of job {}", a.job), rc);
    }
  }
  return {};
}

Result<Blob> Store::Impl::read_file_pixels(std::int64_t job, std::uint32_t tile, const PixelExtent& extent,
                                           util::FileHandle& file) {
  const std::string name = pixel_file_path(pixel_dir, job);
  if (file.get() < 0) {
    auto opened = open_for_reading(name);
    if (!opened) {
      return Error{fmt::format("{} (tile {} of job {}, {} bytes at offset {})", opened.error().message, tile, job,
                               extent.length, extent.offset)};
    }
    file = std::move(opened).value();
  }
  return read_checked(file.get(), name, job, tile, extent.offset, extent.length, extent.crc);
}

Result<StoredTile> Store::Impl::read_tile(sqlite3_stmt* s, std::int64_t job, util::FileHandle& file) {
  StoredTile t;
  t.tile = static_cast<std::uint32_t>(sqlite3_column_int64(s, 0));
  t.worker = column_text(s, 2);
  t.stored_unix = sqlite3_column_int64(s, 3);
  if (const std::optional<PixelExtent> extent = read_extent(s, 4)) {
    auto bytes = read_file_pixels(job, t.tile, *extent, file);
    if (!bytes) return bytes.error();
    t.pixels = std::move(bytes).value();
  } else {
    t.pixels = column_blob(s, 1);
  }
  return t;
}

Result<CommitResult> Store::Impl::insert_tile(const TileWrite& w, std::vector<PendingAppend>& appends) {
  const std::span<const std::uint8_t> bytes = w.pixels.bytes();
  PendingAppend* append = nullptr;
  if (!pixels_in_rows) {
    auto a = pending_for(appends, w.job);
    if (!a) return a.error();
    append = a.value();
  }
  // Binds the tile's pixels, or where they will lie in the job's file, from parameter 3 on.
  const auto bind_pixels = [&](Query& q) {
    if (append == nullptr) {
      q.bind_blob(bytes).bind(w.worker).bind(w.stored_unix).bind_optional(std::optional<std::int64_t>());
      q.bind_optional(std::optional<std::int64_t>()).bind_optional(std::optional<std::int64_t>());
    } else {
      q.bind_blob({})
          .bind(w.worker)
          .bind(w.stored_unix)
          .bind(static_cast<std::int64_t>(append->committed + append->bytes));
      q.bind(static_cast<std::int64_t>(bytes.size())).bind(std::int64_t{util::crc32c(bytes)});
    }
  };
  const auto appended = [&] {
    if (append == nullptr) return;
    append->offsets.push_back(append->committed + append->bytes);
    append->pieces.push_back(iovec{const_cast<std::uint8_t*>(bytes.data()), bytes.size()});
    append->bytes += bytes.size();
  };
  {
    constexpr std::string_view kSql =
        "INSERT OR IGNORE INTO tiles(job, tile, pixels, worker, stored_unix, pixels_offset, pixels_length, pixels_crc) "
        "VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)";
    auto q = query(kSql);
    if (!q) return q.error();
    q.value().bind(w.job).bind(std::int64_t{w.tile});
    bind_pixels(q.value());
    const int rc = q.value().step();
    if (rc == SQLITE_DONE) {
      if (sqlite3_changes64(db) == 1) {
        appended();
        return CommitResult{TileOutcome::kStored, false, {}};
      }
    } else if ((rc & 0xff) == SQLITE_CONSTRAINT && sqlite3_get_autocommit(db) == 0) {
      // OR IGNORE covers the primary key; a missing job (foreign key) fails this statement only.
      return CommitResult{TileOutcome::kRejected, false,
                          error(fmt::format("storing tile {} of job {}", w.tile, w.job), rc).message};
    } else {
      return error(fmt::format("storing tile {} of job {}", w.tile, w.job), rc);
    }
  }
  // Already present: compare the bytes (duplicates are rare, so the extra read is cheap overall).
  Blob from_file;
  std::span<const std::uint8_t> stored;
  bool damaged = false;
  {
    constexpr std::string_view kSql =
        "SELECT pixels, pixels_offset, pixels_length, pixels_crc FROM tiles WHERE job = ?1 AND tile = ?2";
    auto q = query(kSql);
    if (!q) return q.error();
    const int rc = q.value().bind(w.job).bind(std::int64_t{w.tile}).step();
    if (rc != SQLITE_ROW) return error(fmt::format("reading back tile {} of job {}", w.tile, w.job), rc);
    sqlite3_stmt* s = q.value().get();
    const std::optional<PixelExtent> extent = read_extent(s, 1);
    if (!extent) {
      from_file = column_blob(s, 0);
      stored = from_file;
    } else {
      auto pending = pending_for(appends, w.job);
      if (!pending) return pending.error();
      const PendingAppend& a = *pending.value();
      if (extent->offset >= a.committed) {
        // Stored earlier in this batch: its bytes are still the submitted ones, in memory.
        for (std::size_t i = 0; i < a.offsets.size(); ++i) {
          if (a.offsets[i] == extent->offset) {
            stored = std::span(static_cast<const std::uint8_t*>(a.pieces[i].iov_base), a.pieces[i].iov_len);
          }
        }
      } else {
        util::FileHandle file;
        auto read = read_file_pixels(w.job, w.tile, *extent, file);
        if (read) {
          from_file = std::move(read).value();
          stored = from_file;
        } else {
          // Damaged or lost on disk: this result takes the row's place (the tile was leased again
          // because reading it failed, see store.h).
          util::log_warn("{}; replaced by the tile just submitted", read.error().message);
          damaged = true;
        }
      }
    }
  }
  if (damaged) {
    constexpr std::string_view kReplace =
        "UPDATE tiles SET pixels = ?3, worker = ?4, stored_unix = ?5, pixels_offset = ?6, pixels_length = ?7, "
        "pixels_crc = ?8 WHERE job = ?1 AND tile = ?2";
    if (append == nullptr) {
      auto a = pending_for(appends, w.job);
      if (!a) return a.error();
      append = a.value();
    }
    auto r = query(kReplace);
    if (!r) return r.error();
    r.value().bind(w.job).bind(std::int64_t{w.tile});
    bind_pixels(r.value());
    if (const int rc = r.value().step(); rc != SQLITE_DONE) {
      return error(fmt::format("replacing damaged tile {} of job {}", w.tile, w.job), rc);
    }
    appended();
    return CommitResult{TileOutcome::kStored, false, {}};
  }
  const bool identical =
      stored.size() == bytes.size() && (bytes.empty() || std::memcmp(stored.data(), bytes.data(), bytes.size()) == 0);
  return CommitResult{TileOutcome::kAlreadyPresent, identical, {}};
}

Result<std::vector<CommitResult>> Store::insert_tiles(std::span<const TileWrite> writes) {
  const bool own_transaction = sqlite3_get_autocommit(impl_->db) != 0;
  if (own_transaction) {
    if (auto st = impl_->exec(kSqlBegin); !st) return st.error();
  }
  std::vector<CommitResult> results;
  results.reserve(writes.size());
  std::vector<PendingAppend> appends;
  const auto fail = [&](Error e) -> Result<std::vector<CommitResult>> {
    if (own_transaction) impl_->rollback();
    return e;
  };
  for (const TileWrite& w : writes) {
    auto r = impl_->insert_tile(w, appends);
    if (!r) return fail(std::move(r).error());
    results.push_back(std::move(r).value());
  }
  // The pixels are on disk before the rows that point at them commit.
  if (auto st = impl_->flush_appends(appends); !st) return fail(std::move(st).error());
  if (own_transaction) {
    if (auto st = impl_->exec(kSqlCommit); !st) return fail(std::move(st).error());
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
  static const std::string kSql = std::string(kSelectTiles) + "WHERE job = ?1 AND tile = ?2";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(job).bind(std::int64_t{tile}).step();
  if (rc == SQLITE_DONE) return std::optional<StoredTile>();
  if (rc != SQLITE_ROW) return impl_->error(fmt::format("reading tile {} of job {}", tile, job), rc);
  util::FileHandle file;
  auto t = impl_->read_tile(q.value().get(), job, file);
  if (!t) return t.error();
  return std::optional<StoredTile>(std::move(t).value());
}

Result<std::vector<StoredTile>> Store::get_all_tiles(std::int64_t job) {
  std::vector<StoredTile> tiles;
  const Status st = visit_tiles(job, [&](StoredTile&& t) {
    tiles.push_back(std::move(t));
    return Status();
  });
  if (!st) return st.error();
  return tiles;
}

Status Store::visit_tiles(std::int64_t job, const std::function<Status(StoredTile&&)>& visit) {
  static const std::string kSql = std::string(kSelectTiles) + "WHERE job = ?1 ORDER BY tile";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  q.value().bind(job);
  util::FileHandle file;
  std::uint64_t unreadable = 0;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) {
    auto t = impl_->read_tile(q.value().get(), job, file);
    if (t) {
      if (Status st = visit(std::move(t).value()); !st) return st;
      continue;
    }
    // The others are still good: leave this one out so that it is rendered again.
    constexpr std::uint64_t kMaxLogged = 8;
    if (++unreadable <= kMaxLogged)
      util::log_error("{}; the tile is left out and will be rendered again", t.error().message);
  }
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("reading the tiles of job {}", job), rc);
  if (unreadable > 0) {
    util::log_error("{}: job {}: {} stored tiles could not be read back and were left out", impl_->path, job,
                    unreadable);
  }
  return Status();
}

Result<std::size_t> Store::remove_orphan_pixel_files() {
  namespace fs = std::filesystem;
  std::error_code ec;
  if (!fs::is_directory(impl_->pixel_dir, ec)) return std::size_t{0};
  std::vector<std::pair<std::int64_t, std::string>> files;
  for (fs::directory_iterator it(impl_->pixel_dir, ec), end; !ec && it != end; it.increment(ec)) {
    const std::string name = it->path().filename().string();
    constexpr std::string_view kPrefix = "job-", kSuffix = ".pixels";
    if (!name.starts_with(kPrefix) || !name.ends_with(kSuffix)) continue;
    const std::string digits = name.substr(kPrefix.size(), name.size() - kPrefix.size() - kSuffix.size());
    if (digits.empty() || digits.size() > 18 ||
        !std::all_of(digits.begin(), digits.end(), [](char c) { return c >= '0' && c <= '9'; })) {
      continue;
    }
    files.emplace_back(std::stoll(digits), it->path().string());
  }
  if (ec) return Error{fmt::format("{}: cannot list: {}", impl_->pixel_dir, ec.message())};
  std::size_t removed = 0;
  for (const auto& [job, file] : files) {
    auto found = get_job(job);
    if (!found) return found.error();
    if (found.value()) continue;
    if (::unlink(file.c_str()) != 0 && errno != ENOENT) {
      util::log_warn("{}: cannot remove the pixels of deleted job {}: {}", file, job, std::strerror(errno));
      continue;
    }
    util::log_info("{}: removed the pixels of deleted job {}", file, job);
    ++removed;
  }
  return removed;
}

// A clean close would otherwise delete the -wal and -shm files, and the next open would have to
// create them again: on a full disk, the -shm file's allocation fails and the collector could not
// start until space frees. Kept, they cost a few kilobytes (the WAL is emptied by checkpoints).
}  // namespace dtraced::store
