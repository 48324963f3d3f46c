// Tests for tile pixels in files of their own (store/pixel_files.h, schema version 4): where the
// bytes go, a crash between the append and the COMMIT, a truncated file, a damaged tile, a
// version 3 database whose tiles hold their pixels in rows, and the files of deleted jobs.
#include <fcntl.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include <boost/crc.hpp>
#include <catch2/catch.hpp>

#include "store/pixel_files.h"
#include "store_testing.h"
#include "util/crc32c.h"

namespace {
using namespace dtraced::testing;
namespace store = dtraced::store;
namespace util = dtraced::util;

constexpr std::size_t kTileBytes = 12360;  // a 32-px tile of RGB float32 and its header

std::string pixel_file(const StoreDir& dir, std::int64_t job) {
  return dir.path() + "/pixels/job-" + std::to_string(job) + ".pixels";
}

// The committed length of the job's pixel file (pixel_files.bytes).
std::uint64_t committed(const StoreDir& dir, std::int64_t job) {
  const std::string text =
      raw_query_text(dir.db(), "SELECT coalesce(max(bytes), 0) FROM pixel_files WHERE job = " + std::to_string(job));
  return std::stoull(text);
}

std::vector<std::uint32_t> tiles_of(const std::vector<StoredTile>& tiles) {
  std::vector<std::uint32_t> out;
  for (const StoredTile& t : tiles) out.push_back(t.tile);
  return out;
}

void store_tiles(Store& s, std::int64_t job, std::uint32_t first, std::uint32_t count, std::uint64_t salt = 0) {
  std::vector<TileWrite> writes;
  for (std::uint32_t t = first; t < first + count; ++t) writes.push_back(tile_write(job, t, kTileBytes, salt));
  auto r = s.insert_tiles(writes);
  if (!r) FAIL(r.error().message);
  for (const CommitResult& c : r.value()) REQUIRE(c.outcome == TileOutcome::kStored);
}

// The version 3 schema (tiles hold their pixels), as dtraced wrote it before pixel files.
constexpr const char* kVersion3Sql = R"sql(
CREATE TABLE meta(key TEXT PRIMARY KEY NOT NULL, value ANY) STRICT;
CREATE TABLE scenes(digest TEXT PRIMARY KEY NOT NULL, json TEXT NOT NULL) STRICT;
CREATE TABLE jobs(
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
) STRICT;
CREATE TABLE tiles(
  job INTEGER NOT NULL REFERENCES jobs(id),
  tile INTEGER NOT NULL CHECK (tile BETWEEN 0 AND 4294967295),
  pixels BLOB NOT NULL,
  worker TEXT NOT NULL,
  stored_unix INTEGER NOT NULL,
  PRIMARY KEY (job, tile)
) STRICT;
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
INSERT INTO meta(key, value) VALUES ('schema_version', 3);
INSERT INTO meta(key, value) VALUES ('last_job_id', 1);
INSERT INTO scenes VALUES ('digest-a', '{"scene":1}');
INSERT INTO jobs VALUES (1, 'digest-a', '{}', 'a.png', 0, 32, 'rendering', 1700000000, 0, NULL);
INSERT INTO tiles VALUES (1, 0, x'00112233', 'w1', 1700000050);
INSERT INTO tiles VALUES (1, 1, x'44556677', 'w2', 1700000060);
)sql";

}  // namespace

TEST_CASE("CRC-32C gives the standard check value", "[store][pixels]") {
  // util::crc32c: the checksum of the pixel files and of `dtraced render`'s resume file.
  const std::string_view check = "123456789";
  CHECK(util::crc32c(std::span(reinterpret_cast<const std::uint8_t*>(check.data()), check.size())) == 0xE3069283u);
  CHECK(util::crc32c({}) == 0u);
  // The CPU's instruction (where it has SSE4.2) against Boost.CRC's CRC-32C, the fallback, at every
  // length around its 8-byte steps and at offsets that break their alignment.
  std::vector<std::uint8_t> bytes(300);
  for (std::size_t i = 0; i < bytes.size(); ++i) bytes[i] = static_cast<std::uint8_t>(i * 131 + 7);
  for (std::size_t at = 0; at < 8; ++at) {
    for (std::size_t n = 0; at + n <= bytes.size(); n += (n < 40 ? 1 : 37)) {
      boost::crc_optimal<32, 0x1EDC6F41u, 0xFFFFFFFFu, 0xFFFFFFFFu, true, true> boost_crc;
      boost_crc.process_bytes(bytes.data() + at, n);
      INFO("offset " << at << ", " << n << " bytes");
      CHECK(util::crc32c(std::span(bytes.data() + at, n)) == boost_crc.checksum());
    }
  }
}

TEST_CASE("a tile's pixels go to its job's file, once, and read back from another connection", "[store][pixels]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t job = make_job(s);
  store_tiles(s, job, 0, 20);
  CHECK(committed(tmp, job) == 20 * kTileBytes);
  CHECK(fs::file_size(pixel_file(tmp, job)) >= 20 * kTileBytes);
  CHECK(raw_query_text(tmp.db(), "SELECT sum(length(pixels)) FROM tiles") == "0");
  Store other = open_ok(tmp.path());
  auto all = other.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == 20);
  for (const StoredTile& t : all.value()) CHECK(t.pixels == make_pixels(job, t.tile, kTileBytes));
  CHECK(other.get_tile(job, 7).value()->pixels == make_pixels(job, 7, kTileBytes));
  // A duplicate is compared with the bytes in the file, and changes nothing.
  auto again = s.insert_tiles(std::vector{tile_write(job, 3, kTileBytes), tile_write(job, 4, kTileBytes, 1)});
  REQUIRE(again.ok());
  CHECK(again.value()[0].outcome == TileOutcome::kAlreadyPresent);
  CHECK(again.value()[0].identical);
  CHECK(again.value()[1].outcome == TileOutcome::kAlreadyPresent);
  CHECK_FALSE(again.value()[1].identical);
  // ... and so is one within the same batch, whose first copy is not on disk yet.
  auto batch = s.insert_tiles(std::vector{tile_write(job, 30, kTileBytes), tile_write(job, 30, kTileBytes)});
  REQUIRE(batch.ok());
  CHECK(batch.value()[1].outcome == TileOutcome::kAlreadyPresent);
  CHECK(batch.value()[1].identical);
  CHECK(committed(tmp, job) == 21 * kTileBytes);
}

TEST_CASE("a crash between the pixel append and the COMMIT leaves bytes that nothing reads", "[store][pixels]") {
  StoreDir tmp;
  std::int64_t job = 0;
  {
    Store s = open_ok(tmp.path());
    job = make_job(s);
    store_tiles(s, job, 0, 3);
  }
  // The child appends (and syncs) the pixels of tiles 3 to 7, then dies before the COMMIT.
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    auto s = Store::open(tmp.path(), OpenOptions{.verify_integrity = false});
    if (!s) ::_exit(2);
    (void)s.value().transaction([&]() -> Status {
      std::vector<TileWrite> writes;
      for (std::uint32_t t = 3; t < 8; ++t) writes.push_back(tile_write(job, t, kTileBytes, 7));
      if (!s.value().insert_tiles(writes)) ::_exit(3);
      ::kill(::getpid(), SIGKILL);
      ::_exit(4);
    });
    ::_exit(5);
  }
  int status = 0;
  REQUIRE(::waitpid(pid, &status, 0) == pid);
  REQUIRE(WIFSIGNALED(status));
  CHECK(fs::file_size(pixel_file(tmp, job)) >= 8 * kTileBytes);  // appended, never committed
  CHECK(committed(tmp, job) == 3 * kTileBytes);

  Store s = open_ok(tmp.path());
  CHECK(s.stored_tiles(job).value() == std::vector<std::uint32_t>{0, 1, 2});  // leased again
  CHECK(tiles_of(s.get_all_tiles(job).value()) == std::vector<std::uint32_t>{0, 1, 2});
  // The tiles come again (other bytes, say another worker's): they are stored over the garbage,
  // which the first append truncated.
  {
    TileWriter writer(open_ok(tmp.path()));
    Callbacks callbacks;
    for (std::uint32_t t = 3; t < 5; ++t) {
      REQUIRE(writer.submit(tile_write(job, t, kTileBytes), callbacks.done(t)) == SubmitStatus::kAccepted);
    }
    REQUIRE(callbacks.wait_for(2));
    for (const auto& [tile, rs] : callbacks.results()) CHECK(rs.at(0).outcome == TileOutcome::kStored);
  }
  CHECK(committed(tmp, job) == 5 * kTileBytes);
  CHECK(fs::file_size(pixel_file(tmp, job)) == 5 * kTileBytes);  // the garbage was truncated
  auto all = s.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == 5);
  for (const StoredTile& t : all.value()) CHECK(t.pixels == make_pixels(job, t.tile, kTileBytes));
}

TEST_CASE("a failed commit's appended bytes are overwritten by the next batch", "[store][pixels]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t job = make_job(s);
  store_tiles(s, job, 0, 2);
  const Status failed = s.transaction([&]() -> Status {
    auto r = s.insert_tiles(std::vector{tile_write(job, 2, kTileBytes, 9)});
    if (!r) return r.error();
    return dtraced::util::Error{"the body fails after the append"};
  });
  REQUIRE_FALSE(failed.ok());
  CHECK(s.stored_tiles(job).value() == std::vector<std::uint32_t>{0, 1});
  store_tiles(s, job, 2, 1);
  CHECK(s.get_tile(job, 2).value()->pixels == make_pixels(job, 2, kTileBytes));
  CHECK(committed(tmp, job) == 3 * kTileBytes);
}

TEST_CASE("a truncated pixel file or a damaged tile is an error naming the file and tile, the others read",
          "[store][pixels]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t job = make_job(s);
  store_tiles(s, job, 0, 4);
  const std::string file = pixel_file(tmp, job);
  std::string expected_error;
  std::uint32_t bad = 0;
  SECTION("truncated") {
    bad = 3;
    fs::resize_file(file, 3 * kTileBytes + 100);
    expected_error = "truncated";
  }
  SECTION("a flipped byte") {
    bad = 1;
    const std::string bytes = file_bytes(file);
    write_bytes(file, std::string(1, static_cast<char>(bytes[kTileBytes + 500] ^ 0x10)), kTileBytes + 500);
    expected_error = "checksum mismatch";
  }
  SECTION("the file is gone") {
    bad = 0;
    fs::remove(file);
    expected_error = "No such file";
  }
  Store reader = open_ok(tmp.path());
  auto one = reader.get_tile(job, bad);
  REQUIRE_FALSE(one.ok());
  CHECK_THAT(one.error().message, Contains(file));
  CHECK_THAT(one.error().message, Contains("tile " + std::to_string(bad) + " of job " + std::to_string(job)));
  CHECK_THAT(one.error().message, Contains(expected_error));
  // The job's other tiles are restored; the damaged one is left out, so it is leased again.
  auto all = reader.get_all_tiles(job);
  REQUIRE(all.ok());
  std::vector<std::uint32_t> good;
  for (std::uint32_t t = 0; t < 4; ++t) {
    if (t != bad && (expected_error != "No such file")) good.push_back(t);
  }
  CHECK(tiles_of(all.value()) == good);
  for (const StoredTile& t : all.value()) CHECK(t.pixels == make_pixels(job, t.tile, kTileBytes));
  // Its result, submitted again, replaces the damaged row.
  auto again = s.insert_tiles(std::vector{tile_write(job, bad, kTileBytes)});
  REQUIRE(again.ok());
  CHECK(again.value()[0].outcome == TileOutcome::kStored);
  CHECK(reader.get_tile(job, bad).value()->pixels == make_pixels(job, bad, kTileBytes));
}

TEST_CASE("a version 3 database keeps its tiles in rows, and new tiles go to pixel files", "[store][pixels]") {
  StoreDir tmp;
  fs::create_directories(tmp.path());
  raw_exec(tmp.db(), kVersion3Sql);
  {
    Store s = open_ok(tmp.path());
    CHECK(s.get_tile(1, 1).value()->pixels == Blob{0x44, 0x55, 0x66, 0x77});
    auto r = s.insert_tiles(std::vector{TileWrite{1, 0, Blob{0x00, 0x11, 0x22, 0x33}, "w3", 1},
                                        TileWrite{1, 1, Blob{0x00}, "w3", 1}, tile_write(1, 2, kTileBytes)});
    REQUIRE(r.ok());
    CHECK(r.value()[0].outcome == TileOutcome::kAlreadyPresent);
    CHECK(r.value()[0].identical);
    CHECK_FALSE(r.value()[1].identical);
    CHECK(r.value()[2].outcome == TileOutcome::kStored);
  }
  CHECK(raw_query_text(tmp.db(), "SELECT value FROM meta WHERE key = 'schema_version'") == "4");
  CHECK(fs::file_size(pixel_file(tmp, 1)) == kTileBytes);
  Store s = open_ok(tmp.path());
  auto all = s.get_all_tiles(1);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == 3);
  CHECK(all.value()[0].pixels == Blob{0x00, 0x11, 0x22, 0x33});
  CHECK(all.value()[0].worker == "w1");
  CHECK(all.value()[1].pixels == Blob{0x44, 0x55, 0x66, 0x77});
  CHECK(all.value()[2].pixels == make_pixels(1, 2, kTileBytes));
}

TEST_CASE("deleting a job deletes its pixel file, and a file of no job goes when a writer starts", "[store][pixels]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path());
  const std::int64_t keep = make_job(s);
  const std::int64_t gone = make_job(s);
  store_tiles(s, keep, 0, 2);
  store_tiles(s, gone, 0, 2);
  const std::string_view ended[] = {store::kJobCancelled};
  require_ok(s.set_job_state(gone, store::kJobCancelled, 1));
  CHECK(fs::exists(pixel_file(tmp, gone)));  // a cancelled job keeps its pixels
  REQUIRE(s.delete_job(gone, ended).value().deleted);
  CHECK_FALSE(fs::exists(pixel_file(tmp, gone)));
  CHECK(fs::exists(pixel_file(tmp, keep)));
  // As if a crash came between a deletion's COMMIT and its unlink.
  write_bytes(pixel_file(tmp, 77), "left over");
  write_bytes(tmp.path() + "/pixels/notes.txt", "not ours");
  { TileWriter writer(open_ok(tmp.path())); }
  CHECK_FALSE(fs::exists(pixel_file(tmp, 77)));
  CHECK(fs::exists(tmp.path() + "/pixels/notes.txt"));
  CHECK(s.get_all_tiles(keep).value().size() == 2);
}

TEST_CASE("the size cap counts the pixel files", "[store][pixels]") {
  StoreDir tmp;
  Store s = open_ok(tmp.path(), OpenOptions{.max_database_bytes = 1 << 20});
  const std::int64_t job = make_job(s);
  store_tiles(s, job, 0, 20);  // ~240 KiB
  std::vector<TileWrite> writes;
  for (std::uint32_t t = 20; t < 100; ++t) writes.push_back(tile_write(job, t, kTileBytes));  // ~960 KiB more
  auto r = s.insert_tiles(writes);
  REQUIRE_FALSE(r.ok());
  CHECK_THAT(r.error().message, Contains("full"));
  CHECK(s.count_tiles(job).value() == 20);
  CHECK(committed(tmp, job) == 20 * kTileBytes);
}

TEST_CASE("an append that cannot grow the file fails its batch, and the batch stores once it can", "[store][pixels]") {
  StoreDir tmp;
  const std::int64_t job = job_in(tmp);
  // A file size limit (RLIMIT_FSIZE, a full disk's stand-in, in a child alone) of 1 MiB, which
  // the pixel file reaches first (the WAL and the database stay under it).
  constexpr std::uint32_t kBatch = 10;
  const pid_t pid = ::fork();
  REQUIRE(pid >= 0);
  if (pid == 0) {
    ::signal(SIGXFSZ, SIG_IGN);  // a write past the limit fails with EFBIG instead
    rlimit limit{};
    if (::getrlimit(RLIMIT_FSIZE, &limit) != 0) ::_exit(100);
    const rlimit unlimited = limit;
    limit.rlim_cur = 1 << 20;
    auto opened = Store::open(tmp.path(), OpenOptions{.verify_integrity = false});
    if (!opened || ::setrlimit(RLIMIT_FSIZE, &limit) != 0) ::_exit(101);
    Store& s = opened.value();
    const auto batch = [&](std::uint32_t first) {
      std::vector<TileWrite> writes;
      for (std::uint32_t t = first; t < first + kBatch; ++t) writes.push_back(tile_write(job, t, kTileBytes));
      return writes;
    };
    std::uint32_t first = 0;
    for (;; first += kBatch) {
      if (first >= 100) ::_exit(102);  // 100 tiles are past the limit
      auto r = s.insert_tiles(batch(first));
      if (r) {
        if (r.value()[0].outcome != TileOutcome::kStored) ::_exit(103);
        continue;
      }
      if (r.error().message.find("File too large") == std::string::npos) ::_exit(104);
      break;
    }
    if (first == 0 || ::setrlimit(RLIMIT_FSIZE, &unlimited) != 0) ::_exit(105);
    auto stored = s.insert_tiles(batch(first));
    if (!stored || stored.value()[0].outcome != TileOutcome::kStored) ::_exit(106);
    ::_exit(static_cast<int>(first / kBatch + 1));  // the batches stored
  }
  int status = 0;
  REQUIRE(::waitpid(pid, &status, 0) == pid);
  REQUIRE(WIFEXITED(status));
  const int batches = WEXITSTATUS(status);
  REQUIRE(batches >= 2);
  REQUIRE(batches < 100);
  Store s = open_ok(tmp.path());
  auto all = s.get_all_tiles(job);
  REQUIRE(all.ok());
  REQUIRE(all.value().size() == batches * kBatch);
  for (const StoredTile& t : all.value()) CHECK(t.pixels == make_pixels(job, t.tile, kTileBytes));
  CHECK(committed(tmp, job) == batches * kBatch * kTileBytes);
}
