// The collector across restarts on one state directory: after a clean destruction and after a
// SIGKILL of a forked child that had acknowledged tiles (stored tiles are restored and never
// leased again), a job complete but without its image, a corrupt database and a broken start
// counter (start-up stops, the files untouched), the one-shot job (enqueued once, resumed,
// checked like a submission), and an adaptive job's sample counts read back.
#include <fcntl.h>
#include <sqlite3.h>
#include <sys/file.h>
#include <sys/mount.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <set>
#include <sstream>
#include <string>
#include <variant>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "child_process.h"
#include "collector/linger.h"
#include "collector/restore.h"
#include "collector_testing.h"
#include "eventually.h"
#include "util/file.h"

using namespace dtraced::testing;

TEST_CASE("a restart resumes the job with its stored tiles, which are never leased again", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::set<std::uint32_t> first;
  std::uint64_t job = 0;
  {
    Harness h(config);
    job = h.submit();
    auto leases = h.lease_all();
    for (std::size_t i = 0; i < 5; ++i) {
      REQUIRE(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);
      first.insert(leases[i].tile);
    }
    // Destroyed without stop(): the writer drains in the destructor.
  }
  Harness h(config);
  coll::MetricsSnapshot m = h.collector.metrics();
  CHECK(m.epoch == 2);
  CHECK(m.restored_tiles == 5);
  protocol::JobStatus s = h.status(job);
  CHECK(s.state == protocol::JobState::kRendering);
  CHECK(s.tiles_done == 5);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, first).rgb);

  auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - 5);
  for (const auto& l : leases) CHECK_FALSE(first.contains(l.tile));
  // A worker whose acknowledgement was lost retries a stored tile: already done, counted.
  const auto rects = dtraced::scene::TileGrid(32, 24, 8).all();
  const std::uint32_t restored = *first.begin();
  CHECK(h.put(job, restored, payload(job, restored, rects[restored])).result() == Status::ok);
  for (const auto& l : leases) REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  m = h.collector.metrics();
  CHECK(m.counters.restored_tile_leases == 0);
  CHECK(m.counters.restored_tile_submissions == 1);
  CHECK(m.counters.tiles_stored == kTiles - 5);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all_tiles()).rgb);

  // Every tile records the start that acknowledged it.
  auto opened = store::Store::open(config.state_dir, {.verify_integrity = false});
  REQUIRE(opened.ok());
  auto tiles = opened.value().get_all_tiles(static_cast<std::int64_t>(job));
  REQUIRE(tiles.ok());
  for (const auto& t : tiles.value()) {
    CHECK(t.worker == fmt::format("epoch={} worker=unknown", first.contains(t.tile) ? 1 : 2));
  }
}

TEST_CASE("a restart leaves out a stored tile its pixel file lost, and it is rendered again", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::vector<protocol::Lease> stored;
  std::uint64_t job = 0;
  {
    Harness h(config);
    job = h.submit();
    auto leases = h.lease_all();
    for (std::size_t i = 0; i < 3; ++i) {
      REQUIRE(h.put_ok(leases[i]) == protocol::SubmitResult::kStored);
      stored.push_back(leases[i]);
    }
  }
  // The last stored tile's bytes are at the end of the job's pixel file: cut them short.
  const fs::path file = fs::path(config.state_dir) / "pixels" / fmt::format("job-{}.pixels", job);
  REQUIRE(fs::file_size(file) > 100);
  fs::resize_file(file, fs::file_size(file) - 100);
  Harness h(config);
  CHECK(h.collector.metrics().restored_tiles == 2);
  CHECK(h.status(job).tiles_done == 2);
  // The damaged tile is leased again, and its new result replaces the damaged row.
  auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - 2);
  bool again = false;
  for (const auto& l : leases) again = again || l.tile == stored[2].tile;
  CHECK(again);
  for (const auto& l : leases) REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all_tiles()).rgb);
}

TEST_CASE("after a SIGKILL, acknowledged tiles are restored and not leased again", "[collector][service][crash]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  constexpr std::size_t kAcked = 7;
  ForkedChild child([&config](int fd) {
    // Any failure ends the child with a nonzero status before it reports.
    auto created = coll::Collector::create(config);
    if (!created || !created.value()->open()) ::_exit(2);
    coll::Collector& c = *created.value();
    if (c.handle_sync(make(Verb::post, "/v1/jobs", submit_body())).result() != Status::created) ::_exit(3);
    std::string acked;
    for (std::size_t i = 0; i < kAcked; ++i) {
      const Response res = c.handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
      const auto reply = protocol::decode_lease_reply(res.body());
      if (!reply.ok() || !std::holds_alternative<protocol::Lease>(reply.value())) ::_exit(5);
      const protocol::Lease l = std::get<protocol::Lease>(reply.value());
      const Response put = c.handle_sync(
          make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l.job, l.tile), payload(l.job, l.tile, l.rect)));
      if (put.result() != Status::ok) ::_exit(4);
      acked += fmt::format("{} ", l.tile);
    }
    // One more leased but never submitted: it must come back after the crash.
    c.handle_sync(make(Verb::post, "/v1/lease", R"({"worker": "w", "threads": 1})"));
    acked += "\n";
    if (::write(fd, acked.data(), acked.size()) != static_cast<ssize_t>(acked.size())) ::_exit(5);
    for (;;) ::pause();  // killed here, with the writer thread and the loop still alive
  });
  std::string report;
  REQUIRE(child.read(
      report, [](const std::string& r) { return r.find('\n') != std::string::npos; }, kBound));
  child.kill_and_wait();
  std::set<std::uint32_t> acked;
  {
    std::istringstream in(report);
    std::uint32_t t = 0;
    while (in >> t) acked.insert(t);
  }
  REQUIRE(acked.size() == kAcked);

  Harness h(config);
  CHECK(h.collector.metrics().restored_tiles == kAcked);
  CHECK(h.collector.metrics().epoch == 2);
  auto leases = h.lease_all();
  CHECK(leases.size() == kTiles - kAcked);
  for (const auto& l : leases) CHECK_FALSE(acked.contains(l.tile));
  for (const auto& l : leases) h.put_ok(l);
  CHECK(h.collector.metrics().counters.restored_tile_leases == 0);
  CHECK(h.status(1).state == protocol::JobState::kDone);
  auto img = dtraced::image::read_image((dir.path() / "out" / "job-1.png").string());
  REQUIRE(img);
}

TEST_CASE("a job whose tiles were all stored but whose image was not written gets it written at start",
          "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  {
    Harness h(config);
    const std::uint64_t job = h.submit();
    for (const auto& l : h.lease_all()) h.put_ok(l);
    REQUIRE(h.status(job).state == protocol::JobState::kDone);
  }
  // Simulate a crash between the last commit and the image: the job back to rendering, no file.
  {
    auto opened = store::Store::open(config.state_dir);
    REQUIRE(opened.ok());
    REQUIRE(opened.value().set_job_state(1, store::kJobRendering, 0).ok());
  }
  fs::remove(dir.path() / "out" / "job-1.png");
  Harness h(config);
  h.collector.run_until_idle();
  CHECK(fs::exists(dir.path() / "out" / "job-1.png"));
  CHECK(h.status(1).state == protocol::JobState::kDone);
  CHECK(stored_state(config).jobs[0].state == "done");
  CHECK(h.collector.metrics().queue.leases == 0);
}

TEST_CASE("a corrupt database stops start-up with a message and is left untouched", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  fs::create_directories(config.state_dir);
  const std::string db = (fs::path(config.state_dir) / store::kDatabaseFileName).string();
  std::string garbage(8192, '\0');
  for (std::size_t i = 0; i < garbage.size(); ++i) garbage[i] = static_cast<char>(i * 7 + 3);
  {
    std::ofstream out(db, std::ios::binary);
    out << garbage;
  }
  auto c = must_create(config);
  const auto opened = c->open();
  REQUIRE_FALSE(opened);
  CHECK_THAT(opened.error().message, Catch::Matchers::Contains("dtraced.db"));
  CHECK(dtraced::util::read_file_limited(db, 1 << 20).value() == garbage);
  // The start counter was not advanced either.
  CHECK_FALSE(fs::exists(fs::path(config.state_dir) / coll::kEpochFileName));
  CHECK(c->handle_sync(make(Verb::get, "/v1/jobs")).result() == Status::service_unavailable);
}

TEST_CASE("a broken start counter stops start-up", "[collector][service]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  fs::create_directories(config.state_dir);
  {
    std::ofstream out(fs::path(config.state_dir) / coll::kEpochFileName);
    out << "twelve\n";
  }
  CHECK_THAT(open_error(config), Catch::Matchers::Contains("collector.epoch"));
}

TEST_CASE("a second collector on a state directory in use is refused, naming the directory and the PID",
          "[collector][service][lock]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::uint64_t job = 0;
  {
    Harness first(config);
    job = first.submit();
    const std::string error = open_error(config);
    CHECK_THAT(error, Catch::Matchers::Contains(fmt::format("state directory {} is in use by another collector "
                                                            "(process {} holds the lock on",
                                                            config.state_dir, ::getpid())));
    CHECK_THAT(error, Catch::Matchers::Contains(coll::kLockFileName.data()));
    // The refused collector changed nothing: no start counted, the first one's job still served.
    CHECK(dtraced::util::read_file_limited((fs::path(config.state_dir) / coll::kEpochFileName).string(), 64).value() ==
          "1\n");
    CHECK(first.status(job).state == protocol::JobState::kQueued);
  }
  // Once the first one is gone, the directory is free again.
  {
    Harness again(config);
    CHECK(again.collector.metrics().epoch == 2);
    CHECK(again.status(job).state == protocol::JobState::kQueued);
    // A stopped collector releases it even while the object lives on.
    again.collector.stop();
    again.collector.run();
    Harness third(config);
    CHECK(third.collector.metrics().epoch == 3);
  }
}

TEST_CASE("the temporary-file pattern of atomic writes is recognised exactly", "[collector][service][cleanup]") {
  using dtraced::util::temporary_target;
  CHECK(temporary_target("job-1.png.tmp.Ab3xY9") == "job-1.png");
  CHECK(temporary_target("collector.epoch.tmp.000000") == "collector.epoch");
  CHECK(temporary_target("job-1.png.tmp.Ab3xY") == "");    // five characters
  CHECK(temporary_target("job-1.png.tmp.Ab3xY9z") == "");  // seven
  CHECK(temporary_target("job-1.png.tmp.Ab3-Y9") == "");   // not a letter or digit
  CHECK(temporary_target("job-1.png.tmpxAb3xY9") == "");   // no ".tmp."
  CHECK(temporary_target(".tmp.Ab3xY9") == "");            // no target
  CHECK(temporary_target("job-1.png") == "");
}

TEST_CASE("start-up removes the temporary files a killed write left, only ours and only unheld",
          "[collector][service][cleanup]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  const fs::path state(config.state_dir);
  const fs::path out(config.output_dir);
  fs::create_directories(state);
  fs::create_directories(out / "sub");
  const std::string image(4096, 'x');
  const std::vector<fs::path> ours = {out / "job-1.png.tmp.Ab3xY9", out / "shot.pfm.tmp.000000",
                                      state / "collector.epoch.tmp.zzZZ99"};
  const std::vector<fs::path> others = {
      out / "notes.txt.tmp.Ab3xY9",          // not an output name
      out / "job-2.png.tmp.Ab3",             // not the pattern
      out / "sub" / "job-3.png.tmp.Ab3xY9",  // below our directory
      state / "dtraced.db.tmp.Ab3xY9",       // in the state directory, only the start counter's
      out / "job-4.png.tmp.Held00",          // a live writer holds it
      dir.path() / "elsewhere.png",          // what a link points to
  };
  for (const auto& p : ours) write_text(p, image);
  for (const auto& p : others) write_text(p, image);
  fs::create_symlink(dir.path() / "elsewhere.png", out / "job-5.png.tmp.Link00");
  const int held = ::open((out / "job-4.png.tmp.Held00").c_str(), O_RDONLY | O_CLOEXEC);
  REQUIRE(held >= 0);
  REQUIRE(::flock(held, LOCK_EX) == 0);

  Harness h(config);
  for (const auto& p : ours) CHECK_FALSE(fs::exists(p));
  for (const auto& p : others) CHECK(fs::exists(p));
  CHECK(fs::is_symlink(out / "job-5.png.tmp.Link00"));
  CHECK(dtraced::util::read_file_limited((dir.path() / "elsewhere.png").string(), 1 << 20).value() == image);
  ::close(held);
}

TEST_CASE("the one-shot job is enqueued once and resumed after a restart", "[collector][service][one-shot]") {
  TempDir dir;
  coll::CollectorConfig config = one_shot_config(dir);
  config.one_shot->overrides.width = 16;
  config.one_shot->overrides.samples = 2;
  config.one_shot->overrides.tile_size = 8;
  config.exit_when_done = true;

  std::set<std::uint32_t> first;
  {
    Harness h(config);
    protocol::JobStatus s = h.status(1);
    CHECK(s.output == "shot.png");
    CHECK(s.width == 16);
    CHECK(s.height == 24);
    CHECK(s.samples == 2);
    CHECK(s.tiles_total == 6);
    const protocol::Lease l = *h.lease();
    h.put_ok(l);
    first.insert(l.tile);
  }
  {
    Harness h(config);
    CHECK(stored_state(config).jobs.size() == 1);  // resumed, not copied
    CHECK(h.status(1).tiles_done == 1);
    auto leases = h.lease_all();
    CHECK(leases.size() == 5);
    for (const auto& l : leases) CHECK_FALSE(first.contains(l.tile));
    h.start_loop();  // the collector lingers on its clock for the workers it knows (stop.h)
    for (const auto& l : leases) h.put_ok(l);
    // The image is written and the collector stops itself (once its linger is over).
    REQUIRE(eventually([&] {
      h.clock.advance(coll::linger_bound(config.queue));
      return h.loop.wait_for(0s) == std::future_status::ready;
    }));
    CHECK(h.loop.get() == 0);
    CHECK(fs::exists(dir.path() / "out" / "shot.png"));
  }
  {
    // Once more with the same arguments: nothing to do, exit 0 at once.
    Harness h(config);
    require_ok(h.collector.listen());
    CHECK(h.collector.port() == 0);  // never listened
    CHECK(h.collector.run() == 0);
    CHECK(stored_state(config).jobs.size() == 1);
  }
  {
    // A different output is a different job.
    config.one_shot->output = "other.png";
    config.exit_when_done = false;
    Harness h(config);
    CHECK(stored_state(config).jobs.size() == 2);
  }
}

TEST_CASE("a one-shot job takes adaptive sampling's settings, checked like a submission",
          "[collector][service][one-shot][adaptive]") {
  TempDir dir;
  coll::CollectorConfig config = one_shot_config(dir);
  config.one_shot->overrides.samples = 16;
  config.one_shot->overrides.error_target = 0.1;
  config.one_shot->overrides.min_samples = 4;
  {
    Harness h(config);
    const protocol::Lease l = *h.lease();
    CHECK(l.settings.samples == 16);
    CHECK(l.settings.error_target == 0.1);
    CHECK(l.settings.min_samples == 4);
  }
  // Out of range: start-up stops and names the field.
  TempDir dir2;
  config = one_shot_config(dir2);
  config.one_shot->overrides.error_target = 2.0;
  CHECK_THAT(open_error(config), Catch::Matchers::Contains("error_target"));
}

TEST_CASE("a one-shot job with a bad scene stops start-up", "[collector][service][one-shot]") {
  TempDir dir;
  coll::CollectorConfig config = make_config(dir);
  config.one_shot = one_shot((dir.path() / "missing.json").string(), "x.png");
  CHECK_THAT(open_error(config), Catch::Matchers::Contains("missing.json"));
}

// ---- adaptive sampling: per-pixel sample counts ----------------------------------------------------

namespace {

// Counts a worker of an adaptive job (samples 16, min_samples 4) could send: checkpoints 4 and 8,
// or all 16.
std::vector<std::uint32_t> fake_counts(std::uint32_t tile, const dtraced::scene::TileRect& rect) {
  std::vector<std::uint32_t> spp(std::size_t{rect.width} * rect.height);
  for (std::size_t i = 0; i < spp.size(); ++i) spp[i] = std::uint32_t{4} << ((tile + i) % 3);
  return spp;
}

std::string adaptive_payload(const protocol::Lease& l, std::vector<std::uint32_t> spp) {
  return protocol::encode_tile_payload({l.job, l.tile, l.rect, fake_pixels(l.job, l.tile, l.rect), std::move(spp)});
}

constexpr std::string_view kAdaptive = R"(, "samples": 16, "error_target": 0.1, "min_samples": 4)";

}  // namespace

TEST_CASE("an adaptive job: counts checked, stored with the pixels, and their mean survives restarts",
          "[collector][service][adaptive]") {
  TempDir dir;
  const coll::CollectorConfig config = make_config(dir);
  std::uint64_t job = 0, uniform = 0;
  std::uint64_t sum = 0, pixels = 0;
  {
    Harness h(config);
    job = h.submit(kAdaptive);
    CHECK_FALSE(h.status(job).mean_spp.has_value());  // nothing stored yet
    auto leases = h.lease_all();
    REQUIRE(leases.size() == kTiles);
    for (const auto& l : leases) {
      CHECK(l.settings.error_target == 0.1);
      CHECK(l.settings.min_samples == 4);
      CHECK(l.settings.samples == 16);
    }
    const protocol::Lease& l = leases[0];
    const auto refused = [&](std::string body, std::string_view fragment) {
      const Response res = h.put(l.job, l.tile, std::move(body));
      CHECK(res.result() == Status::bad_request);
      const protocol::ErrorBody e = error_of(res);
      CHECK(e.field == "/spp");
      CHECK(e.error.find(fragment) != std::string::npos);
    };
    refused(payload(l.job, l.tile, l.rect), "no sample counts");
    std::vector<std::uint32_t> bad = fake_counts(l.tile, l.rect);
    bad[3] = 17;
    refused(adaptive_payload(l, bad), "took 17 samples");
    bad[3] = 0;
    refused(adaptive_payload(l, bad), "took 0 samples");
    CHECK(h.status(job).tiles_done == 0);

    for (std::size_t i = 0; i < 5; ++i) {
      const auto counts = fake_counts(leases[i].tile, leases[i].rect);
      const Response res = h.put(leases[i].job, leases[i].tile, adaptive_payload(leases[i], counts));
      REQUIRE(res.result() == Status::ok);
      for (const std::uint32_t n : counts) sum += n;
      pixels += counts.size();
    }
    const protocol::JobStatus s = h.status(job);
    REQUIRE(s.mean_spp.has_value());
    CHECK(*s.mean_spp == double(sum) / double(pixels));
    CHECK(*s.mean_spp > 4.0);
    CHECK(*s.mean_spp < 16.0);

    // A uniform job takes no counts, and its mean is its samples once a tile is stored.
    uniform = h.submit();
    auto more = h.lease_all();
    REQUIRE_FALSE(more.empty());
    const Response res = h.put(more[0].job, more[0].tile, adaptive_payload(more[0], fake_counts(0, more[0].rect)));
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).error.find("uniformly") != std::string::npos);
    CHECK_FALSE(h.status(uniform).mean_spp.has_value());
    REQUIRE(h.put_ok(more[0]) == protocol::SubmitResult::kStored);
    CHECK(h.status(uniform).mean_spp == 1.0);
  }
  {
    // Restarted while rendering: the stored counts are read back with the pixels.
    Harness h(config);
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
    for (const auto& l : h.lease_all()) {
      if (l.job != job) continue;
      const auto counts = fake_counts(l.tile, l.rect);
      REQUIRE(h.put(l.job, l.tile, adaptive_payload(l, counts)).result() == Status::ok);
      for (const std::uint32_t n : counts) sum += n;
      pixels += counts.size();
    }
    CHECK(h.status(job).state == protocol::JobState::kDone);
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
  }
  // The blobs are the floats followed by the counts.
  {
    auto opened = store::Store::open(config.state_dir, {.verify_integrity = false});
    REQUIRE(opened.ok());
    auto tile = opened.value().get_tile(static_cast<std::int64_t>(job), 0);
    REQUIRE(tile.ok());
    REQUIRE(tile.value());
    CHECK(tile.value()->pixels.size() == 8 * 8 * 16);
  }
  // Restarted once done: the mean is read back from the store after start-up (on the pool; the
  // first request runs the loop until that is done).
  {
    Harness h(config);
    CHECK(pixels == 32 * 24);
    CHECK(h.status(job).state == protocol::JobState::kDone);
    CHECK(h.status(job).mean_spp == double(sum) / double(pixels));
    CHECK(h.status(uniform).mean_spp == 1.0);
  }
  // A finished job's stored tiles damaged behind the collector's back (their pixel file cut short,
  // store/pixel_files.h): start-up still succeeds, the job stays done and its mean is unknown
  // rather than wrong.
  {
    const fs::path file = fs::path(config.state_dir) / "pixels" / fmt::format("job-{}.pixels", job);
    REQUIRE(fs::file_size(file) > 100);
    fs::resize_file(file, 100);
  }
  Harness h(config);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK_FALSE(h.status(job).mean_spp.has_value());
  CHECK(h.status(uniform).mean_spp == 1.0);
}

// A small tmpfs of our own, filled to the last byte: mount(2) needs root (or CAP_SYS_ADMIN);
// without it the test says so and checks nothing.
namespace {
struct SmallDisk {
  explicit SmallDisk(const fs::path& at) : path(at) {
    fs::create_directories(path);
    mounted = ::mount("tmpfs", path.c_str(), "tmpfs", 0, "size=8m") == 0;
  }
  ~SmallDisk() {
    if (mounted) ::umount2(path.c_str(), MNT_DETACH);
  }
  // Writes a file until the disk refuses another byte.
  void fill() const {
    const int fd = ::open((path / "filler").c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
    REQUIRE(fd >= 0);
    const std::string chunk(4096, 'f');
    for (std::size_t size = chunk.size(); size > 0; size /= 2) {
      while (::write(fd, chunk.data(), size) == static_cast<ssize_t>(size)) {
      }
    }
    ::close(fd);
    const int probe = ::open((path / "probe").c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
    REQUIRE(probe >= 0);
    const bool full = ::write(probe, "x", 1) < 0 && errno == ENOSPC;
    ::close(probe);
    fs::remove(path / "probe");
    REQUIRE(full);
  }
  void free_space() const { fs::remove(path / "filler"); }
  fs::path path;
  bool mounted = false;
};
}  // namespace

TEST_CASE("a collector starts on a full disk with its stored tiles, and goes on once space frees",
          "[collector][service][disk]") {
  TempDir dir;
  SmallDisk disk(dir.path() / "disk");
  if (!disk.mounted) {
    WARN("skipped: cannot mount a tmpfs here (" << std::strerror(errno) << "); run as root to test a full disk");
    return;
  }
  coll::CollectorConfig config = make_config(dir);
  config.state_dir = (disk.path / "state").string();
  config.output_dir = (disk.path / "out").string();
  std::uint64_t job = 0;
  std::set<std::uint32_t> first;
  {
    Harness h(config);
    job = h.submit();
    for (const auto& l : h.lease_all()) {
      if (first.size() == 5) break;
      REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
      first.insert(l.tile);
    }
  }
  disk.fill();
  {
    Harness h(config);  // opens, or the test fails here
    CHECK(h.collector.metrics().epoch == 2);
    CHECK(h.collector.metrics().restored_tiles == 5);
    CHECK(h.status(job).tiles_done == 5);
    // The start counter could not be written; it still says 1, whole.
    CHECK(dtraced::util::read_file_limited((fs::path(config.state_dir) / coll::kEpochFileName).string(), 64).value() ==
          "1\n");
  }
  disk.free_space();
  Harness h(config);
  CHECK(h.status(job).tiles_done == 5);
  for (const auto& l : h.lease_all()) REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all_tiles()).rgb);
}
