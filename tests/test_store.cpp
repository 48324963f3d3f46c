// Tests for dtraced::store: the schema and every query, refusal of bad database files without
// touching them (other schema version, missing tables, not a database, corrupt pages), group
// commit from many threads (exactly-once "stored", duplicates, rejected tiles, failed batches,
// bounded queue, draining stop), acknowledged tiles surviving a SIGKILL (a forked child writes,
// the parent kills it and reopens), and a commit-rate benchmark that prints figures only.
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <sqlite3.h>
#include <stdlib.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <map>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "store/store.h"
#include "store/tile_writer.h"

namespace {

namespace fs = std::filesystem;
using Catch::Matchers::Contains;
using dtraced::store::Blob;
using dtraced::store::CommitResult;
using dtraced::store::OpenOptions;
using dtraced::store::Store;
using dtraced::store::StoredJob;
using dtraced::store::StoredTile;
using dtraced::store::SubmitStatus;
using dtraced::store::TileOutcome;
using dtraced::store::TileWrite;
using dtraced::store::TileWriter;
using dtraced::store::WriterLimits;
using dtraced::util::Status;
using namespace std::chrono_literals;

// A 64x64 tile of linear RGB float32, as the wire and the collector carry it.
constexpr std::size_t kBenchTileBytes = 64 * 64 * 3 * sizeof(float);
// Every wait in this file is bounded by this, so a hang fails instead of stalling CI.
constexpr auto kWaitLimit = 60s;

class TempDir {
 public:
  TempDir() {
    std::string templ = (fs::temp_directory_path() / "dtraced-store-XXXXXX").string();
    REQUIRE(::mkdtemp(templ.data()) != nullptr);
    path_ = templ;
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  ~TempDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  const std::string& path() const { return path_; }
  std::string db() const { return path_ + "/dtraced.db"; }

 private:
  std::string path_;
};

std::string file_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  REQUIRE(in);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// Replaces the file's contents, or with an offset overwrites bytes in place.
void write_bytes(const std::string& path, const std::string& bytes, std::streamoff offset = -1) {
  std::fstream out;
  if (offset < 0) {
    out.open(path, std::ios::binary | std::ios::out | std::ios::trunc);
  } else {
    out.open(path, std::ios::binary | std::ios::in | std::ios::out);
    out.seekp(offset);
  }
  REQUIRE(out);
  out.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  REQUIRE(out);
}

// Pixels that depend on (job, tile, salt), so a misplaced or torn tile shows.
Blob make_pixels(std::int64_t job, std::uint32_t tile, std::size_t bytes, std::uint64_t salt = 0) {
  Blob b(bytes);
  std::uint64_t x = (static_cast<std::uint64_t>(job) << 32) ^ tile ^ (salt * 0x9e3779b97f4a7c15ull);
  for (std::size_t i = 0; i < bytes; ++i) {
    if (i % 8 == 0) {  // splitmix64
      x += 0x9e3779b97f4a7c15ull;
      std::uint64_t z = x;
      z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
      z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
      z ^= z >> 31;
      std::memcpy(b.data() + i, &z, std::min<std::size_t>(8, bytes - i));
    }
  }
  return b;
}

Store open_ok(const std::string& dir, const OpenOptions& options = {}) {
  auto r = Store::open(dir, options);
  if (!r) FAIL(r.error().message);
  return std::move(r).value();
}

std::string open_error(const std::string& dir) {
  auto r = Store::open(dir);
  REQUIRE_FALSE(r.ok());
  return r.error().message;
}

void require_ok(const Status& st) {
  if (!st) FAIL(st.error().message);
}

StoredJob sample_job(std::string digest = "digest-a") {
  StoredJob job;
  job.digest = std::move(digest);
  job.settings_json = R"({"width":64,"height":48})";
  job.output = "out.png";
  job.priority = -3;
  job.tile_size = 32;
  job.created_unix = 1700000000;
  return job;
}

std::int64_t make_job(Store& store, std::optional<std::string> key = std::nullopt) {
  require_ok(store.put_scene("digest-a", R"({"scene":1})"));
  StoredJob job = sample_job();
  job.client_key = std::move(key);
  auto id = store.insert_job(job);
  if (!id) FAIL(id.error().message);
  return id.value();
}

TileWrite tile_write(std::int64_t job, std::uint32_t tile, std::size_t bytes, std::uint64_t salt = 0) {
  return TileWrite{job, tile, make_pixels(job, tile, bytes, salt), "worker-1", 1700000100 + tile};
}

// Raw SQLite, to build the files the store must refuse.
void raw_exec(const std::string& path, const std::string& sql) {
  sqlite3* db = nullptr;
  const int orc = sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE, nullptr);
  REQUIRE(orc == SQLITE_OK);
  char* err = nullptr;
  const int rc = sqlite3_exec(db, sql.c_str(), nullptr, nullptr, &err);
  const std::string message = err != nullptr ? err : "";
  sqlite3_free(err);
  sqlite3_close(db);
  INFO(message);
  REQUIRE(rc == SQLITE_OK);
}

std::string raw_query_text(const std::string& path, const std::string& sql) {
  sqlite3* db = nullptr;
  REQUIRE(sqlite3_open_v2(path.c_str(), &db, SQLITE_OPEN_READONLY, nullptr) == SQLITE_OK);
  sqlite3_stmt* s = nullptr;
  REQUIRE(sqlite3_prepare_v2(db, sql.c_str(), -1, &s, nullptr) == SQLITE_OK);
  std::string out;
  if (sqlite3_step(s) == SQLITE_ROW) out = reinterpret_cast<const char*>(sqlite3_column_text(s, 0));
  sqlite3_finalize(s);
  sqlite3_close(db);
  return out;
}

// Collects writer callbacks by key; waits with a bound.
class Callbacks {
 public:
  TileWriter::Done done(std::uint32_t key) {
    return [this, key](CommitResult r) {
      std::lock_guard lock(mu_);
      results_[key].push_back(std::move(r));
      ++count_;
      cv_.notify_all();
    };
  }
  bool wait_for(std::size_t n) {
    std::unique_lock lock(mu_);
    return cv_.wait_for(lock, kWaitLimit, [&] { return count_ >= n; });
  }
  std::map<std::uint32_t, std::vector<CommitResult>> results() {
    std::lock_guard lock(mu_);
    return results_;
  }
  std::size_t count() {
    std::lock_guard lock(mu_);
    return count_;
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::uint32_t, std::vector<CommitResult>> results_;
  std::size_t count_ = 0;
};

// Holds the writer thread inside a task until opened, so the tiles submitted meanwhile form one
// batch (or pile up against the limits).
class Gate {
 public:
  void close(TileWriter& writer) {
    REQUIRE(writer.post([this](Store&) {
      entered_.set_value();
      opened_.wait();
    }) == SubmitStatus::kAccepted);
    REQUIRE(entered_.get_future().wait_for(kWaitLimit) == std::future_status::ready);
  }
  void open() { open_.set_value(); }
  ~Gate() {
    try {
      open_.set_value();
    } catch (const std::future_error&) {  // already open
    }
  }

 private:
  std::promise<void> entered_;
  std::promise<void> open_;
  std::shared_future<void> opened_ = open_.get_future().share();
};

// ---------------------------------------------------------------------------------------------

TEST_CASE("open creates the state directory and a WAL database with schema version 1", "[store]") {
  TempDir tmp;
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
  CHECK(raw_query_text(dir + "/dtraced.db", "SELECT value FROM meta WHERE key = 'schema_version'") == "1");
  // A second open of the same, now non-empty, file accepts it.
  Store again = open_ok(dir);
}

TEST_CASE("scenes are stored once and read back", "[store]") {
  TempDir tmp;
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
  TempDir tmp;
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
    c.state = "paused";
    CHECK_FALSE(store.insert_job(c).ok());
    c.state = "queued";
    c.tile_size = 0;
    CHECK_FALSE(store.insert_job(c).ok());
    Status st = store.set_job_state(id_a.value(), "paused", 0);
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
  TempDir tmp;
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

TEST_CASE("transaction() commits together or not at all", "[store]") {
  TempDir tmp;
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
  TempDir tmp;
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
  TempDir tmp;
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
  TempDir tmp;
  std::string expected;
  SECTION("someone else's database") {
    raw_exec(tmp.db(), "CREATE TABLE photos(id INTEGER PRIMARY KEY, name TEXT); INSERT INTO photos VALUES(1, 'x');");
    expected = "no meta table";
  }
  SECTION("no schema_version") {
    { Store store = open_ok(tmp.path()); }
    raw_exec(tmp.db(), "DELETE FROM meta");
    expected = "no schema_version";
  }
  SECTION("schema_version of the wrong type") {
    { Store store = open_ok(tmp.path()); }
    raw_exec(tmp.db(), "UPDATE meta SET value = '1'");
    expected = "not an integer";
  }
  SECTION("a table missing") {
    { Store store = open_ok(tmp.path()); }
    raw_exec(tmp.db(), "DROP TABLE tiles");
    expected = "table 'tiles' is missing";
  }
  SECTION("a column missing") {
    { Store store = open_ok(tmp.path()); }
    raw_exec(tmp.db(), "ALTER TABLE tiles DROP COLUMN worker");
    expected = "table 'tiles' has columns (job,tile,pixels,stored_unix)";
  }
  const std::string before = file_bytes(tmp.db());
  const std::string error = open_error(tmp.path());
  CHECK_THAT(error, Contains(tmp.db()));
  CHECK_THAT(error, Contains(expected));
  CHECK(file_bytes(tmp.db()) == before);
}

TEST_CASE("a file that is not a database is refused and not modified", "[store]") {
  TempDir tmp;
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
  TempDir tmp;
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
  TempDir tmp;
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

// ---------------------------------------------------------------------------------------------
// Group commit.

TEST_CASE("1000 tiles submitted from several threads are each stored exactly once", "[store][writer]") {
  TempDir tmp;
  std::int64_t job = 0;
  {
    Store setup = open_ok(tmp.path());
    job = make_job(setup);
  }
  Callbacks callbacks;
  TileWriter writer(open_ok(tmp.path()));
  constexpr std::uint32_t kThreads = 4, kPerThread = 250, kTiles = kThreads * kPerThread;
  constexpr std::size_t kBytes = 2000;
  std::vector<std::thread> threads;
  std::atomic<int> refused{0};
  for (std::uint32_t t = 0; t < kThreads; ++t) {
    threads.emplace_back([&, t] {
      for (std::uint32_t k = 0; k < kPerThread; ++k) {
        const std::uint32_t tile = t * kPerThread + k;
        if (writer.submit(tile_write(job, tile, kBytes), callbacks.done(tile)) != SubmitStatus::kAccepted) ++refused;
      }
    });
  }
  for (auto& th : threads) th.join();
  REQUIRE(refused == 0);
  REQUIRE(callbacks.wait_for(kTiles));
  auto results = callbacks.results();
  REQUIRE(results.size() == kTiles);
  for (const auto& [tile, rs] : results) {
    REQUIRE(rs.size() == 1);
    CHECK(rs[0].outcome == TileOutcome::kStored);
  }

  // Duplicates: same bytes and different bytes.
  REQUIRE(writer.submit(tile_write(job, 17, kBytes), callbacks.done(100017)) == SubmitStatus::kAccepted);
  REQUIRE(writer.submit(tile_write(job, 18, kBytes, 9), callbacks.done(100018)) == SubmitStatus::kAccepted);
  REQUIRE(callbacks.wait_for(kTiles + 2));
  results = callbacks.results();
  CHECK(results[100017].at(0).outcome == TileOutcome::kAlreadyPresent);
  CHECK(results[100017].at(0).identical);
  CHECK(results[100018].at(0).outcome == TileOutcome::kAlreadyPresent);
  CHECK_FALSE(results[100018].at(0).identical);

  const auto stats = writer.stats();
  CHECK(stats.tiles_stored == kTiles);
  CHECK(stats.tiles_already_present == 2);
  CHECK(stats.pending_tiles == 0);
  CHECK(stats.pending_bytes == 0);
  CHECK(stats.batches <= kTiles + 2);
  WARN(fmt::format("1000 concurrent submits went into {} transactions (largest {})", stats.batches,
                   stats.largest_batch));

  // Readable from another connection while the writer still runs (WAL: readers do not block).
  Store reader = open_ok(tmp.path(), OpenOptions{.verify_integrity = false});
  auto all = reader.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == kTiles);
  for (const StoredTile& t : all.value()) {
    REQUIRE(t.pixels == make_pixels(job, t.tile, kBytes));
  }
}

TEST_CASE("tasks run in submission order with the tiles around them", "[store][writer]") {
  TempDir tmp;
  Callbacks callbacks;
  TileWriter writer(open_ok(tmp.path()));
  Gate gate;
  gate.close(writer);
  // The job is created by a task queued before its tile, in the same drained batch.
  std::promise<std::int64_t> job_id;
  REQUIRE(writer.post([&](Store& store) { job_id.set_value(make_job(store)); }) == SubmitStatus::kAccepted);
  REQUIRE(writer.submit(tile_write(1, 0, 100), callbacks.done(0)) == SubmitStatus::kAccepted);
  std::promise<std::uint64_t> counted;
  REQUIRE(writer.post([&](Store& store) { counted.set_value(store.count_tiles(1).value()); }) ==
          SubmitStatus::kAccepted);
  gate.open();
  REQUIRE(callbacks.wait_for(1));
  CHECK(job_id.get_future().get() == 1);
  CHECK(callbacks.results()[0].at(0).outcome == TileOutcome::kStored);
  CHECK(counted.get_future().get() == 1);
  writer.stop();  // the count is updated after a task returns
  CHECK(writer.stats().tasks_run == 3);
}

TEST_CASE("a transaction holds at most max_batch_tiles tiles", "[store][writer]") {
  TempDir tmp;
  Store setup = open_ok(tmp.path());
  const std::int64_t job = make_job(setup);
  Callbacks callbacks;
  TileWriter writer(std::move(setup), WriterLimits{.max_batch_tiles = 4});
  Gate gate;
  gate.close(writer);
  for (std::uint32_t t = 0; t < 10; ++t) {
    REQUIRE(writer.submit(tile_write(job, t, 100), callbacks.done(t)) == SubmitStatus::kAccepted);
  }
  gate.open();
  REQUIRE(callbacks.wait_for(10));
  writer.stop();
  CHECK(writer.stats().batches == 3);
  CHECK(writer.stats().largest_batch == 4);
  CHECK(writer.stats().tiles_stored == 10);
}

TEST_CASE("a rejected tile does not fail the rest of its batch", "[store][writer]") {
  TempDir tmp;
  Store setup = open_ok(tmp.path());
  const std::int64_t job = make_job(setup);
  Callbacks callbacks;
  TileWriter writer(std::move(setup));
  Gate gate;
  gate.close(writer);
  REQUIRE(writer.submit(tile_write(job, 0, 100), callbacks.done(0)) == SubmitStatus::kAccepted);
  REQUIRE(writer.submit(tile_write(job + 1, 0, 100), callbacks.done(1)) == SubmitStatus::kAccepted);
  REQUIRE(writer.submit(tile_write(job, 1, 100), callbacks.done(2)) == SubmitStatus::kAccepted);
  gate.open();
  REQUIRE(callbacks.wait_for(3));
  auto r = callbacks.results();
  CHECK(r[0].at(0).outcome == TileOutcome::kStored);
  CHECK(r[1].at(0).outcome == TileOutcome::kRejected);
  CHECK(r[2].at(0).outcome == TileOutcome::kStored);
  CHECK(writer.stats().batches == 1);
}

TEST_CASE("a failed transaction fails every tile of the batch and stores none", "[store][writer]") {
  TempDir tmp;
  std::int64_t job = 0;
  {
    Store setup = open_ok(tmp.path());
    job = make_job(setup);
  }
  Callbacks callbacks;
  std::uint64_t stored_after = 0;
  SECTION("the database is full (a size cap stands in for the disk)") {
    TileWriter writer(open_ok(tmp.path(), OpenOptions{.max_database_bytes = 256 * 1024}));
    Gate gate;
    gate.close(writer);
    for (std::uint32_t t = 0; t < 10; ++t) {  // ~480 KiB in one transaction
      REQUIRE(writer.submit(tile_write(job, t, kBenchTileBytes), callbacks.done(t)) == SubmitStatus::kAccepted);
    }
    gate.open();
    REQUIRE(callbacks.wait_for(10));
    for (const auto& [tile, rs] : callbacks.results()) {
      CHECK(rs.at(0).outcome == TileOutcome::kFailed);
      CHECK_THAT(rs.at(0).error, Contains("full"));
    }
    CHECK(writer.stats().tiles_failed == 10);
    // The writer goes on: a batch that fits is stored.
    REQUIRE(writer.submit(tile_write(job, 0, kBenchTileBytes), callbacks.done(100)) == SubmitStatus::kAccepted);
    REQUIRE(callbacks.wait_for(11));
    CHECK(callbacks.results()[100].at(0).outcome == TileOutcome::kStored);
    stored_after = 1;
  }
  SECTION("another connection holds the write lock past the busy timeout") {
    TileWriter writer(open_ok(tmp.path(), OpenOptions{.busy_timeout = 50ms}));
    sqlite3* other = nullptr;
    REQUIRE(sqlite3_open_v2(tmp.db().c_str(), &other, SQLITE_OPEN_READWRITE, nullptr) == SQLITE_OK);
    REQUIRE(sqlite3_exec(other, "BEGIN IMMEDIATE", nullptr, nullptr, nullptr) == SQLITE_OK);
    for (std::uint32_t t = 0; t < 5; ++t) {
      REQUIRE(writer.submit(tile_write(job, t, 100), callbacks.done(t)) == SubmitStatus::kAccepted);
    }
    REQUIRE(callbacks.wait_for(5));
    for (const auto& [tile, rs] : callbacks.results()) {
      CHECK(rs.at(0).outcome == TileOutcome::kFailed);
      CHECK_THAT(rs.at(0).error, Contains("locked"));
    }
    REQUIRE(sqlite3_exec(other, "ROLLBACK", nullptr, nullptr, nullptr) == SQLITE_OK);
    sqlite3_close(other);
    REQUIRE(writer.submit(tile_write(job, 0, 100), callbacks.done(100)) == SubmitStatus::kAccepted);
    REQUIRE(callbacks.wait_for(6));
    CHECK(callbacks.results()[100].at(0).outcome == TileOutcome::kStored);
    stored_after = 1;
  }
  Store check = open_ok(tmp.path());
  CHECK(check.count_tiles(job).value() == stored_after);
}

TEST_CASE("the pending queue is bounded in tiles, bytes and tasks", "[store][writer]") {
  TempDir tmp;
  Store setup = open_ok(tmp.path());
  const std::int64_t job = make_job(setup);
  Callbacks callbacks;
  std::size_t accepted = 0;
  SECTION("tiles") {
    TileWriter writer(std::move(setup), WriterLimits{.max_pending_tiles = 3, .max_pending_bytes = 1 << 20});
    Gate gate;
    gate.close(writer);
    for (std::uint32_t t = 0; t < 3; ++t) {
      REQUIRE(writer.submit(tile_write(job, t, 100), callbacks.done(t)) == SubmitStatus::kAccepted);
    }
    CHECK(writer.submit(tile_write(job, 3, 100), callbacks.done(3)) == SubmitStatus::kBusy);
    CHECK(writer.stats().busy_refusals == 1);
    CHECK(writer.stats().pending_tiles == 3);
    gate.open();
    REQUIRE(callbacks.wait_for(3));
    CHECK(writer.submit(tile_write(job, 3, 100), callbacks.done(3)) == SubmitStatus::kAccepted);
    accepted = 4;
    REQUIRE(callbacks.wait_for(accepted));
  }
  SECTION("bytes") {
    TileWriter writer(std::move(setup), WriterLimits{.max_pending_tiles = 100, .max_pending_bytes = 2500});
    Gate gate;
    gate.close(writer);
    REQUIRE(writer.submit(tile_write(job, 0, 1000), callbacks.done(0)) == SubmitStatus::kAccepted);
    REQUIRE(writer.submit(tile_write(job, 1, 1000), callbacks.done(1)) == SubmitStatus::kAccepted);
    CHECK(writer.submit(tile_write(job, 2, 1000), callbacks.done(2)) == SubmitStatus::kBusy);
    CHECK(writer.submit(tile_write(job, 2, 3000), callbacks.done(2)) == SubmitStatus::kTooLarge);
    CHECK(writer.submit(tile_write(job, 2, 400), callbacks.done(2)) == SubmitStatus::kAccepted);
    CHECK(writer.stats().pending_bytes == 2 * (1000 + 8) + 400 + 8);
    gate.open();
    accepted = 3;
    REQUIRE(callbacks.wait_for(accepted));
    CHECK(writer.stats().pending_bytes == 0);
  }
  SECTION("tasks") {
    TileWriter writer(std::move(setup), WriterLimits{.max_pending_tasks = 2});
    Gate gate;
    gate.close(writer);  // the running task still counts
    CHECK(writer.post([](Store&) {}) == SubmitStatus::kAccepted);
    CHECK(writer.post([](Store&) {}) == SubmitStatus::kBusy);
    // Tiles have their own limits.
    CHECK(writer.submit(tile_write(job, 0, 100), callbacks.done(0)) == SubmitStatus::kAccepted);
    gate.open();
    accepted = 1;
    REQUIRE(callbacks.wait_for(accepted));
  }
  for (const auto& [tile, rs] : callbacks.results()) {
    REQUIRE(rs.size() == 1);  // refused submissions are never called back
    CHECK(rs[0].outcome == TileOutcome::kStored);
  }
  CHECK(callbacks.count() == accepted);
}

TEST_CASE("stop() commits and calls back everything accepted, then refuses", "[store][writer]") {
  TempDir tmp;
  Store setup = open_ok(tmp.path());
  const std::int64_t job = make_job(setup);
  Callbacks callbacks;
  std::uint32_t accepted = 0;
  {
    TileWriter writer(std::move(setup));
    Gate gate;
    gate.close(writer);
    for (; accepted < 100; ++accepted) {
      REQUIRE(writer.submit(tile_write(job, accepted, 500), callbacks.done(accepted)) == SubmitStatus::kAccepted);
    }
    auto stopped = std::async(std::launch::async, [&] { writer.stop(); });
    // stop() refuses new work at once, even while the writer is still busy.
    const auto deadline = std::chrono::steady_clock::now() + kWaitLimit;
    for (;;) {
      const SubmitStatus s = writer.submit(tile_write(job, accepted, 500), callbacks.done(accepted));
      if (s == SubmitStatus::kStopped) break;
      REQUIRE(s == SubmitStatus::kAccepted);
      ++accepted;
      REQUIRE(std::chrono::steady_clock::now() < deadline);
      std::this_thread::sleep_for(1ms);
    }
    CHECK(writer.post([](Store&) {}) == SubmitStatus::kStopped);
    CHECK(callbacks.count() == 0);  // still held by the gate
    gate.open();
    REQUIRE(stopped.wait_for(kWaitLimit) == std::future_status::ready);
    CHECK(callbacks.count() == accepted);  // stop() returned after every callback
    writer.stop();                         // idempotent
  }
  for (const auto& [tile, rs] : callbacks.results()) {
    REQUIRE(rs.size() == 1);
    CHECK(rs[0].outcome == TileOutcome::kStored);
  }
  Store check = open_ok(tmp.path());
  CHECK(check.count_tiles(job).value() == accepted);
}

// ---------------------------------------------------------------------------------------------
// Durability: what was acknowledged survives the death of the process that acknowledged it.

TEST_CASE("acknowledged tiles survive a SIGKILL of the writing process", "[store][writer][durability]") {
  TempDir tmp;
  std::int64_t job = 0;
  {
    Store setup = open_ok(tmp.path());
    job = make_job(setup);
  }
  constexpr std::size_t kAcksBeforeKill = 300;
  constexpr unsigned kChildLifetimeSeconds = 60;  // SIGALRM ends an orphaned child
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    // The child: write tiles as fast as possible and report each acknowledgement on the pipe,
    // after its commit returned, until killed. No Catch2 here; every exit is _exit.
    ::close(fds[0]);
    ::alarm(kChildLifetimeSeconds);
    const int fd = fds[1];
    auto opened = Store::open(tmp.path(), OpenOptions{.verify_integrity = false});
    if (!opened) ::_exit(2);
    TileWriter writer(std::move(opened).value(), WriterLimits{.max_pending_tiles = 256});
    for (std::uint32_t tile = 0; tile < 1'000'000; ++tile) {
      for (;;) {
        const SubmitStatus s = writer.submit(tile_write(job, tile, 4096), [fd, tile](CommitResult r) {
          if (r.outcome != TileOutcome::kStored) ::_exit(3);
          if (::write(fd, &tile, sizeof tile) != sizeof tile) ::_exit(4);
        });
        if (s == SubmitStatus::kAccepted) break;
        if (s != SubmitStatus::kBusy) ::_exit(5);
        std::this_thread::sleep_for(100us);
      }
    }
    ::pause();
    ::_exit(6);
  }
  ::close(fds[1]);
  std::set<std::uint32_t> acked;
  bool killed = false;
  const auto deadline = std::chrono::steady_clock::now() + kWaitLimit;
  for (;;) {
    if (!killed && acked.size() >= kAcksBeforeKill) {
      REQUIRE(::kill(pid, SIGKILL) == 0);
      killed = true;
    }
    const auto left =
        std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
    if (left <= 0ms) break;
    pollfd p{fds[0], POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) break;
    std::uint32_t tile;
    const ssize_t n = ::read(fds[0], &tile, sizeof tile);
    if (n == 0) break;  // every writer end closed: the child is gone
    REQUIRE(n == sizeof tile);
    acked.insert(tile);
  }
  ::close(fds[0]);
  if (!killed) ::kill(pid, SIGKILL);
  int status = 0;
  REQUIRE(::waitpid(pid, &status, 0) == pid);
  INFO("acknowledged before the kill: " << acked.size());
  REQUIRE(killed);
  REQUIRE(WIFSIGNALED(status));
  CHECK(WTERMSIG(status) == SIGKILL);

  // A full open (integrity check included) recovers the WAL and finds every acknowledged tile.
  Store store = open_ok(tmp.path());
  auto all = store.get_all_tiles(job);
  REQUIRE(all.ok());
  std::set<std::uint32_t> stored;
  for (const StoredTile& t : all.value()) {
    REQUIRE(t.pixels == make_pixels(job, t.tile, 4096));
    stored.insert(t.tile);
  }
  for (std::uint32_t tile : acked) REQUIRE(stored.count(tile) == 1);
  WARN(fmt::format("durability: {} tiles acknowledged before SIGKILL, {} found after reopening", acked.size(),
                   stored.size()));
}

// ---------------------------------------------------------------------------------------------
// Benchmark: figures only, no assertion on time.

TEST_CASE("benchmark: durable tile commits per second with 64x64 float tiles", "[store][benchmark]") {
  TempDir tmp;
  std::int64_t job = 0;
  {
    Store setup = open_ok(tmp.path());
    job = make_job(setup);
  }
  using Clock = std::chrono::steady_clock;
  auto seconds_since = [](Clock::time_point t0) { return std::chrono::duration<double>(Clock::now() - t0).count(); };
  std::uint32_t next_tile = 0;
  std::vector<Blob> pool;  // distinct contents, made before timing
  for (int i = 0; i < 64; ++i) pool.push_back(make_pixels(job, 1000000 + i, kBenchTileBytes));

  // 1. Store::insert_tiles directly: one transaction per batch of a fixed size.
  {
    Store store = open_ok(tmp.path(), OpenOptions{.verify_integrity = false});
    for (std::size_t batch : {1, 16, 256}) {
      const std::size_t total = batch == 1 ? 100 : 1024;
      const auto t0 = Clock::now();
      for (std::size_t done = 0; done < total; done += batch) {
        std::vector<TileWrite> w;
        for (std::size_t k = 0; k < batch; ++k) w.push_back({job, next_tile++, pool[k % pool.size()], "bench", 0});
        REQUIRE(store.insert_tiles(w).ok());
      }
      const double s = seconds_since(t0);
      WARN(fmt::format("insert_tiles, {:>3} tiles per transaction: {:>7.0f} tiles/s ({:.2f} ms per transaction)", batch,
                       total / s, 1e3 * s / (total / batch)));
    }
  }
  // 2. TileWriter, four producers submitting as fast as the bounded queue lets them.
  {
    std::atomic<std::uint64_t> stored{0}, busy{0};
    TileWriter writer(open_ok(tmp.path(), OpenOptions{.verify_integrity = false}));
    constexpr std::uint32_t kProducers = 4, kPerProducer = 1000;
    const std::uint32_t base = next_tile;
    const auto t0 = Clock::now();
    std::vector<std::thread> producers;
    for (std::uint32_t p = 0; p < kProducers; ++p) {
      producers.emplace_back([&, p] {
        for (std::uint32_t k = 0; k < kPerProducer; ++k) {
          for (;;) {
            const std::uint32_t tile = base + p * kPerProducer + k;
            const SubmitStatus s =
                writer.submit({job, tile, pool[tile % pool.size()], "bench", 0}, [&](CommitResult r) {
                  if (r.outcome == TileOutcome::kStored) ++stored;
                });
            if (s == SubmitStatus::kAccepted) break;
            ++busy;
            std::this_thread::sleep_for(100us);
          }
        }
      });
    }
    for (auto& th : producers) th.join();
    writer.stop();
    const double s = seconds_since(t0);
    const auto stats = writer.stats();
    CHECK(stored == kProducers * kPerProducer);
    WARN(fmt::format(
        "TileWriter, {} producers: {:.0f} durable tiles/s ({} tiles of {} bytes in {:.2f} s; {} transactions, "
        "mean {:.1f} and largest {} tiles; {:.0f}% of the wall time inside transactions; {} busy refusals)",
        kProducers, kProducers * kPerProducer / s, kProducers * kPerProducer, kBenchTileBytes, s, stats.batches,
        double(stats.tiles_stored) / stats.batches, stats.largest_batch, 100 * stats.write_seconds / s, busy.load()));
  }
  // 3. The floor under SQLite: the same bytes appended to a plain file, one fdatasync per 256.
  {
    const std::string path = tmp.path() + "/raw.bin";
    const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    REQUIRE(fd >= 0);
    constexpr std::size_t kTotal = 1024, kBatch = 256;
    const auto t0 = Clock::now();
    for (std::size_t i = 0; i < kTotal; ++i) {
      const Blob& b = pool[i % pool.size()];
      REQUIRE(::write(fd, b.data(), b.size()) == static_cast<ssize_t>(b.size()));
      if ((i + 1) % kBatch == 0) REQUIRE(::fdatasync(fd) == 0);
    }
    const double s = seconds_since(t0);
    ::close(fd);
    WARN(fmt::format("plain file append + fdatasync per {}: {:.0f} tiles/s ({:.0f} MB/s)", kBatch, kTotal / s,
                     kTotal * kBenchTileBytes / s / 1e6));
  }
}

}  // namespace
