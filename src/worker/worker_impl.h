// dtraced::worker internals: the state of a running Worker and the coroutines that share it,
// declared once and defined by concern:
//   worker.cpp      construction, run(), stats(), run_worker()
//   lifecycle.cpp   the main loop, signals, and the stop sequence with its grace period
//   pipeline.cpp    a render slot: lease, scene by digest, render on the pool, hand-off
//   submission.cpp  keeping a rendered tile until the collector acknowledges it
// Private to src/worker: worker.h is the module's interface, and the only header that sees Asio
// types is this one (and those of retry_gate.h and in_hand.h, which it includes).
//
// Thread safety: everything lives on the event loop (io), except the counters read by stats()
// and the render pool's work, which sees only copies and the immutable scenes.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>

#include <boost/asio/io_context.hpp>
#include <boost/asio/signal_set.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/beast/http/field.hpp>

#include "async/async.h"
#include "http/client.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "util/clock.h"
#include "worker/answers.h"
#include "worker/in_hand.h"
#include "worker/log_limiter.h"
#include "worker/retry_gate.h"
#include "worker/scene_cache.h"
#include "worker/worker.h"

namespace dtraced::worker {

// A lease ready to render: its scene is built.
struct Work {
  protocol::Lease lease;
  FramesPtr scene;
  InHand::Reservation reservation;
};

// The next lease a tile's upload asks for (protocol::kNextLeaseHeader), handed from the
// submission to the slot that renders after it. Finished once the upload's first answer came (or
// the submission ended without one); `answer` is then the lease or retry-after it carried, if any.
struct OfferedLease {
  explicit OfferedLease(const async::Executor& executor) : done(executor) {}
  void finish(std::optional<LeaseAnswer> got) {
    if (finished) return;
    answer = std::move(got);
    finished = true;
    done.notify_all();
  }
  async::Signal done;
  bool finished = false;
  std::optional<LeaseAnswer> answer;
  // The lease's place in hand: the acknowledged tile's, handed over with the answer (so a lease
  // that rides on an upload never makes the tiles in hand more than they were).
  InHand::Reservation reservation;
};
using OfferPtr = std::shared_ptr<OfferedLease>;

// A rendered tile awaiting its acknowledgement.
struct HeldTile {
  std::uint64_t job = 0;
  std::uint32_t tile = 0;
  std::string payload;  // protocol::encode_tile_payload
  InHand::Reservation reservation;
  std::uint64_t render_ms = 0;  // sent as protocol::kRenderMsHeader
  util::TimePoint rendered_at;  // when its render ended: the acknowledgement's latency counts from here
  OfferPtr offer;               // the next lease its upload asks for; null when it asks for none
};

struct SceneOutcome {
  FramesPtr scene;       // set on success
  bool stopped = false;  // the worker is stopping; nobody needs the scene now
  std::string error;     // why not, otherwise
};

// A fetch of one scene that other slots needing the same scene wait for.
struct PendingScene {
  explicit PendingScene(const async::Executor& executor) : done(executor) {}
  async::Signal done;
  bool finished = false;
  SceneOutcome outcome;
};

// A count the event loop changes and stats() reads from any thread.
class Counter {
 public:
  void add(std::uint64_t n = 1) { n_.fetch_add(n, std::memory_order_relaxed); }
  void remove() { n_.fetch_sub(1, std::memory_order_relaxed); }
  std::uint64_t get() const { return n_.load(std::memory_order_relaxed); }

 private:
  std::atomic<std::uint64_t> n_{0};
};

struct Worker::Impl {
  Impl(WorkerConfig resolved, const util::Clock& clock, std::optional<http::ClientTls> tls);

  // ---- lifecycle.cpp: start, signals, stop ----

  async::Awaitable<> main_loop(RunOptions options);
  async::Awaitable<> watch_signals();
  async::Awaitable<> drain();
  void begin_stop();
  bool drained() const { return slots_live == 0 && in_hand.count() == 0 && tiles_held.get() == 0; }

  // ---- pipeline.cpp: lease, scene, render ----

  async::Awaitable<> slot();
  // The next tile to render: the one `offered` brings (the answer to an upload), else from
  // POST /v1/lease. nullopt when the worker stops. `pending`, when given, is where the slot's
  // current render puts the offer its own upload makes: that offer's lease (which takes the
  // uploaded tile's place) is taken from there as soon as it comes, full hand or not.
  async::Awaitable<std::optional<Work>> acquire(OfferPtr offered, OfferPtr* pending = nullptr);
  // What an upload's answer brought: the Work of its lease; nullopt with `stopped` false when the
  // answer brought none (or a retry-after, which it obeys) and POST /v1/lease must ask.
  async::Awaitable<std::optional<Work>> take_offer(OfferPtr offered, bool& stopped);
  // Waits at the lease gate; nullopt once stopping, or once `offer` (if any) has finished.
  async::Awaitable<std::optional<RetryGate::Attempt>> enter_lease_gate(OfferedLease* offer);
  // A lease the collector granted (to POST /v1/lease or in an upload's answer): marks the worker
  // busy and the job not gone, and gets its scene ready (ensure_scene).
  async::Awaitable<std::pair<protocol::Lease, SceneOutcome>> begin_lease(protocol::Lease lease);
  // nullopt when the worker stopped first.
  async::Awaitable<std::optional<LeaseAnswer>> request_lease();
  async::Awaitable<SceneOutcome> ensure_scene(std::string digest);
  async::Awaitable<SceneOutcome> fetch_scene(std::string digest);
  // Renders `work` and spawns its submission; `offered` is set to the next lease its upload asks
  // for, when a lease request could go out freely now (RetryGate::open).
  async::Awaitable<> render_and_hand_off(Work work, OfferPtr& offered);
  void note_lease_failure(RetryGate::Attempt& attempt, const std::string& message, bool token_rejected);
  void note_lease_success(RetryGate::Attempt& attempt);
  // A lease answer said the collector has finished and is going away: with exit_when_done, begins
  // the stop (once) and returns true; otherwise logs it once and returns false (a retry-after).
  bool note_collector_finished();
  // A lease answer said there is no work now: with exit_when_idle, when there has been none for
  // that long and nothing is rendering or awaiting acknowledgement, begins the stop and returns
  // true.
  bool note_no_work();

  // With max_runtime: begins the stop once it has passed since the start.
  async::Awaitable<> watch_runtime(util::TimePoint started_at);

  // ---- submission.cpp ----

  async::Awaitable<> submit(HeldTile tile);

  http::Request authorized(http::Request request) const {
    request.set(boost::beast::http::field::authorization, authorization);
    return request;
  }

  // ---- state (declaration order is construction order) ----

  const WorkerConfig config;
  const util::Clock& clock;  // every time the worker reads and every sleep
  const http::Url url;
  const std::string authorization;

  async::net::io_context io{1};  // run by one thread: run()'s caller
  // Every request to the collector, on kept-alive connections. After io: destroyed before it.
  http::Client client;
  async::net::thread_pool pool;  // render threads
  std::mt19937_64 rng;           // retry jitter
  SceneCache scenes;
  std::map<std::string, std::shared_ptr<PendingScene>, std::less<>> fetching;
  RetryGate lease_gate;
  RetryGate submit_gate;
  async::Event stop;     // no more leases
  async::Event abandon;  // stop submitting: the grace period is over
  InHand in_hand;
  GoneJobs gone;
  GoneAnswers gone_answers;  // to tell a job's end from a collector that leases it again
  LogLimiter log_limiter;    // lines that would repeat many times a second
  std::optional<async::net::signal_set> signals;
  util::TimePoint stop_requested_at;
  std::uint32_t slots_live = 0;
  std::uint32_t rendering = 0;  // tiles on the render pool now
  // The last sign of work: the start, a lease granted, a render finished (exit_when_idle).
  util::TimePoint last_work_at;
  bool notify_systemd = false;
  bool told_finished = false;  // a "finished" answer was logged (without exit_when_done)
  bool ran = false;
  bool failed = false;

  std::atomic<bool> started{false};
  std::atomic<bool> stopping{false};
  std::atomic<bool> collector_finished{false};
  std::atomic<bool> stopped_idle{false};
  std::atomic<bool> stopped_runtime{false};
  Counter tiles_rendered;
  Counter tiles_submitted;
  Counter tiles_dropped;
  Counter tiles_rejected;
  Counter tiles_abandoned;
  Counter submit_retries;
  Counter lease_failures;
  Counter leases_dropped;
  Counter upload_leases;  // leases that came in the answer to an upload
  Counter scenes_fetched;
  Counter scenes_rejected;
  Counter tiles_held;
  Counter ack_ms;           // WorkerStats::ack_ms
  Counter in_hand_wait_ms;  // WorkerStats::in_hand_wait_ms
};

// Whole milliseconds from `from` to `to`, 0 if the clock went backwards (it does not: steady).
inline std::uint64_t ms_between(util::TimePoint from, util::TimePoint to) {
  const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(to - from).count();
  return ms > 0 ? static_cast<std::uint64_t>(ms) : 0;
}

}  // namespace dtraced::worker
