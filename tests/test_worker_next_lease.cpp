// A real worker against a real collector over loopback: after its first tiles, each next lease
// comes in the answer to an upload (protocol::kNextLeaseHeader), so a tile costs one request; the
// job completes with every tile stored once. (The worker against a collector that never gives a
// next lease, as older ones do, is tests/test_worker_e2e.cpp: its fake collector ignores the
// header.) Also the worker's reading of an upload answer that carries the next lease.
#include <chrono>
#include <memory>
#include <thread>
#include <utility>

#include <catch2/catch.hpp>

#include "collector_testing.h"
#include "worker/answers.h"
#include "worker/config.h"
#include "worker/worker.h"

namespace {

using namespace dtraced::testing;
namespace worker = dtraced::worker;
namespace http = dtraced::http;

worker::WorkerConfig worker_config(std::uint16_t port, std::uint32_t threads, std::uint32_t in_hand = 4) {
  worker::WorkerConfig config;
  config.collector_url = fmt::format("http://127.0.0.1:{}", port);
  config.token = std::string(kToken);
  config.name = "next-lease-worker";
  config.threads = threads;
  config.scene_cache = 2;
  config.grace = 60s;
  config.timeouts = {kBound, kBound, kBound};
  config.backoff_initial = 2ms;
  config.backoff_max = 40ms;
  config.max_unacknowledged = in_hand;
  config.jitter_seed = 42;
  return config;
}

http::ClientResult answered(http::Status status, std::string body, bool finished = false) {
  http::ClientResult result;
  result.response = http::make_text_response(status, std::move(body), http::kJsonContentType);
  if (finished) result.response.set(protocol::kFinishedHeader, "1");
  return result;
}

}  // namespace

TEST_CASE("a worker takes its next lease from the answer to its upload", "[worker][next_lease]") {
  // With as many places in hand as threads, a slot's next lease can only be the one its own
  // upload brings, in the place of the tile it acknowledges (the hand is full until then).
  const auto [threads, in_hand] = GENERATE(table<std::uint32_t, std::uint32_t>({{1, 4}, {2, 4}, {1, 1}, {2, 2}}));
  INFO(threads << " threads, " << in_hand << " tiles in hand");
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  require_ok(h.collector.listen());
  h.start_loop();

  auto created = worker::Worker::create(worker_config(h.collector.port(), threads, in_hand));
  REQUIRE(created.ok());
  std::unique_ptr<worker::Worker> w = std::move(created).value();
  std::thread runner([&] { w->run(); });
  const auto deadline = std::chrono::steady_clock::now() + kBound;
  while (h.status(job).tiles_done < kTiles && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(5ms);
  }
  w->request_stop();
  runner.join();
  const worker::WorkerStats s = w->stats();

  CHECK(h.status(job).tiles_done == kTiles);
  CHECK(s.tiles_submitted == kTiles);
  CHECK(s.tiles_rejected == 0);
  CHECK(s.tiles_in_hand == 0);
  // Each slot leases its first two tiles by POST /v1/lease (the second while the first renders,
  // before any upload); every later one may come in an upload's answer. At least half did.
  CHECK(s.upload_leases >= kTiles / 2);
  CHECK(metric(h, &coll::CollectorCounters::upload_leases) >= s.upload_leases);
  CHECK(metric(h, &coll::CollectorCounters::tiles_stored) == kTiles);
  CHECK(h.stop_loop() == 0);
}

TEST_CASE("a submission's answer may carry the next lease, or a retry-after, or none", "[worker][next_lease]") {
  using worker::classify_submit;
  using worker::SubmitVerdict;
  protocol::Lease lease;
  lease.job = 9;
  lease.digest = std::string(64, 'b');
  lease.tile = 1;
  lease.rect = {8, 0, 8, 8};
  lease.settings.width = 32;
  lease.settings.height = 24;

  const auto stored = classify_submit(
      answered(http::Status::ok, protocol::encode(protocol::UploadAnswer{protocol::SubmitResult::kStored, lease})));
  CHECK(stored.verdict == SubmitVerdict::kAcknowledged);
  REQUIRE(stored.next);
  REQUIRE(stored.next->lease);
  CHECK(*stored.next->lease == lease);

  // A finished collector's retry-after, on a duplicate's answer.
  const auto finished = classify_submit(answered(
      http::Status::ok,
      protocol::encode(protocol::UploadAnswer{protocol::SubmitResult::kAlreadyDone, protocol::RetryAfter{5000}}),
      /*finished=*/true));
  CHECK(finished.verdict == SubmitVerdict::kAcknowledged);
  REQUIRE(finished.next);
  CHECK(finished.next->retry_after == 5000ms);
  CHECK(finished.next->collector_finished);

  // 410 with the next lease: the job is gone, the farm's work is not.
  const auto gone = classify_submit(
      answered(http::Status::gone, protocol::encode(protocol::UploadAnswer{protocol::SubmitResult::kJobGone, lease})));
  CHECK(gone.verdict == SubmitVerdict::kJobGone);
  REQUIRE(gone.next);
  CHECK(gone.next->lease);

  // An older collector's answer: no next lease.
  const auto plain = classify_submit(answered(http::Status::ok, protocol::encode(protocol::SubmitResult::kStored)));
  CHECK(plain.verdict == SubmitVerdict::kAcknowledged);
  CHECK_FALSE(plain.next);
  // A malformed next lease makes the whole answer unreadable: sent again, as any such answer.
  const auto broken = classify_submit(answered(http::Status::ok, R"({"result": "stored", "next": {"lease": 1}})"));
  CHECK(broken.verdict == SubmitVerdict::kRetry);
  CHECK_FALSE(broken.next);
}
