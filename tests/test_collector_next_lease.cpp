// The next lease in the answer to a tile upload (protocol::kNextLeaseHeader, UploadAnswer): a
// worker that asks gets exactly what POST /v1/lease would have answered, after its tile's verdict;
// a worker that does not ask gets the answer it always got; a refused upload gives no lease.
#include <optional>
#include <set>
#include <string>
#include <variant>

#include <catch2/catch.hpp>

#include "collector_testing.h"
#include "protocol/worker_messages.h"

namespace {

using namespace dtraced::testing;

// PUT of `l`'s tile with fake pixels; `next` the kNextLeaseHeader value ("" for none).
Request upload(const protocol::Lease& l, std::string_view next, float salt = 0) {
  Request req =
      make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l.job, l.tile), payload(l.job, l.tile, l.rect, salt));
  req.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
  req.set(protocol::kWorkerHeader, "w1");
  if (!next.empty()) req.set(protocol::kNextLeaseHeader, next);
  return req;
}

protocol::UploadAnswer decoded(const Response& res) {
  auto answer = protocol::decode_upload_answer(res.body());
  if (!answer) FAIL(answer.error().front().to_string());
  return answer.value();
}

}  // namespace

TEST_CASE("an upload that asks for its next lease gets it in the answer, until none is left",
          "[collector][next_lease]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  std::optional<protocol::Lease> l = h.lease();
  REQUIRE(l);
  std::set<std::uint32_t> stored;
  std::optional<protocol::UploadAnswer> last;
  for (std::uint32_t i = 0; i < kTiles; ++i) {
    REQUIRE(l);
    INFO("tile " << l->tile);
    CHECK(l->job == job);
    const Response res = h.collector.handle_sync(upload(*l, "2"));
    REQUIRE(res.result() == Status::ok);
    last = decoded(res);
    CHECK(last->result == protocol::SubmitResult::kStored);
    CHECK(stored.insert(l->tile).second);
    REQUIRE(last->next);
    const auto* next = std::get_if<protocol::Lease>(&*last->next);
    l = next != nullptr ? std::optional<protocol::Lease>(*next) : std::nullopt;
  }
  // Every tile leased once (one by POST, the rest in answers) and stored; the last answer says
  // "nothing now", as POST /v1/lease would.
  CHECK(stored.size() == kTiles);
  CHECK_FALSE(l);
  CHECK(std::holds_alternative<protocol::RetryAfter>(*last->next));
  CHECK(h.status(job).tiles_done == kTiles);
  CHECK(h.metrics().queue.leases == kTiles);
  CHECK(metric(h, &coll::CollectorCounters::upload_leases) == kTiles);
  CHECK(metric(h, &coll::CollectorCounters::tiles_stored) == kTiles);
  // The registry counted the worker's lease requests under its name, as for POST /v1/lease.
  const Response workers = h.call(Verb::get, "/v1/workers");
  auto list = protocol::decode_worker_list(workers.body());
  REQUIRE(list.ok());
  bool found = false;
  for (const protocol::WorkerInfo& w : list.value().workers) {
    if (w.name != "w1") continue;
    found = true;
    CHECK(w.leases == kTiles);  // lease requests: eleven in uploads, the last one answered "nothing now"
    CHECK(w.tiles == kTiles);
    CHECK(w.threads == 2);
  }
  CHECK(found);
}

TEST_CASE("an upload that does not ask gets the plain answer and no lease", "[collector][next_lease]") {
  TempDir dir;
  Harness h(dir);
  h.submit();
  const std::optional<protocol::Lease> l = h.lease();
  REQUIRE(l);
  // A garbled value counts as no header.
  for (const std::string_view next :
       {std::string_view(), std::string_view("0"), std::string_view("x"), std::string_view("99999999")}) {
    INFO("header '" << next << "'");
    const Response res = h.collector.handle_sync(upload(*l, next));
    REQUIRE(res.result() == Status::ok);
    // The body an older worker reads (decode_submit_result refuses unknown keys).
    auto plain = protocol::decode_submit_result(res.body());
    REQUIRE(plain.ok());
    CHECK(res.find(boost::beast::string_view(protocol::kFinishedHeader.data(), protocol::kFinishedHeader.size())) ==
          res.end());
  }
  CHECK(h.metrics().queue.leases == 1);
  CHECK(metric(h, &coll::CollectorCounters::upload_leases) == 0);
}

TEST_CASE("an upload refused gives no lease, a duplicate or a gone job's tile does", "[collector][next_lease]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::optional<protocol::Lease> l = h.lease();
  REQUIRE(l);

  SECTION("a payload that fails validation") {
    Request bad = upload(*l, "1");
    bad.body() = "not a tile";
    const Response res = h.collector.handle_sync(std::move(bad));
    CHECK(res.result() == Status::bad_request);
    CHECK_FALSE(protocol::decode_upload_answer(res.body()).ok());
    // Another tile's rectangle under this tile's index.
    protocol::Lease wrong = *l;
    wrong.rect.x0 += wrong.rect.width;
    Request moved = upload(wrong, "1");
    moved.target(fmt::format("/v1/jobs/{}/tiles/{}", l->job, l->tile));
    CHECK(h.collector.handle_sync(std::move(moved)).result() == Status::bad_request);
    CHECK(h.metrics().queue.leases == 1);
    CHECK(metric(h, &coll::CollectorCounters::upload_leases) == 0);
  }
  SECTION("a tile of another pixel version") {
    Request stale = upload(*l, "1");
    stale.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion + 1));
    CHECK(h.collector.handle_sync(std::move(stale)).result() == Status::conflict);
    CHECK(h.metrics().queue.leases == 1);
  }
  SECTION("an upload without a pixel version: stored, but no lease (POST /v1/lease would refuse it)") {
    Request old = upload(*l, "1");
    old.erase(boost::beast::string_view(protocol::kPixelVersionHeader.data(), protocol::kPixelVersionHeader.size()));
    const Response res = h.collector.handle_sync(std::move(old));
    REQUIRE(res.result() == Status::ok);
    const protocol::UploadAnswer answer = decoded(res);
    CHECK(answer.result == protocol::SubmitResult::kStored);
    CHECK_FALSE(answer.next);
    CHECK(h.metrics().queue.leases == 1);
  }
  SECTION("a duplicate: already_done, with the next lease") {
    REQUIRE(h.collector.handle_sync(upload(*l, "")).result() == Status::ok);
    const Response res = h.collector.handle_sync(upload(*l, "1"));
    REQUIRE(res.result() == Status::ok);
    const protocol::UploadAnswer answer = decoded(res);
    CHECK(answer.result == protocol::SubmitResult::kAlreadyDone);
    REQUIRE(answer.next);
    const auto* next = std::get_if<protocol::Lease>(&*answer.next);
    REQUIRE(next);
    CHECK(next->tile != l->tile);
  }
  SECTION("a cancelled job: 410 job_gone, and a retry-after when nothing else is queued") {
    REQUIRE(h.call(Verb::post, fmt::format("/v1/jobs/{}/cancel", job)).result() == Status::ok);
    const Response res = h.collector.handle_sync(upload(*l, "1"));
    REQUIRE(res.result() == Status::gone);
    const protocol::UploadAnswer answer = decoded(res);
    CHECK(answer.result == protocol::SubmitResult::kJobGone);
    REQUIRE(answer.next);
    CHECK(std::holds_alternative<protocol::RetryAfter>(*answer.next));
  }
}

TEST_CASE("an upload answer with a next lease survives a round trip and its decoder names bad fields",
          "[protocol][next_lease]") {
  protocol::Lease lease;
  lease.job = 3;
  lease.digest = std::string(64, 'a');
  lease.tile = 5;
  lease.rect = {8, 16, 8, 8};
  lease.settings.width = 32;
  lease.settings.height = 24;
  for (const protocol::UploadAnswer& a :
       {protocol::UploadAnswer{protocol::SubmitResult::kStored, std::nullopt},
        protocol::UploadAnswer{protocol::SubmitResult::kAlreadyDone, protocol::LeaseReply{lease}},
        protocol::UploadAnswer{protocol::SubmitResult::kJobGone, protocol::LeaseReply{protocol::RetryAfter{250}}}}) {
    const std::string text = protocol::encode(a);
    INFO(text);
    auto back = protocol::decode_upload_answer(text);
    REQUIRE(back.ok());
    CHECK(back.value() == a);
    // Without a next lease it is the very answer older workers read.
    if (!a.next) CHECK(text == protocol::encode(a.result));
  }
  const auto first_error = [](std::string_view text) {
    auto d = protocol::decode_upload_answer(text);
    REQUIRE_FALSE(d.ok());
    return d.error().front();
  };
  CHECK(first_error(R"({"result": "kept"})").path == "/result");
  CHECK(first_error(R"({"result": "stored", "next": {"retry_after_ms": -1}})").path == "/next/retry_after_ms");
  CHECK(first_error(R"({"result": "stored", "next": {}})").path == "/next");
  CHECK(first_error(R"({"result": "stored", "later": 1})").path == "/later");
  CHECK(protocol::parse_next_lease_header("1") == 1u);
  CHECK(protocol::parse_next_lease_header(std::to_string(protocol::kMaxWorkerThreads)) == protocol::kMaxWorkerThreads);
  for (const std::string_view bad : {"", "0", "-1", "1x", " 1", "4097"}) {
    INFO(bad);
    CHECK_FALSE(protocol::parse_next_lease_header(bad));
  }
}

TEST_CASE("a lease's answer is the protocol's encoding of it, in POST /v1/lease and in an upload answer",
          "[collector][next_lease]") {
  // The collector writes a lease's JSON itself, with the job's settings encoded once per frame:
  // it must be the protocol encoder's text byte for byte, whatever the settings carry.
  TempDir dir;
  Harness h(dir);
  const std::uint64_t plain = h.submit();
  const std::uint64_t sequence =
      h.submit(R"(, "frames": {"first": 4, "last": 8, "step": 2}, "output": "seq.gif", "fps": 10, "tone": "reinhard",)"
               R"( "exposure": 0.5, "background": [0.1, 0.25, 1e-7], "seed": 9)");
  const std::uint64_t adaptive = h.submit(R"(, "error_target": 0.03125, "min_samples": 2)");
  std::set<std::uint64_t> jobs;
  std::set<std::uint32_t> frames;
  for (int i = 0; i < 10 * static_cast<int>(kTiles); ++i) {
    const Response res = h.call(Verb::post, "/v1/lease", R"({"worker": "test", "threads": 1})");
    REQUIRE(res.result() == Status::ok);
    auto reply = protocol::decode_lease_reply(res.body());
    REQUIRE(reply.ok());
    CHECK(res.body() == protocol::encode(reply.value()));
    const auto* l = std::get_if<protocol::Lease>(&reply.value());
    if (l == nullptr) break;
    jobs.insert(l->job);
    frames.insert(l->settings.frame);
    // The fake payload has no sample counts, which an adaptive job's tiles need.
    if (l->job == adaptive) continue;
    // Stored with the next lease in the answer: the splice of the result and the lease's text.
    const Response up = h.collector.handle_sync(upload(*l, "1"));
    REQUIRE(up.result() == Status::ok);
    const protocol::UploadAnswer answer = decoded(up);
    CHECK(up.body() == protocol::encode(answer));
    REQUIRE(answer.next);
    if (const auto* next = std::get_if<protocol::Lease>(&*answer.next)) {
      jobs.insert(next->job);
      frames.insert(next->settings.frame);
    }
  }
  // Both jobs, and frames of the sequence other than the first (a new frame's settings).
  CHECK(jobs == std::set<std::uint64_t>{plain, sequence, adaptive});
  CHECK(frames.size() >= 3);
}
