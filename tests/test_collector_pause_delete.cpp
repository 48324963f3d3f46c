// Pausing, resuming and deleting jobs through the collector's handler, without sockets
// (collector_testing.h): what a paused job hands out and accepts, that a pause survives a restart,
// what a deletion removes (rows, tiles, the image only when asked) and what every bad request gets.
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "collector_testing.h"

using namespace dtraced::testing;

namespace {

namespace fs = std::filesystem;

protocol::JobStatus change(Harness& h, std::uint64_t job, std::string_view what) {
  const Response res = h.call(Verb::post, fmt::format("/v1/jobs/{}/{}", job, what));
  INFO(res.body());
  REQUIRE(res.result() == Status::ok);
  return protocol::decode_job_status(res.body()).value();
}

protocol::JobDeleted delete_ok(Harness& h, std::uint64_t job, std::string_view query = "") {
  const Response res = h.call(Verb::delete_, fmt::format("/v1/jobs/{}{}", job, query));
  INFO(res.body());
  REQUIRE(res.result() == Status::ok);
  auto deleted = protocol::decode_job_deleted(res.body());
  REQUIRE(deleted.ok());
  return deleted.value();
}

// Submits a job and stores every tile of it.
std::uint64_t finished_job(Harness& h) {
  const std::uint64_t job = h.submit();
  for (const auto& l : h.lease_all()) REQUIRE(h.put_ok(l) == protocol::SubmitResult::kStored);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  return job;
}

}  // namespace

// ---- pause and resume -------------------------------------------------------------------------

TEST_CASE("a paused job hands out no tile, accepts the tiles already out, and resumes where it was",
          "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const protocol::Lease a = *h.lease();
  const protocol::Lease b = *h.lease();

  const protocol::JobStatus paused = change(h, job, "pause");
  CHECK(paused.state == protocol::JobState::kPaused);
  CHECK_FALSE(paused.eta_s.has_value());
  CHECK(stored_state(h.config).jobs.at(0).state == "paused");
  CHECK_FALSE(h.lease().has_value());
  h.clock.advance(std::chrono::hours(1));  // long past any re-offer bound: still nothing
  CHECK_FALSE(h.lease().has_value());
  CHECK(h.put_ok(a) == protocol::SubmitResult::kStored);
  CHECK(h.status(job).tiles_done == 1);
  CHECK(h.status(job).state == protocol::JobState::kPaused);
  CHECK_FALSE(h.status(job).no_worker_s.has_value());  // no worker on purpose

  const protocol::JobStatus resumed = change(h, job, "resume");
  CHECK(resumed.state == protocol::JobState::kRendering);
  CHECK(stored_state(h.config).jobs.at(0).state == "queued");
  std::vector<protocol::Lease> rest = h.lease_all();
  // Every tile but the stored one; b, out for an hour, is offered again.
  CHECK(rest.size() == kTiles - 1);
  for (const auto& l : rest) {
    CHECK(l.tile != a.tile);
    h.put_ok(l);
  }
  CHECK(h.put_ok(b) == protocol::SubmitResult::kAlreadyDone);
  REQUIRE(h.status(job).state == protocol::JobState::kDone);
  CHECK(fetch_pfm(h, job).rgb == expected_image(job, 32, 24, 8, all_tiles()).rgb);
}

TEST_CASE("a paused job stays paused across a restart and resumes after it", "[collector][manage]") {
  TempDir dir;
  std::uint64_t job = 0;
  {
    Harness h(dir);
    job = h.submit();
    REQUIRE(h.put_ok(*h.lease()) == protocol::SubmitResult::kStored);
    change(h, job, "pause");
  }
  Harness h(dir);
  const protocol::JobStatus restored = h.status(job);
  CHECK(restored.state == protocol::JobState::kPaused);
  CHECK(restored.tiles_done == 1);
  CHECK_FALSE(h.lease().has_value());
  CHECK(change(h, job, "resume").state == protocol::JobState::kRendering);
  CHECK(h.lease_all().size() == kTiles - 1);
}

TEST_CASE("the tiles out when a job was paused can finish it", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::vector<protocol::Lease> all = h.lease_all();
  REQUIRE(all.size() == kTiles);
  change(h, job, "pause");
  for (const auto& l : all) CHECK(h.put_ok(l) == protocol::SubmitResult::kStored);
  CHECK(h.status(job).state == protocol::JobState::kDone);
  CHECK(stored_state(h.config).jobs.at(0).state == "done");
  const Response again = h.call(Verb::post, fmt::format("/v1/jobs/{}/resume", job));
  CHECK(again.result() == Status::conflict);
  CHECK_THAT(error_of(again).error, Catch::Contains("is done; only a paused job can be resumed"));
}

TEST_CASE("pause and resume answer a repeat with the status, and refuse what they cannot change",
          "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  CHECK(change(h, job, "resume").state == protocol::JobState::kQueued);  // nothing to resume: unchanged
  CHECK(change(h, job, "pause").state == protocol::JobState::kPaused);
  CHECK(change(h, job, "pause").state == protocol::JobState::kPaused);
  CHECK(h.call(Verb::post, "/v1/jobs/77/pause").result() == Status::not_found);
  CHECK(h.call(Verb::post, "/v1/jobs/77/resume").result() == Status::not_found);
  CHECK(h.call(Verb::get, fmt::format("/v1/jobs/{}/pause", job)).result() == Status::method_not_allowed);
  CHECK(h.call(Verb::post, fmt::format("/v1/jobs/{}/pause?now=1", job)).result() == Status::bad_request);
  CHECK(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job)).result() == Status::ok);
  for (const char* what : {"pause", "resume"}) {
    const Response res = h.call(Verb::post, fmt::format("/v1/jobs/{}/{}", job, what));
    CHECK(res.result() == Status::conflict);
    CHECK_THAT(error_of(res).error, Catch::Contains("is cancelled"));
  }
  CHECK(stored_state(h.config).jobs.at(0).state == "cancelled");
}

TEST_CASE("the job list and the state counts know paused jobs", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t a = h.submit();
  h.submit();
  change(h, a, "pause");
  const Response res = h.call(Verb::get, "/v1/jobs?state=paused");
  REQUIRE(res.result() == Status::ok);
  const auto list = protocol::decode_job_list(res.body()).value();
  REQUIRE(list.jobs.size() == 1);
  CHECK(list.jobs[0].id == a);
  CHECK(h.metrics().jobs_by_state[static_cast<std::size_t>(protocol::JobState::kPaused)] == 1);
  CHECK(h.metrics().jobs_by_state[static_cast<std::size_t>(protocol::JobState::kQueued)] == 1);
}

// ---- delete -----------------------------------------------------------------------------------

TEST_CASE("deleting a done job removes it and its tiles and keeps its image unless asked", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t kept = finished_job(h);
  const std::uint64_t gone = finished_job(h);
  const fs::path kept_image = fs::path(h.config.output_dir) / h.status(kept).output;
  const fs::path gone_image = fs::path(h.config.output_dir) / h.status(gone).output;
  REQUIRE(fs::exists(kept_image));
  REQUIRE(fs::exists(gone_image));

  const protocol::JobDeleted first = delete_ok(h, kept);
  CHECK(first.id == kept);
  CHECK(first.tiles == kTiles);
  CHECK(first.image == "kept");
  CHECK(fs::exists(kept_image));
  CHECK(h.call(Verb::get, fmt::format("/v1/jobs/{}", kept)).result() == Status::not_found);
  CHECK(h.call(Verb::get, fmt::format("/v1/jobs/{}/image", kept)).result() == Status::not_found);
  CHECK(h.call(Verb::delete_, fmt::format("/v1/jobs/{}", kept)).result() == Status::not_found);

  const protocol::JobDeleted second = delete_ok(h, gone, "?image=delete");
  CHECK(second.image == "deleted");
  CHECK_FALSE(fs::exists(gone_image));

  const StoredState stored = stored_state(h.config);
  CHECK(stored.jobs.empty());
  CHECK(stored.tiles.empty());
  CHECK(protocol::decode_job_list(h.call(Verb::get, "/v1/jobs").body()).value().jobs.empty());
  // A new job never gets a deleted job's id, also after a restart.
  h.collector.stop();
  h.collector.run();
  Harness again(dir);
  CHECK(again.submit() == gone + 1);
}

TEST_CASE("a cancelled job is deleted with the tiles it had, and has no image", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  REQUIRE(h.put_ok(*h.lease()) == protocol::SubmitResult::kStored);
  change(h, job, "cancel");
  const protocol::JobDeleted deleted = delete_ok(h, job, "?image=delete");
  CHECK(deleted.tiles == 1);
  CHECK(deleted.image == "none");
  CHECK(stored_state(h.config).jobs.empty());
}

TEST_CASE("delete refuses unfinished jobs and bad requests, and changes nothing", "[collector][manage]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t queued = h.submit();
  const std::uint64_t paused = h.submit();
  change(h, paused, "pause");
  for (const std::uint64_t job : {queued, paused}) {
    const Response res = h.call(Verb::delete_, fmt::format("/v1/jobs/{}", job));
    CHECK(res.result() == Status::conflict);
    CHECK_THAT(error_of(res).error, Catch::Contains("only a done or cancelled job can be deleted (cancel it first)"));
  }
  CHECK(h.call(Verb::delete_, "/v1/jobs/99").result() == Status::not_found);
  struct Case {
    std::string query;
    std::string field;
  };
  for (const Case& bad :
       {Case{"?image=maybe", "/image"}, Case{"?image=keep&image=delete", "/image"}, Case{"?force=1", "/force"}}) {
    INFO(bad.query);
    const Response res = h.call(Verb::delete_, fmt::format("/v1/jobs/{}{}", queued, bad.query));
    CHECK(res.result() == Status::bad_request);
    CHECK(error_of(res).field == bad.field);
  }
  const Response post = h.call(Verb::post, fmt::format("/v1/jobs/{}", queued));
  CHECK(post.result() == Status::method_not_allowed);
  CHECK_THAT(error_of(post).error, Catch::Contains("GET, DELETE"));
  const StoredState stored = stored_state(h.config);
  REQUIRE(stored.jobs.size() == 2);
  CHECK(stored.jobs[0].state == "queued");
  CHECK(stored.jobs[1].state == "paused");
}
