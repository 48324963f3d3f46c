// What the store's tests share: a state directory, deterministic tile pixels, jobs and tile writes
// to store, raw SQLite to build the files the store must refuse, and helpers that collect the
// writer's callbacks or hold its thread inside a task (every wait bounded by kWaitLimit).
#pragma once

#include <sqlite3.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <iterator>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "store/store.h"
#include "store/tile_writer.h"
#include "temp_dir.h"

namespace dtraced::testing {

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
inline constexpr std::size_t kBenchTileBytes = 64 * 64 * 3 * sizeof(float);
// Every wait in this file is bounded by this, so a hang fails instead of stalling CI.
inline constexpr auto kWaitLimit = 60s;

// A fresh state directory (a TempDir) named by string, as the store takes it, with its database's path.
class StoreDir {
 public:
  StoreDir() : path_(dir_.str()) {}
  const std::string& path() const { return path_; }
  std::string db() const { return path_ + "/dtraced.db"; }

 private:
  TempDir dir_{"dtraced-store"};
  std::string path_;
};

inline std::string file_bytes(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  REQUIRE(in);
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

// Replaces the file's contents, or with an offset overwrites bytes in place.
inline void write_bytes(const std::string& path, const std::string& bytes, std::streamoff offset = -1) {
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
inline Blob make_pixels(std::int64_t job, std::uint32_t tile, std::size_t bytes, std::uint64_t salt = 0) {
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

inline Store open_ok(const std::string& dir, const OpenOptions& options = {}) {
  auto r = Store::open(dir, options);
  if (!r) FAIL(r.error().message);
  return std::move(r).value();
}

inline std::string open_error(const std::string& dir) {
  auto r = Store::open(dir);
  REQUIRE_FALSE(r.ok());
  return r.error().message;
}

inline void require_ok(const Status& st) {
  if (!st) FAIL(st.error().message);
}

inline StoredJob sample_job(std::string digest = "digest-a") {
  StoredJob job;
  job.digest = std::move(digest);
  job.settings_json = R"({"width":64,"height":48})";
  job.output = "out.png";
  job.priority = -3;
  job.tile_size = 32;
  job.created_unix = 1700000000;
  return job;
}

inline std::int64_t make_job(Store& store, std::optional<std::string> key = std::nullopt) {
  require_ok(store.put_scene("digest-a", R"({"scene":1})"));
  StoredJob job = sample_job();
  job.client_key = std::move(key);
  auto id = store.insert_job(job);
  if (!id) FAIL(id.error().message);
  return id.value();
}

// A job stored in the directory's database, through a connection closed again.
inline std::int64_t job_in(const StoreDir& dir) {
  Store setup = open_ok(dir.path());
  return make_job(setup);
}

// A connection to the directory's database, which holds one job.
struct Seeded {
  Store store;
  std::int64_t job = 0;
};
inline Seeded seeded(const StoreDir& dir) {
  Store store = open_ok(dir.path());
  const std::int64_t job = make_job(store);
  return {std::move(store), job};
}

inline TileWrite tile_write(std::int64_t job, std::uint32_t tile, std::size_t bytes, std::uint64_t salt = 0) {
  return TileWrite{job, tile, make_pixels(job, tile, bytes, salt), "worker-1", 1700000100 + tile};
}

// Raw SQLite, to build the files the store must refuse.
inline void raw_exec(const std::string& path, const std::string& sql) {
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

inline std::string raw_query_text(const std::string& path, const std::string& sql) {
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

}  // namespace dtraced::testing
