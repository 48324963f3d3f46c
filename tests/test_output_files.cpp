// Output files are never lost or overwritten: two jobs cannot hold one output name (409 at
// submit), a submission cannot name a file that is already there, and a finished image never
// replaces a file, even one that appeared while the job rendered; its pixels stay fetchable and
// the write is tried again once the name is free. Also the file helpers underneath
// (util::write_file_new, util::check_output_path).
#include <sys/stat.h>

#include <filesystem>
#include <string>

#include <catch2/catch.hpp>

#include "collector/lifecycle.h"
#include "collector/output_files.h"
#include "collector_testing.h"
#include "eventually.h"
#include "util/file.h"

using namespace dtraced::testing;

namespace {

std::string read_text(const fs::path& path) {
  auto text = dtraced::util::read_file_limited(path.string(), 1 << 20);
  REQUIRE(text);
  return *text;
}

void finish(Harness& h) {
  for (const auto& l : h.lease_all()) h.put_ok(l);
}

}  // namespace

TEST_CASE("a job whose output name another job holds is refused with 409 naming that job", "[collector][output]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t first = h.submit(R"(, "output": "same.png")");
  const Response again = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "output": "same.png")"));
  REQUIRE(again.result() == Status::conflict);
  const protocol::ErrorBody e = error_of(again);
  CHECK(e.field == "/output");
  CHECK(e.error.find(fmt::format("held by job {}", first)) != std::string::npos);
  // A job's default name is held too.
  const std::uint64_t unnamed = h.submit();
  const Response taken_default =
      h.call(Verb::post, "/v1/jobs", submit_body(fmt::format(R"(, "output": "job-{}.png")", unnamed)));
  CHECK(taken_default.result() == Status::conflict);

  // Still held once the job is done: its image file is there.
  finish(h);
  REQUIRE(h.status(first).state == protocol::JobState::kDone);
  const Response after = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "output": "same.png")"));
  CHECK(after.result() == Status::conflict);
  // Nothing was stored for the refused ones.
  CHECK(stored_state(h.config).jobs.size() == 2);
}

TEST_CASE("a submission naming a file already in the output directory is refused with 409", "[collector][output]") {
  TempDir dir;
  Harness h(dir);
  const fs::path taken = dir.path() / "out" / "taken.png";
  write_text(taken, "someone else's picture");
  const Response res = h.call(Verb::post, "/v1/jobs", submit_body(R"(, "output": "taken.png")"));
  REQUIRE(res.result() == Status::conflict);
  CHECK(error_of(res).error.find("exists and is never overwritten") != std::string::npos);
  CHECK(read_text(taken) == "someone else's picture");
  CHECK(stored_state(h.config).jobs.empty());
}

TEST_CASE("a finished image never replaces a file that took its name, and its pixels stay fetchable",
          "[collector][output]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit(R"(, "output": "late.pfm")");
  const auto leases = h.lease_all();
  for (std::size_t i = 0; i + 1 < leases.size(); ++i) h.put_ok(leases[i]);
  // Another program (or a second collector) writes the name while the job renders.
  const fs::path late = dir.path() / "out" / "late.pfm";
  write_text(late, "written by someone else");

  h.start_loop();  // the collector sleeps on its clock before trying again
  CHECK(h.put_ok(leases.back()) == protocol::SubmitResult::kStored);
  REQUIRE(h.clock.wait_for_sleepers(1, kBound));
  CHECK(read_text(late) == "written by someone else");
  CHECK(metric(h, &coll::CollectorCounters::image_write_failures) == 1);
  CHECK(h.status(job).state == protocol::JobState::kRendering);
  std::set<std::uint32_t> all;
  for (const auto& l : leases) all.insert(l.tile);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all).rgb);

  // Once the name is free, the next attempt writes the image.
  fs::remove(late);
  h.clock.advance(dtraced::collector::kFinishRetryDelay);
  REQUIRE(eventually([&] { return h.status(job).state == protocol::JobState::kDone; }));
  auto written = dtraced::image::read_image(late.string());
  REQUIRE(written);
  CHECK(written->rgb == expected_image(job, 32, 24, 8, all).rgb);
  CHECK(h.stop_loop() == 0);
}

TEST_CASE("writing an image over the same bytes succeeds, over other bytes fails naming the file",
          "[collector][output]") {
  TempDir dir;
  const std::string path = (dir.path() / "a.png").string();
  dtraced::image::ImageRGBf img(4, 2);
  img.rgb.assign(img.rgb.size(), 0.5f);
  require_ok(coll::write_output_image(path, img, 8));
  const std::string first = read_text(path);
  // A restart writes a finished job's image again: the same bytes are not a conflict.
  require_ok(coll::write_output_image(path, img, 8));
  img.rgb[0] = 1.0f;
  const dtraced::util::Status other = coll::write_output_image(path, img, 8);
  REQUIRE_FALSE(other);
  CHECK(other.error().file == path);
  CHECK(other.error().message.find("never overwritten") != std::string::npos);
  CHECK(read_text(path) == first);
  // No temporary file is left behind.
  CHECK(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()) == 1);
}

TEST_CASE("write_file_new writes a new file and leaves an existing one alone", "[util][file]") {
  TempDir dir;
  const std::string path = (dir.path() / "f").string();
  auto made = dtraced::util::write_file_new(path, "one");
  REQUIRE(made);
  CHECK(*made == dtraced::util::NewFile::kWritten);
  struct stat st {};
  REQUIRE(::stat(path.c_str(), &st) == 0);
  CHECK((st.st_mode & 0777) == 0644);
  auto again = dtraced::util::write_file_new(path, "two");
  REQUIRE(again);
  CHECK(*again == dtraced::util::NewFile::kExists);
  CHECK(read_text(path) == "one");
  CHECK(std::distance(fs::directory_iterator(dir.path()), fs::directory_iterator()) == 1);
  auto nowhere = dtraced::util::write_file_new((dir.path() / "no" / "f").string(), "x");
  REQUIRE_FALSE(nowhere);
  CHECK(nowhere.error().file == (dir.path() / "no" / "f").string());
}

TEST_CASE("check_output_path names a missing directory, a file in its place, and a directory as output",
          "[util][file]") {
  TempDir dir;
  CHECK(dtraced::util::check_output_path((dir.path() / "x.png").string()));
  CHECK(dtraced::util::check_output_path("relative.png"));
  const auto missing = dtraced::util::check_output_path((dir.path() / "nope" / "x.png").string());
  REQUIRE_FALSE(missing);
  CHECK(missing.error().to_string() ==
        (dir.path() / "nope").string() + ": the output directory does not exist (No such file or directory)");
  write_text(dir.path() / "file", "");
  const auto not_dir = dtraced::util::check_output_path((dir.path() / "file" / "x.png").string());
  REQUIRE_FALSE(not_dir);
  CHECK(not_dir.error().file == (dir.path() / "file").string());
  fs::create_directory(dir.path() / "d.png");
  const auto is_dir = dtraced::util::check_output_path((dir.path() / "d.png").string());
  REQUIRE_FALSE(is_dir);
  CHECK(is_dir.error().message == "the output is a directory");
}
