// Tests for dtraced::store: the schema and every query, and refusal of bad database files
// without touching them (other schema version, missing tables, not a database, corrupt pages).
// The writer thread, durability across SIGKILL and the commit benchmark are in
// test_store_writer.cpp.
#include <fcntl.h>
#include <sys/mman.h>
#include <sys/vfs.h>
#include <unistd.h>

#include <cstdint>
#include <filesystem>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>
#include <linux/magic.h>

#include "store/coalescing_vfs.h"
#include "store_testing.h"

namespace {
using namespace dtraced::testing;
using dtraced::store::CheckpointMode;
using dtraced::store::TilePixels;
}  // namespace

// ---------------------------------------------------------------------------------------------

TEST_CASE("open creates the state directory and a WAL database with schema version 4", "[store]") {
  StoreDir tmp;
  const std::string dir = tmp.path() + "/nested/state";
  {
    Store store = open_ok(dir);
    CHECK(store.path() == dir + "/dtraced.db");
    auto jobs = store.list_jobs();
    REQUIRE(jobs.ok());
    CHECK(jobs.value().empty());
  }
  CHECK(fs::is_regular_file(dir + "/dtraced.db"));
  CHECK(raw_query_text(dir + "/dtraced.db", "PRAGMA journal_mode") == "wal");
  CHECK(raw_query_text(dir + "/dtraced.db", "SELECT value FROM meta WHERE key = 'schema_version'") == "4");
  CHECK(raw_query_text(dir + "/dtraced.db", "PRAGMA auto_vacuum") == "2");  // incremental
  // A second open of the same, now non-empty, file accepts it.
  Store again = open_ok(dir);
}

TEST_CASE("scenes are stored once and read back", "[store]") {
  StoreDir tmp;
  Store store = open_ok(tmp.path());
  require_ok(store.put_scene("abc", R"({"a":1})"));
  require_ok(store.put_scene("abc", R"({"a":1})"));  // idempotent
  auto got = store.get_scene("abc");
  REQUIRE(got.ok());
  REQUIRE(got.value().has_value());
  CHECK(*got.value() == R"({"a":1})");
  auto missing = store.get_scene("nope");
  REQUIRE(missing.ok());
  CHECK_FALSE(missing.value().has_value());
  // An empty JSON string stays a string, not NULL.
  require_ok(store.put_scene("empty", ""));
  CHECK(store.get_scene("empty").value() == std::optional<std::string>(""));
}

TEST_CASE("jobs: insert, get, list, state changes, lookup by client key, constraints", "[store]") {
  StoreDir tmp;
  Store store = open_ok(tmp.path());
  require_ok(store.put_scene("digest-a", "{}"));

  StoredJob a = sample_job();
  auto id_a = store.insert_job(a);
  REQUIRE(id_a.ok());
  StoredJob b = sample_job();
  b.priority = 7;
  b.tile_size = 4294967295u;
  b.client_key = "one-shot:abc";
  auto id_b = store.insert_job(b);
  REQUIRE(id_b.ok());
  CHECK(id_b.value() > id_a.value());

  auto got = store.get_job(id_b.value());
  REQUIRE(got.ok());
  REQUIRE(got.value().has_value());
  b.id = id_b.value();
  CHECK(*got.value() == b);

  auto by_key = store.find_job_by_key("one-shot:abc");
  REQUIRE(by_key.ok());
  REQUIRE(by_key.value().has_value());
  CHECK(by_key.value()->id == id_b.value());
  CHECK_FALSE(store.find_job_by_key("other").value().has_value());
  CHECK_FALSE(store.get_job(12345).value().has_value());

  require_ok(store.set_job_state(id_a.value(), dtraced::store::kJobDone, 1700000999));
  auto list = store.list_jobs();
  REQUIRE(list.ok());
  REQUIRE(list.value().size() == 2);
  CHECK(list.value()[0].id == id_a.value());
  CHECK(list.value()[0].state == "done");
  CHECK(list.value()[0].finished_unix == 1700000999);
  CHECK_FALSE(list.value()[0].client_key.has_value());
  CHECK(list.value()[1].state == "queued");

  SECTION("a job needs its scene") {
    auto r = store.insert_job(sample_job("no-such-digest"));
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Contains("FOREIGN KEY"));
  }
  SECTION("client keys are unique") {
    StoredJob c = sample_job();
    c.client_key = "one-shot:abc";
    auto r = store.insert_job(c);
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Contains("UNIQUE"));
  }
  SECTION("unknown states and zero tile sizes are refused") {
    StoredJob c = sample_job();
    c.state = "suspended";
    CHECK_FALSE(store.insert_job(c).ok());
    c.state = "queued";
    c.tile_size = 0;
    CHECK_FALSE(store.insert_job(c).ok());
    Status st = store.set_job_state(id_a.value(), "suspended", 0);
    REQUIRE_FALSE(st.ok());
    CHECK_THAT(st.error().message, Contains("CHECK"));
  }
  SECTION("state of a missing job") {
    Status st = store.set_job_state(999, "done", 0);
    REQUIRE_FALSE(st.ok());
    CHECK_THAT(st.error().message, Contains("no job 999"));
  }
  CHECK(store.list_jobs().value().size() == 2);
}

TEST_CASE("tiles: first result wins, duplicates compared, missing job rejected alone", "[store]") {
  StoreDir tmp;
  Store store = open_ok(tmp.path());
  const std::int64_t job = make_job(store);

  std::vector<TileWrite> writes;
  writes.push_back(tile_write(job, 5, 1000));
  writes.push_back(tile_write(job, 1, 1000));
  writes.push_back(tile_write(job + 100, 1, 1000));          // no such job
  writes.push_back(tile_write(job, 5, 1000));                // duplicate inside the batch, same bytes
  writes.push_back(tile_write(job, 1, 1000, 1));             // duplicate, other bytes
  writes.push_back(TileWrite{job, 4294967295u, {}, "", 0});  // empty pixels, largest index
  auto r = store.insert_tiles(writes);
  REQUIRE(r.ok());
  const auto& res = r.value();
  REQUIRE(res.size() == writes.size());
  CHECK(res[0].outcome == TileOutcome::kStored);
  CHECK(res[1].outcome == TileOutcome::kStored);
  CHECK(res[2].outcome == TileOutcome::kRejected);
  CHECK_THAT(res[2].error, Contains("FOREIGN KEY"));
  CHECK(res[3].outcome == TileOutcome::kAlreadyPresent);
  CHECK(res[3].identical);
  CHECK(res[4].outcome == TileOutcome::kAlreadyPresent);
  CHECK_FALSE(res[4].identical);
  CHECK(res[5].outcome == TileOutcome::kStored);

  CHECK(store.stored_tiles(job).value() == std::vector<std::uint32_t>{1, 5, 4294967295u});
  CHECK(store.count_tiles(job).value() == 3);
  CHECK(store.count_tiles(job + 100).value() == 0);
  auto t1 = store.get_tile(job, 1);
  REQUIRE(t1.ok());
  REQUIRE(t1.value().has_value());
  CHECK(t1.value()->pixels == make_pixels(job, 1, 1000));  // the first result, not the salted one
  CHECK(t1.value()->worker == "worker-1");
  CHECK(t1.value()->stored_unix == 1700000101);
  CHECK_FALSE(store.get_tile(job, 2).value().has_value());

  auto all = store.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == 3);
  CHECK(all.value()[0].tile == 1);
  CHECK(all.value()[1].tile == 5);
  CHECK(all.value()[1].pixels == make_pixels(job, 5, 1000));
  CHECK(all.value()[2].tile == 4294967295u);
  CHECK(all.value()[2].pixels.empty());
}

TEST_CASE("a tile's pixels can be a slice of the payload they came in", "[store]") {
  StoreDir tmp;
  Store store = open_ok(tmp.path());
  const std::int64_t job = make_job(store);
  const Blob pixels = make_pixels(job, 7, 3000);
  // A header, the pixels, a trailer: only the pixels are stored.
  const auto with_payload = [&](std::uint32_t tile, const Blob& bytes) {
    TileWrite w = tile_write(job, tile, 0);
    w.pixels = TilePixels(std::string(40, 'h') + std::string(bytes.begin(), bytes.end()) + std::string(32, 't'), 40,
                          bytes.size());
    CHECK(w.pixels.size() == bytes.size());
    CHECK(w.pixels.held_bytes() == 40 + bytes.size() + 32);
    CHECK(Blob(w.pixels.bytes().begin(), w.pixels.bytes().end()) == bytes);
    return w;
  };
  Blob other = pixels;
  other[100] ^= 1;
  std::vector<TileWrite> writes{with_payload(7, pixels), with_payload(7, pixels), with_payload(7, other)};
  auto r = store.insert_tiles(writes);
  REQUIRE(r.ok());
  CHECK(r.value()[0].outcome == TileOutcome::kStored);
  CHECK(r.value()[1].outcome == TileOutcome::kAlreadyPresent);
  CHECK(r.value()[1].identical);
  CHECK(r.value()[2].outcome == TileOutcome::kAlreadyPresent);
  CHECK_FALSE(r.value()[2].identical);
  CHECK(store.get_tile(job, 7).value()->pixels == pixels);
}

TEST_CASE("transaction() commits together or not at all", "[store]") {
  StoreDir tmp;
  Store store = open_ok(tmp.path());
  const std::int64_t job = make_job(store);

  Status failed = store.transaction([&]() -> Status {
    require_ok(store.put_scene("digest-b", "{}"));
    std::vector<TileWrite> w{tile_write(job, 0, 100)};
    REQUIRE(store.insert_tiles(w).ok());
    return dtraced::util::Error{"changed my mind"};
  });
  REQUIRE_FALSE(failed.ok());
  CHECK(failed.error().message == "changed my mind");
  CHECK_FALSE(store.get_scene("digest-b").value().has_value());
  CHECK(store.count_tiles(job).value() == 0);

  require_ok(store.transaction([&]() -> Status {
    if (Status st = store.put_scene("digest-b", "{}"); !st) return st;
    auto id = store.insert_job(sample_job("digest-b"));
    if (!id) return id.error();
    std::vector<TileWrite> w{tile_write(id.value(), 0, 100)};
    auto r = store.insert_tiles(w);
    if (!r) return r.error();
    CHECK(store.transaction([] { return Status{}; }).ok() == false);  // not reentrant
    return {};
  }));
  CHECK(store.get_scene("digest-b").value().has_value());
  CHECK(store.list_jobs().value().size() == 2);
}

TEST_CASE("a reopened store sees everything written before", "[store]") {
  StoreDir tmp;
  std::int64_t job = 0;
  {
    Store store = open_ok(tmp.path());
    job = make_job(store, "key-1");
    std::vector<TileWrite> w{tile_write(job, 3, 5000), tile_write(job, 4, 5000)};
    REQUIRE(store.insert_tiles(w).ok());
    require_ok(store.set_job_state(job, "rendering", 0));
  }
  Store store = open_ok(tmp.path());
  auto got = store.find_job_by_key("key-1");
  REQUIRE(got.ok());
  REQUIRE(got.value().has_value());
  CHECK(got.value()->id == job);
  CHECK(got.value()->state == "rendering");
  CHECK(store.get_scene("digest-a").value() == std::optional<std::string>(R"({"scene":1})"));
  CHECK(store.stored_tiles(job).value() == std::vector<std::uint32_t>{3, 4});
  CHECK(store.get_tile(job, 4).value()->pixels == make_pixels(job, 4, 5000));
}

// ---------------------------------------------------------------------------------------------
// Files the store must refuse, and leave exactly as they were.

TEST_CASE("another schema version is refused and the file left untouched", "[store]") {
  StoreDir tmp;
  { Store store = open_ok(tmp.path()); }
  raw_exec(tmp.db(), "UPDATE meta SET value = 99 WHERE key = 'schema_version'");
  const std::string before = file_bytes(tmp.db());
  const std::string error = open_error(tmp.path());
  CHECK_THAT(error, Contains(tmp.db()));
  CHECK_THAT(error, Contains("schema version 99"));
  CHECK_THAT(error, Contains("untouched"));
  CHECK(file_bytes(tmp.db()) == before);
  // And again: a refusal is repeatable, nothing got "repaired" in between.
  CHECK_THAT(open_error(tmp.path()), Contains("schema version 99"));
  CHECK(file_bytes(tmp.db()) == before);
}

TEST_CASE("a database that is not dtraced's, or lacks parts of the schema, is refused untouched", "[store]") {
  struct Damage {
    const char* what;
    bool ours_first;  // start from a database the store made
    const char* sql;
    const char* expected;
  };
  const Damage damages[] = {
      {"someone else's database", false,
       "CREATE TABLE photos(id INTEGER PRIMARY KEY, name TEXT); INSERT INTO photos VALUES(1, 'x');", "no meta table"},
      {"no schema_version", true, "DELETE FROM meta", "no schema_version"},
      {"schema_version of the wrong type", true, "UPDATE meta SET value = '1'", "not an integer"},
      {"a table missing", true, "DROP TABLE tiles", "table 'tiles' is missing"},
      {"a column missing", true, "ALTER TABLE tiles DROP COLUMN worker",
       "table 'tiles' has columns (job,tile,pixels,stored_unix,pixels_offset,pixels_length,pixels_crc)"},
  };
  for (const Damage& damage : damages) {
    DYNAMIC_SECTION(damage.what) {
      StoreDir tmp;
      if (damage.ours_first) {
        Store store = open_ok(tmp.path());
      }
      raw_exec(tmp.db(), damage.sql);
      const std::string before = file_bytes(tmp.db());
      const std::string error = open_error(tmp.path());
      CHECK_THAT(error, Contains(tmp.db()));
      CHECK_THAT(error, Contains(damage.expected));
      CHECK(file_bytes(tmp.db()) == before);
    }
  }
}

TEST_CASE("a file that is not a database is refused and not modified", "[store]") {
  StoreDir tmp;
  std::mt19937_64 rng(42);
  std::string garbage(64 * 1024, '\0');
  for (char& c : garbage) c = static_cast<char>(rng());
  SECTION("random bytes") {}
  SECTION("a text file") { garbage = "this is my shopping list\n"; }
  write_bytes(tmp.db(), garbage);
  const std::string error = open_error(tmp.path());
  CHECK_THAT(error, Contains(tmp.db()));
  CHECK_THAT(error, Contains("not an SQLite database"));
  CHECK(file_bytes(tmp.db()) == garbage);
}

TEST_CASE("a database with garbage in its middle pages is refused and not modified", "[store]") {
  StoreDir tmp;
  {
    Store store = open_ok(tmp.path());
    const std::int64_t job = make_job(store);
    std::vector<TileWrite> w;
    for (std::uint32_t t = 0; t < 400; ++t) w.push_back(tile_write(job, t, t % 20 == 0 ? 20000 : 300));
    REQUIRE(store.insert_tiles(w).ok());
  }  // the last connection checkpoints: everything is in the main file now
  const auto size = static_cast<std::streamoff>(fs::file_size(tmp.db()));
  constexpr std::streamoff kPage = 4096;
  REQUIRE(size >= 40 * kPage);
  std::mt19937_64 rng(7);
  std::string page(kPage, '\0');
  for (std::streamoff p = size / kPage * 2 / 5; p < size / kPage * 3 / 5; p += 3) {
    for (char& c : page) c = static_cast<char>(rng());
    write_bytes(tmp.db(), page, p * kPage);
  }
  const std::string before = file_bytes(tmp.db());
  const std::string error = open_error(tmp.path());
  INFO(error);
  CHECK_THAT(error, Contains(tmp.db()));
  CHECK((error.find("corrupt") != std::string::npos || error.find("malformed") != std::string::npos));
  CHECK_THAT(error, Contains("untouched"));
  CHECK(file_bytes(tmp.db()) == before);
}

TEST_CASE("state paths that are not what they should be", "[store]") {
  StoreDir tmp;
  SECTION("the state directory is a file") {
    write_bytes(tmp.path() + "/file", "x");
    auto r = Store::open(tmp.path() + "/file");
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Contains(tmp.path() + "/file"));
  }
  SECTION("the database path is a directory") {
    fs::create_directory(tmp.db());
    const std::string error = open_error(tmp.path());
    CHECK_THAT(error, Contains("not a regular file"));
    CHECK(fs::is_directory(tmp.db()));
  }
  SECTION("a zero-length file is a new database") {
    write_bytes(tmp.db(), "");
    Store store = open_ok(tmp.path());
    CHECK(store.list_jobs().ok());
  }
}

namespace {

// How many of the file's pages the kernel holds in its page cache (mincore), or nullopt where
// that says nothing (tmpfs keeps every page) or cannot be read.
std::optional<std::size_t> cached_pages(const std::string& path, std::size_t& pages) {
  struct statfs info {};
  if (::statfs(path.c_str(), &info) != 0 || info.f_type == TMPFS_MAGIC) return std::nullopt;
  const std::size_t size = fs::file_size(path);
  const auto page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
  pages = (size + page - 1) / page;
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return std::nullopt;
  void* map = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, fd, 0);
  ::close(fd);
  if (map == MAP_FAILED) return std::nullopt;
  std::vector<unsigned char> resident(pages);
  const int rc = ::mincore(map, size, resident.data());
  ::munmap(map, size);
  if (rc != 0) return std::nullopt;
  std::size_t cached = 0;
  for (const unsigned char r : resident) cached += r & 1;
  return cached;
}

}  // namespace

TEST_CASE("a checkpoint leaves the pages it copied out of the page cache", "[store][wal]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path(), OpenOptions{.pixels_in_rows = true});  // tiles that weigh on the WAL
  const std::int64_t job = make_job(s);
  std::vector<TileWrite> w;
  for (std::uint32_t t = 0; t < 64; ++t) w.push_back(tile_write(job, t, kBenchTileBytes));
  REQUIRE(s.insert_tiles(w).ok());
  auto copied = s.checkpoint(CheckpointMode::kReuse);
  REQUIRE(copied.ok());
  REQUIRE(copied.value().complete);
  std::size_t pages = 0;
  const auto cached = cached_pages(tmp.db(), pages);
  if (!cached) {
    WARN("the page cache of " << tmp.db() << " cannot be told here (tmpfs?); not checked");
    return;
  }
  // 64 tiles of 48 KiB: about 3 MiB copied into the file, and synced, so none need stay cached.
  INFO(*cached << " of " << pages << " pages cached");
  REQUIRE(pages > 700);
  CHECK(*cached < pages / 4);
  CHECK(s.count_tiles(job).value() == 64);  // read back from the disk
}

TEST_CASE("a reuse checkpoint copies every frame and the next writes overwrite the WAL file", "[store][wal]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t job = make_job(s);
  const std::string wal = tmp.db() + "-wal";
  const auto write_batch = [&](std::uint32_t first) {
    std::vector<TileWrite> w;
    for (std::uint32_t t = first; t < first + 8; ++t) w.push_back(tile_write(job, t, kBenchTileBytes));
    REQUIRE(s.insert_tiles(w).ok());
  };
  write_batch(0);
  const auto grown = fs::file_size(wal);
  REQUIRE(grown > 8 * kBenchTileBytes);

  auto reuse = s.checkpoint(CheckpointMode::kReuse);
  REQUIRE(reuse.ok());
  CHECK(reuse.value().wal_frames > 0);
  CHECK(reuse.value().copied_frames == reuse.value().wal_frames);
  CHECK(reuse.value().complete);
  CHECK_FALSE(reuse.value().truncated);
  CHECK(fs::file_size(wal) == grown);  // kept, not truncated

  // The same amount again starts over at the WAL's beginning: appended, the file would double.
  write_batch(8);
  CHECK(fs::file_size(wal) <= grown + grown / 8);

  auto truncate = s.checkpoint(CheckpointMode::kTruncate);
  REQUIRE(truncate.ok());
  CHECK(truncate.value().truncated);
  CHECK(truncate.value().complete);
  CHECK(fs::file_size(wal) == 0);
  CHECK(s.count_tiles(job).value() == 16);
}

// ---------------------------------------------------------------------------------------------
// The coalescing VFS (store/coalescing_vfs.h).

TEST_CASE("the coalescing VFS writes a WAL file's bytes in order and shows them to reads", "[store][vfs]") {
  StoreDir tmp;
  // SQLite gives a WAL file the mode of its database, which must exist.
  std::ofstream(tmp.path() + "/file").put('\0');
  const std::string path = tmp.path() + "/file-wal";
  sqlite3_vfs* vfs = sqlite3_vfs_find(dtraced::store::coalescing_vfs_name());
  REQUIRE(vfs != nullptr);
  std::vector<char> storage(static_cast<std::size_t>(vfs->szOsFile));
  auto* file = reinterpret_cast<sqlite3_file*>(storage.data());
  int out_flags = 0;
  REQUIRE(vfs->xOpen(vfs, path.c_str(), file, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_WAL,
                     &out_flags) == SQLITE_OK);
  std::string model;
  const auto write = [&](std::size_t offset, std::size_t n, char fill) {
    const std::string bytes(n, fill);
    REQUIRE(file->pMethods->xWrite(file, bytes.data(), static_cast<int>(n), static_cast<sqlite3_int64>(offset)) ==
            SQLITE_OK);
    if (model.size() < offset + n) model.resize(offset + n, '\0');
    model.replace(offset, n, bytes);
  };
  // Consecutive frames (a 24-byte header, then a page), past what one write of the default VFS
  // takes (128 KiB), then a write back into them and one past a gap.
  write(0, 32, 'h');
  for (int frame = 0; frame < 24; ++frame) {
    write(model.size(), 24, static_cast<char>('a' + frame));
    write(model.size(), 16384, static_cast<char>('A' + frame));
  }
  write(100, 50, 'x');
  write(model.size() + 4096, 10, 'y');
  // A read sees what was written, buffered or not.
  std::string read(64, '\0');
  REQUIRE(file->pMethods->xRead(file, read.data(), 64, 90) == SQLITE_OK);
  CHECK(read == model.substr(90, 64));
  write(model.size(), 24, 'z');
  sqlite3_int64 size = 0;
  REQUIRE(file->pMethods->xFileSize(file, &size) == SQLITE_OK);
  CHECK(size == static_cast<sqlite3_int64>(model.size()));
  write(model.size(), 16384, 'Z');
  REQUIRE(file->pMethods->xSync(file, SQLITE_SYNC_NORMAL) == SQLITE_OK);
  CHECK(file_bytes(path) == model);
  write(model.size(), 24, 'q');
  REQUIRE(file->pMethods->xClose(file) == SQLITE_OK);
  CHECK(file_bytes(path) == model);
}

TEST_CASE("a WAL write that fails in the coalescing VFS fails the next sync, whichever call saw it first",
          "[store][vfs]") {
  StoreDir tmp;
  std::ofstream(tmp.path() + "/file").put('\0');
  const std::string path = tmp.path() + "/file-wal";
  std::ofstream(path).put('\0');
  sqlite3_vfs* vfs = sqlite3_vfs_find(dtraced::store::coalescing_vfs_name());
  REQUIRE(vfs != nullptr);
  std::vector<char> storage(static_cast<std::size_t>(vfs->szOsFile));
  auto* file = reinterpret_cast<sqlite3_file*>(storage.data());
  int out_flags = 0;
  // Opened read-only: every write that reaches the file fails.
  REQUIRE(vfs->xOpen(vfs, path.c_str(), file, SQLITE_OPEN_READONLY | SQLITE_OPEN_WAL, &out_flags) == SQLITE_OK);
  const std::string frame(24 + 16384, 'f');
  // Buffered: the write itself succeeds.
  REQUIRE(file->pMethods->xWrite(file, frame.data(), static_cast<int>(frame.size()), 32) == SQLITE_OK);
  // A call whose result SQLite may ignore flushes the buffer and reports the failure...
  CHECK(file->pMethods->xFileControl(file, SQLITE_FCNTL_SYNC_OMITTED, nullptr) != SQLITE_OK);
  // ...and the next sync fails all the same, so no commit can count the lost frame.
  CHECK(file->pMethods->xSync(file, SQLITE_SYNC_NORMAL) != SQLITE_OK);
  // Reported once: nothing more was lost since.
  CHECK(file->pMethods->xSync(file, SQLITE_SYNC_NORMAL) == SQLITE_OK);
  // A failure the write itself reports (the buffer flushed ahead of a non-consecutive write) is
  // heeded there and does not fail a later sync.
  REQUIRE(file->pMethods->xWrite(file, frame.data(), static_cast<int>(frame.size()), 32) == SQLITE_OK);
  CHECK(file->pMethods->xWrite(file, frame.data(), 24, 1 << 20) != SQLITE_OK);
  CHECK(file->pMethods->xSync(file, SQLITE_SYNC_NORMAL) == SQLITE_OK);
  REQUIRE(file->pMethods->xClose(file) == SQLITE_OK);
}

TEST_CASE("through the coalescing VFS, a commit and a checkpoint reach the files before they return", "[store][vfs]") {
  StoreDir tmp;
  const std::string path = tmp.db();
  sqlite3* db = nullptr;
  REQUIRE(sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE,
                          dtraced::store::coalescing_vfs_name()) == SQLITE_OK);
  const auto exec = [](sqlite3* on, const char* sql) {
    char* err = nullptr;
    const int rc = sqlite3_exec(on, sql, nullptr, nullptr, &err);
    INFO((err != nullptr ? err : ""));
    sqlite3_free(err);
    REQUIRE(rc == SQLITE_OK);
  };
  exec(db,
       "PRAGMA page_size = 16384; PRAGMA journal_mode = WAL; PRAGMA synchronous = FULL;"
       "PRAGMA wal_autocheckpoint = 0; CREATE TABLE t(id INTEGER PRIMARY KEY, b BLOB NOT NULL)");
  // Another connection, through the default VFS, as another process would read the files.
  sqlite3* other = nullptr;
  REQUIRE(sqlite3_open_v2(path.c_str(), &other, SQLITE_OPEN_READONLY, nullptr) == SQLITE_OK);
  const auto rows = [&] {
    sqlite3_stmt* q = nullptr;
    REQUIRE(sqlite3_prepare_v2(other, "SELECT count(*), sum(length(b)) FROM t", -1, &q, nullptr) == SQLITE_OK);
    REQUIRE(sqlite3_step(q) == SQLITE_ROW);
    const auto found = std::pair(sqlite3_column_int64(q, 0), sqlite3_column_int64(q, 1));
    sqlite3_finalize(q);
    return found;
  };
  for (int batch = 1; batch <= 3; ++batch) {
    exec(db,
         "BEGIN; WITH RECURSIVE n(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM n WHERE i < 40)"
         " INSERT INTO t(b) SELECT randomblob(12360) FROM n; COMMIT");
    CHECK(rows() == std::pair<sqlite3_int64, sqlite3_int64>(40 * batch, 40 * batch * 12360));
  }
  // TRUNCATE: every page copied into the database file and the WAL emptied, so the other
  // connection now reads the pages from the database file alone.
  exec(db, "PRAGMA wal_checkpoint(TRUNCATE)");
  CHECK(fs::file_size(path + "-wal") == 0);
  CHECK(rows() == std::pair<sqlite3_int64, sqlite3_int64>(120, 120 * 12360));
  sqlite3_stmt* check = nullptr;
  REQUIRE(sqlite3_prepare_v2(other, "PRAGMA integrity_check", -1, &check, nullptr) == SQLITE_OK);
  REQUIRE(sqlite3_step(check) == SQLITE_ROW);
  CHECK(std::string(reinterpret_cast<const char*>(sqlite3_column_text(check, 0))) == "ok");
  sqlite3_finalize(check);
  sqlite3_close(other);
  sqlite3_close(db);
}
