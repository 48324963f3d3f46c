// Tests for dtraced::store::TileWriter: group commit from many threads (exactly-once "stored",
// duplicates, rejected tiles, failed batches, bounded queue, draining stop), acknowledged tiles
// surviving a SIGKILL (a forked child writes, the parent kills it and reopens), and a commit-rate
// benchmark that prints figures only.
#include <fcntl.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <future>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "child_process.h"
#include "eventually.h"
#include "store_testing.h"

namespace {
using namespace dtraced::testing;
}  // namespace

// ---------------------------------------------------------------------------------------------
// Group commit.

TEST_CASE("1000 tiles submitted from several threads are each stored exactly once", "[store][writer]") {
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
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
  StoreDir tmp;
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

TEST_CASE("tiles queued together are one commit, and each is acknowledged only after it", "[store][writer]") {
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
  constexpr std::uint32_t kTiles = 50;
  TileWriter writer(std::move(setup));
  // Another connection, used only by the callbacks (they run one at a time on the writer thread):
  // what it reads is what is on disk for everyone.
  sqlite3* other = nullptr;
  REQUIRE(sqlite3_open_v2(tmp.db().c_str(), &other, SQLITE_OPEN_READONLY, nullptr) == SQLITE_OK);
  const auto committed_tiles = [&] {
    sqlite3_stmt* s = nullptr;
    REQUIRE(sqlite3_prepare_v2(other, "SELECT count(*) FROM tiles", -1, &s, nullptr) == SQLITE_OK);
    REQUIRE(sqlite3_step(s) == SQLITE_ROW);
    const auto n = sqlite3_column_int64(s, 0);
    sqlite3_finalize(s);
    return n;
  };
  Callbacks callbacks;
  std::vector<std::int64_t> seen(kTiles, -1);
  Gate gate;
  gate.close(writer);
  for (std::uint32_t t = 0; t < kTiles; ++t) {
    auto done = [&, t, inner = callbacks.done(t)](CommitResult r) {
      seen[t] = committed_tiles();
      inner(std::move(r));
    };
    REQUIRE(writer.submit(tile_write(job, t, 1000), done) == SubmitStatus::kAccepted);
  }
  gate.open();
  REQUIRE(callbacks.wait_for(kTiles));
  writer.stop();
  sqlite3_close(other);
  CHECK(writer.stats().batches == 1);
  CHECK(writer.stats().largest_batch == kTiles);
  // Every acknowledgement came after the whole transaction was committed: all 50 were visible.
  for (std::uint32_t t = 0; t < kTiles; ++t) CHECK(seen[t] == kTiles);
}

TEST_CASE("a transaction holds at most max_batch_tiles tiles", "[store][writer]") {
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
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

namespace {

// A writer that just committed a batch of `first` tiles, and gathers the next batch for a long
// time (so only a full batch, a task or stop() ends a gather within the test's wait limits).
struct Gathering {
  explicit Gathering(StoreDir& tmp, std::uint32_t first) {
    auto [setup, id] = seeded(tmp);
    job = id;
    writer.emplace(std::move(setup), WriterLimits{.checkpoint_when_idle = std::chrono::minutes(10),
                                                  .gather_wait = std::chrono::minutes(10)});
    Gate gate;
    gate.close(*writer);
    for (std::uint32_t t = 0; t < first; ++t) submit(t);
    gate.open();
    REQUIRE(callbacks.wait_for(first));
    REQUIRE(writer->stats().batches == 1);
  }
  void submit(std::uint32_t tile) {
    REQUIRE(writer->submit(tile_write(job, tile, 100), callbacks.done(tile)) == SubmitStatus::kAccepted);
  }
  // Submits one tile and returns once the writer waits for more.
  void start_gather(std::uint32_t tile) {
    const std::uint64_t before = writer->stats().gather_waits;
    submit(tile);
    REQUIRE(eventually([&] { return writer->stats().gather_waits == before + 1; }));
  }

  std::int64_t job = 0;
  Callbacks callbacks;
  std::optional<TileWriter> writer;
};

}  // namespace

TEST_CASE("under load the writer waits for as many tiles as its last batch held, then writes them together",
          "[store][writer]") {
  StoreDir tmp;
  Gathering g(tmp, 8);
  g.start_gather(8);
  // Seven more make eight: one transaction, without waiting out gather_wait.
  for (std::uint32_t t = 9; t < 16; ++t) g.submit(t);
  REQUIRE(g.callbacks.wait_for(16));
  const auto stats = g.writer->stats();
  CHECK(stats.batches == 2);
  CHECK(stats.largest_batch == 8);
  CHECK(stats.tiles_stored == 16);
  CHECK(stats.gather_timeouts == 0);
  // A single tile in flight (the last batch held one) is written at once: nothing to gather.
  g.writer->stop();
  StoreDir other;
  Gathering lone(other, 1);
  lone.submit(1);
  REQUIRE(lone.callbacks.wait_for(2));
  CHECK(lone.writer->stats().gather_waits == 0);
  CHECK(lone.writer->stats().batches == 2);
}

TEST_CASE("a task or a stop ends the writer's wait for a fuller batch", "[store][writer]") {
  StoreDir tmp;
  Gathering g(tmp, 4);
  g.start_gather(4);
  std::promise<void> ran;
  REQUIRE(g.writer->post([&](Store&) { ran.set_value(); }) == SubmitStatus::kAccepted);
  REQUIRE(ran.get_future().wait_for(kWaitLimit) == std::future_status::ready);
  REQUIRE(g.callbacks.wait_for(5));
  CHECK(g.writer->stats().tiles_stored == 5);

  CHECK(g.writer->stats().gather_timeouts == 0);

  StoreDir other;
  Gathering stopped(other, 4);
  stopped.start_gather(4);
  stopped.writer->stop();  // writes and acknowledges the tile it was waiting with
  CHECK(stopped.callbacks.count() == 5);
  CHECK(stopped.writer->stats().tiles_stored == 5);
  CHECK(stopped.writer->stats().gather_timeouts == 0);
  Store check = open_ok(other.path());
  CHECK(check.count_tiles(stopped.job).value() == 5);
}

namespace {

// Submits `tiles` tiles of `bytes` each while the writer is held, then lets it write them all in
// a row (never idle); returns the largest -wal file seen by any tile's callback (after its commit
// and before the writer's next checkpoint).
std::uintmax_t largest_wal_in_burst(TileWriter& writer, const std::string& wal, std::int64_t job, std::uint32_t tiles,
                                    std::size_t bytes) {
  Callbacks callbacks;
  std::atomic<std::uintmax_t> largest{0};
  Gate gate;
  gate.close(writer);
  for (std::uint32_t t = 0; t < tiles; ++t) {
    auto done = [&, inner = callbacks.done(t)](CommitResult r) {
      std::error_code ec;
      const std::uintmax_t size = std::filesystem::file_size(wal, ec);
      if (!ec && size > largest) largest = size;
      inner(std::move(r));
    };
    REQUIRE(writer.submit(tile_write(job, t, bytes), done) == SubmitStatus::kAccepted);
  }
  gate.open();
  REQUIRE(callbacks.wait_for(tiles));
  return largest.load();
}

}  // namespace

TEST_CASE("the WAL stays under its bound over a long burst and is emptied when the writer is idle",
          "[store][writer][wal]") {
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
  const std::string wal = setup.path() + "-wal";
  constexpr std::uint32_t kTiles = 1200;  // 150 transactions in a row, 19.7 MB of pixels
  constexpr std::size_t kBytes = 16 << 10;
  constexpr std::uint64_t kBound = 1 << 20;
  constexpr WriterLimits kLimits{.max_batch_tiles = 8, .checkpoint_wal_bytes = kBound};
  TileWriter writer(std::move(setup), kLimits);
  const std::uintmax_t largest = largest_wal_in_burst(writer, wal, job, kTiles, kBytes);
  CHECK(writer.stats().tiles_stored == kTiles);
  CHECK(writer.stats().batches == kTiles / 8);
  // At most the bound plus one batch: eight 16 KiB tiles are 128 KiB of pixels; the WAL adds frame
  // headers and the b-tree pages.
  INFO("largest WAL: " << largest << " bytes");
  CHECK(largest <= kBound + (256 << 10));
  CHECK(largest >= kBound / 2);  // the bound is what checkpoints, not the batches
  // Half the bound asks for a checkpoint beside the commits; a batch (~135 KiB) is less than half.
  CHECK(writer.stats().checkpoints_background > 0);
  WARN(fmt::format("{} checkpoints, {} of them beside the commits; the writer waited {:.3f} s for them",
                   writer.stats().checkpoints, writer.stats().checkpoints_background,
                   writer.stats().checkpoint_seconds));
  // 19.7 MB through a WAL of at most ~1.25 MiB: at least one checkpoint per 1.25 MiB.
  CHECK(writer.stats().checkpoints >= kTiles * kBytes / (kBound + (256 << 10)));
  // Idle: the WAL file is emptied (its bytes are all in the database).
  CHECK(eventually([&] { return std::filesystem::file_size(wal) == 0; }));
  writer.stop();
  CHECK(writer.stats().checkpoints_failed == 0);
  Store check = open_ok(tmp.path());
  CHECK(check.count_tiles(job).value() == kTiles);
}

TEST_CASE("a checkpoint connection copies the WAL while the writer's connection writes, which then starts it over",
          "[store][writer][wal]") {
  StoreDir tmp;
  auto [writer, job] = seeded(tmp);
  require_ok(writer.manage_checkpoints());
  const std::string wal = writer.path() + "-wal";
  auto opened = writer.open_checkpoint_connection();
  if (!opened) FAIL(opened.error().message);
  Store checkpointer = std::move(opened).value();
  constexpr std::size_t kBytes = 16 << 10;
  const auto insert = [&](Store& s, std::uint32_t first) {
    std::vector<TileWrite> writes;
    for (std::uint32_t t = first; t < first + 20; ++t) writes.push_back(tile_write(job, t, kBytes));
    return s.insert_tiles(writes);
  };
  REQUIRE(insert(writer, 0).ok());
  const std::uint64_t wal_after_first = writer.wal_bytes();
  REQUIRE(wal_after_first > 20 * kBytes);

  // A PASSIVE checkpoint neither waits for an open write transaction nor is refused by it: it
  // copies what was committed before it.
  int first_frames = 0;
  require_ok(writer.transaction([&]() -> Status {
    REQUIRE(insert(writer, 20).ok());
    auto r = checkpointer.checkpoint(dtraced::store::CheckpointMode::kReuse);
    if (!r) FAIL(r.error().message);
    CHECK(r.value().complete);
    CHECK(r.value().wal_frames > 0);
    CHECK(r.value().copied_frames == r.value().wal_frames);
    first_frames = r.value().wal_frames;
    return {};
  }));
  // The commit came after that checkpoint: its frames are still to copy, so the WAL goes on
  // growing until a checkpoint copies them too.
  const std::uint64_t wal_after_second = writer.wal_bytes();
  CHECK(wal_after_second > wal_after_first);
  auto second = checkpointer.checkpoint(dtraced::store::CheckpointMode::kReuse);
  if (!second) FAIL(second.error().message);
  CHECK(second.value().complete);
  CHECK(second.value().wal_frames > first_frames);
  CHECK(second.value().copied_frames == second.value().wal_frames);
  // Every frame is copied: the writer's next commit starts the WAL over from its beginning.
  const std::uintmax_t file = std::filesystem::file_size(wal);
  REQUIRE(insert(writer, 40).ok());
  CHECK(writer.wal_bytes() < wal_after_second);
  CHECK(std::filesystem::file_size(wal) == file);

  // query_only: the checkpoint connection can change no row.
  CHECK_FALSE(insert(checkpointer, 60).ok());
  Store check = open_ok(tmp.path(), OpenOptions{.verify_integrity = false});
  CHECK(check.count_tiles(job).value() == 60);
}

TEST_CASE("under the bound nothing is checkpointed while tiles keep coming, not even by SQLite",
          "[store][writer][wal]") {
  StoreDir tmp;
  Store setup = open_ok(tmp.path(), OpenOptions{.pixels_in_rows = true});  // tiles that weigh on the WAL
  const std::int64_t job = make_job(setup);
  const std::string wal = setup.path() + "-wal";
  // 640 tiles of 16 KiB: 10.5 MB of pixels in about 1,260 frames of 16 KiB pages (a tile's row and
  // its overflow page), past SQLite's own automatic checkpoint (1000 frames), and under half the
  // bound, where the writer's background checkpoints would start.
  constexpr std::uint32_t kTiles = 640;
  constexpr std::size_t kBytes = 16 << 10;
  constexpr WriterLimits kLimits{.max_batch_tiles = 4,
                                 .checkpoint_wal_bytes = std::uint64_t{64} << 20,
                                 .checkpoint_when_idle = std::chrono::minutes(1)};
  TileWriter writer(std::move(setup), kLimits);
  const std::uintmax_t largest = largest_wal_in_burst(writer, wal, job, kTiles, kBytes);
  INFO("largest WAL: " << largest << " bytes");
  CHECK(largest >= kTiles * kBytes);  // every tile's pages are still in the WAL
  CHECK(largest >= 1000 * (16 << 10));
  CHECK(writer.stats().checkpoints == 0);
  writer.stop();  // the stop checkpoints what is left
  CHECK(writer.stats().checkpoints == 1);
  CHECK(std::filesystem::file_size(wal) == 0);
  Store check = open_ok(tmp.path());
  CHECK(check.count_tiles(job).value() == kTiles);
}

TEST_CASE("a trickle of tiles is not checkpointed after every batch, and a stop checkpoints what is left",
          "[store][writer][wal]") {
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
  const std::string wal = setup.path() + "-wal";
  // Idle for a minute before a checkpoint: the test never waits that long between tiles.
  constexpr WriterLimits kLimits{.checkpoint_when_idle = std::chrono::minutes(1)};
  TileWriter writer(std::move(setup), kLimits);
  Callbacks callbacks;
  // One tile at a time, each acknowledged before the next is sent: the queue runs empty after
  // every batch, as with a few workers sending small tiles.
  for (std::uint32_t t = 0; t < 10; ++t) {
    REQUIRE(writer.submit(tile_write(job, t, 1000), callbacks.done(t)) == SubmitStatus::kAccepted);
    REQUIRE(callbacks.wait_for(t + 1));
  }
  CHECK(writer.stats().batches == 10);
  CHECK(writer.stats().checkpoints == 0);
  CHECK(std::filesystem::file_size(wal) > 0);
  writer.stop();
  CHECK(writer.stats().checkpoints == 1);
  CHECK(std::filesystem::file_size(wal) == 0);
  Store check = open_ok(tmp.path());
  CHECK(check.count_tiles(job).value() == 10);
}

TEST_CASE("a failing checkpoint is logged once and retried, and no acknowledged tile is lost", "[store][writer][wal]") {
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
  const std::string log = tmp.path() + "/stderr.log";
  constexpr std::uint32_t kTiles = 200;
  constexpr std::size_t kBytes = 16 << 10;
  // The child's files may not grow past 1 MiB (RLIMIT_FSIZE, a full disk's stand-in, set in the
  // child alone): once the database reaches it, checkpoints fail; the WAL cannot start over and
  // grows to it too, and then commits fail. The limit is lifted once a commit failed.
  ForkedChild child([&](int fd) {
    const int log_fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (log_fd < 0 || ::dup2(log_fd, STDERR_FILENO) < 0) ::_exit(2);
    ::signal(SIGXFSZ, SIG_IGN);  // a write past the limit fails with EFBIG instead
    rlimit limit{};
    if (::getrlimit(RLIMIT_FSIZE, &limit) != 0) ::_exit(3);
    const rlimit unlimited = limit;
    limit.rlim_cur = 1 << 20;
    if (::setrlimit(RLIMIT_FSIZE, &limit) != 0) ::_exit(4);
    // Tiles in their rows: the WAL and the database grow with them (store.h, pixels_in_rows).
    auto opened = Store::open(tmp.path(), OpenOptions{.verify_integrity = false, .pixels_in_rows = true});
    if (!opened) ::_exit(5);
    std::optional<TileWriter> writer;
    writer.emplace(std::move(opened).value(), WriterLimits{.checkpoint_wal_bytes = 256 << 10});
    // One tile at a time, each reported (tile, outcome) once acknowledged.
    const auto store_tile = [&](std::uint32_t tile) {
      std::atomic<int> outcome{-1};
      const SubmitStatus s = writer->submit(tile_write(job, tile, kBytes), [&](CommitResult r) {
        const unsigned char report[5] = {static_cast<unsigned char>(tile), static_cast<unsigned char>(tile >> 8), 0, 0,
                                         static_cast<unsigned char>(r.outcome)};
        if (::write(fd, report, sizeof report) != sizeof report) ::_exit(6);
        outcome = static_cast<int>(r.outcome);
      });
      if (s != SubmitStatus::kAccepted) ::_exit(7);
      while (outcome < 0) std::this_thread::sleep_for(100us);
      return static_cast<TileOutcome>(outcome.load());
    };
    std::vector<std::uint32_t> failed;
    for (std::uint32_t tile = 0; tile < kTiles; ++tile) {
      if (store_tile(tile) == TileOutcome::kFailed) failed.push_back(tile);
      if (failed.size() == 1 && ::setrlimit(RLIMIT_FSIZE, &unlimited) != 0) ::_exit(8);
    }
    for (std::uint32_t tile : failed) {
      if (store_tile(tile) != TileOutcome::kStored) ::_exit(9);
    }
    writer->stop();
    const auto stats = writer->stats();
    writer.reset();
    const unsigned char summary[5] = {
        0xff, 0xff, static_cast<unsigned char>(std::min<std::uint64_t>(stats.checkpoints_failed, 255)),
        static_cast<unsigned char>(failed.size()), 0xff};
    if (::write(fd, summary, sizeof summary) != sizeof summary) ::_exit(10);
    ::pause();
    ::_exit(11);
  });
  // The summary (0xff 0xff ...) comes last; a tile's second byte is 0.
  std::string reports;
  const auto summarised = [](const std::string& r) {
    return r.size() >= 5 && r.size() % 5 == 0 && static_cast<unsigned char>(r[r.size() - 4]) == 0xff;
  };
  REQUIRE(child.read(reports, summarised, kWaitLimit));
  child.kill_and_wait();
  const auto byte = [&](std::size_t i) { return static_cast<unsigned char>(reports[i]); };
  const std::size_t summary = reports.size() - 5;
  const unsigned checkpoints_failed = byte(summary + 2), tiles_failed = byte(summary + 3);
  INFO("checkpoints failed: " << checkpoints_failed << ", tiles failed once: " << tiles_failed);
  CHECK(tiles_failed >= 1);        // the limit did stop commits
  CHECK(checkpoints_failed >= 2);  // and checkpoints, more than once
  std::set<std::uint32_t> stored;  // acknowledged as stored
  for (std::size_t i = 0; i < summary; i += 5) {
    const std::uint32_t tile = byte(i) | (std::uint32_t{byte(i + 1)} << 8);
    const auto outcome = static_cast<TileOutcome>(byte(i + 4));
    CHECK((outcome == TileOutcome::kStored || outcome == TileOutcome::kFailed));
    if (outcome == TileOutcome::kStored) CHECK(stored.insert(tile).second);
  }
  CHECK(stored.size() == kTiles);
  // Logged once for the whole streak of failures.
  const std::string logged = file_bytes(log);
  INFO(logged);
  std::size_t warnings = 0;
  for (std::size_t at = 0; (at = logged.find("logged once until one succeeds", at)) != std::string::npos; ++at) {
    ++warnings;
  }
  CHECK(warnings == 1);
  Store check = open_ok(tmp.path());
  auto all = check.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == kTiles);
  for (const StoredTile& t : all.value()) CHECK(t.pixels == make_pixels(job, t.tile, kBytes));
}

TEST_CASE("a rejected tile does not fail the rest of its batch", "[store][writer]") {
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
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
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
  Callbacks callbacks;
  std::uint64_t stored_after = 0;
  SECTION("the database is full (a size cap stands in for the disk)") {
    // An empty database of 16 KiB pages is about 200 KiB (a page or two per table and index).
    TileWriter writer(open_ok(tmp.path(), OpenOptions{.max_database_bytes = 512 * 1024}));
    Gate gate;
    gate.close(writer);
    for (std::uint32_t t = 0; t < 20; ++t) {  // ~960 KiB in one transaction
      REQUIRE(writer.submit(tile_write(job, t, kBenchTileBytes), callbacks.done(t)) == SubmitStatus::kAccepted);
    }
    gate.open();
    REQUIRE(callbacks.wait_for(20));
    for (const auto& [tile, rs] : callbacks.results()) {
      CHECK(rs.at(0).outcome == TileOutcome::kFailed);
      CHECK_THAT(rs.at(0).error, Contains("full"));
    }
    CHECK(writer.stats().tiles_failed == 20);
    // The writer goes on: a batch that fits is stored.
    REQUIRE(writer.submit(tile_write(job, 0, kBenchTileBytes), callbacks.done(100)) == SubmitStatus::kAccepted);
    REQUIRE(callbacks.wait_for(21));
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
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
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
  StoreDir tmp;
  auto [setup, job] = seeded(tmp);
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
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
  constexpr std::size_t kAcksBeforeKill = 300;
  ForkedChild child([&tmp, job](int fd) {
    // Write tiles as fast as possible and report each acknowledgement on the pipe, after its
    // commit returned, until killed.
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
  });
  std::string reports;
  const auto enough = [](const std::string& r) { return r.size() >= kAcksBeforeKill * sizeof(std::uint32_t); };
  REQUIRE(child.read(reports, enough, kWaitLimit));
  const int status = child.kill_and_wait();
  CHECK(WTERMSIG(status) == SIGKILL);
  // What the child wrote before it died: the pipe holds it until read.
  child.read(
      reports, [](const std::string&) { return false; }, kWaitLimit);
  std::set<std::uint32_t> acked;
  for (std::size_t i = 0; i + sizeof(std::uint32_t) <= reports.size(); i += sizeof(std::uint32_t)) {
    std::uint32_t tile = 0;
    std::memcpy(&tile, reports.data() + i, sizeof tile);
    acked.insert(tile);
  }
  INFO("acknowledged before the kill: " << acked.size());

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
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
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
