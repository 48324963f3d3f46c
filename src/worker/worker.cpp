#include "worker/worker.h"

#include <signal.h>

#include <algorithm>
#include <atomic>
#include <cassert>
#include <chrono>
#include <deque>
#include <exception>
#include <functional>
#include <limits>
#include <map>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <string_view>
#include <utility>
#include <variant>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/experimental/awaitable_operators.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/signal_set.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "async/async.h"
#include "http/client.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "render/tile.h"
#include "scene/load.h"
#include "util/log.h"
#include "util/sd_notify.h"
#include "worker/backoff.h"
#include "worker/scene_cache.h"

namespace dtraced::worker {
namespace {

namespace net = async::net;
namespace bhttp = boost::beast::http;
using namespace net::experimental::awaitable_operators;
using async::Awaitable;
using async::Event;
using async::Executor;
using async::kAwaitTuple;
using async::Signal;
using util::TimePoint;

// A failing collector is logged on the first failure of a run of failures and then every
// kLogEveryNthFailure-th: an outage of an hour leaves a few dozen lines, not one per attempt.
constexpr std::uint32_t kLogEveryNthFailure = 10;
// Jobs remembered as gone (410), so that their other tiles and leases are dropped unsent.
constexpr std::size_t kMaxGoneJobs = 1024;
// Bytes of an unexpected answer's body quoted in a log line.
constexpr std::size_t kMaxQuotedBodyBytes = 200;

bool should_log_failure(std::uint32_t failures_in_a_row) {
  return failures_in_a_row == 1 || (failures_in_a_row > 0 && failures_in_a_row % kLogEveryNthFailure == 0);
}

// "HTTP 503: the store is busy" from an answer that is not the one hoped for: the JSON error
// body when there is one, else the start of the body with anything unprintable masked.
std::string describe_answer(const http::Response& response) {
  const unsigned status = response.result_int();
  const auto error = protocol::decode_error_body(response.body());
  if (error) {
    const protocol::ErrorBody& body = error.value();
    if (body.field.empty()) return fmt::format("HTTP {}: {}", status, body.error);
    return fmt::format("HTTP {}: {} (at {})", status, body.error, body.field);
  }
  std::string excerpt = response.body().substr(0, kMaxQuotedBodyBytes);
  for (char& c : excerpt) {
    if (c < 0x20 || c > 0x7e) c = '?';
  }
  if (excerpt.empty()) return fmt::format("HTTP {}", status);
  return fmt::format("HTTP {}: {}", status, excerpt);
}

// When requests of one kind (leases, or submissions) may go out. After a failure the next
// request waits a backoff delay; while the collector keeps failing, or has no work ("retry
// after"), only one request at a time goes out (the probe) and the others wait for its outcome,
// so that a worker with many threads asks once, not once per thread. Probes are taken in the
// order the requests arrived at the gate, and a request that failed queues again at the back:
// if the collector fails on one tile only, the others still get their turn, succeed, and end the
// backoff for everyone. Failures are counted in rounds: the requests that were already in flight
// when the collector went away fail together, and count (and back off) once.
//
// One owner: the event loop.
class RetryGate {
 public:
  // A request allowed out. Report its outcome with succeeded() or failed(); one dropped without
  // either (its coroutine stopped) just frees the probe for another request.
  class Attempt {
   public:
    Attempt(Attempt&& other) noexcept
        : gate_(std::exchange(other.gate_, nullptr)), round_(other.round_), probe_(other.probe_) {}
    Attempt(const Attempt&) = delete;
    Attempt& operator=(const Attempt&) = delete;
    Attempt& operator=(Attempt&&) = delete;
    ~Attempt() {
      if (gate_ != nullptr) gate_->finish(*this);
    }

   private:
    friend class RetryGate;
    Attempt(RetryGate* gate, std::uint64_t round, bool probe) : gate_(gate), round_(round), probe_(probe) {}

    RetryGate* gate_;
    std::uint64_t round_;
    bool probe_;
  };

  RetryGate(const Executor& executor, const util::Clock& clock, Backoff backoff, std::mt19937_64& rng)
      : clock_(clock), backoff_(backoff), rng_(rng), changed_(executor) {}

  // Waits until a request may go out; nullopt once `stop` is set.
  Awaitable<std::optional<Attempt>> enter(Event& stop) {
    const Ticket ticket(*this);
    for (;;) {
      if (stop.is_set()) co_return std::nullopt;
      const TimePoint not_before = std::max(backoff_until_, idle_until_);
      if (clock_.now() < not_before) {
        co_await (async::sleep_until(clock_, not_before, &stop) || changed_.wait());
        continue;
      }
      const bool probe = failures_ > 0 || idle_;
      if (probe && (probing_ || *waiting_.begin() != ticket.number)) {
        co_await (changed_.wait() || stop.wait());
        continue;
      }
      if (probe) probing_ = true;
      co_return std::optional<Attempt>(Attempt(this, round_, probe));
    }
  }

  // The collector answered. Returns the number of failures in a row this ends (0 normally).
  std::uint32_t succeeded(Attempt& attempt) {
    finish(attempt);
    const std::uint32_t ended = failures_;
    if (failures_ > 0) {
      failures_ = 0;
      ++round_;
      backoff_until_ = TimePoint::min();
      changed_.notify_all();
    }
    return ended;
  }

  // The request failed. Returns the failures in a row counting this one, or 0 when another
  // request of the same round has already failed (and backed off) for it.
  std::uint32_t failed(Attempt& attempt) {
    finish(attempt);
    if (attempt.round_ != round_) return 0;
    if (failures_ < std::numeric_limits<std::uint32_t>::max()) ++failures_;
    ++round_;
    backoff_until_ = clock_.now() + backoff_.delay(failures_ - 1, rng_);
    changed_.notify_all();
    return failures_;
  }

  // The collector has no work: ask again (one request at a time) no sooner than `delay` from now.
  void idle_for(std::chrono::milliseconds delay) {
    idle_ = true;
    idle_until_ = std::max(idle_until_, clock_.now() + delay);
  }

  // The collector has work again: every request may go out at once.
  void busy() {
    if (!idle_) return;
    idle_ = false;
    idle_until_ = TimePoint::min();
    changed_.notify_all();
  }

 private:
  void finish(Attempt& attempt) {
    if (attempt.gate_ == nullptr) return;
    attempt.gate_ = nullptr;
    if (attempt.probe_) {
      probing_ = false;
      changed_.notify_all();
    }
  }

  // A request's place in the line for probes, from its arrival at the gate until it leaves.
  struct Ticket {
    explicit Ticket(RetryGate& gate) : gate(gate), number(gate.next_ticket_++) { gate.waiting_.insert(number); }
    Ticket(const Ticket&) = delete;
    Ticket& operator=(const Ticket&) = delete;
    ~Ticket() {
      gate.waiting_.erase(number);
      gate.changed_.notify_all();  // the next in line may probe now
    }
    RetryGate& gate;
    const std::uint64_t number;
  };

  const util::Clock& clock_;
  Backoff backoff_;
  std::mt19937_64& rng_;
  Signal changed_;  // failures, idleness or the probe changed
  std::uint32_t failures_ = 0;
  std::uint64_t round_ = 0;
  bool probing_ = false;
  std::uint64_t next_ticket_ = 0;
  std::set<std::uint64_t> waiting_;  // tickets of the requests at the gate, oldest first
  bool idle_ = false;
  TimePoint backoff_until_ = TimePoint::min();
  TimePoint idle_until_ = TimePoint::min();
};

// The tiles in hand (config.h, max_unacknowledged), counted by reservations that release
// themselves when the lease, the tile or the coroutine holding them goes away. The event loop
// changes the counts; other threads may read them.
class InHand {
 public:
  class Reservation {
   public:
    Reservation() = default;
    Reservation(Reservation&& other) noexcept : owner_(std::exchange(other.owner_, nullptr)) {}
    Reservation& operator=(Reservation&& other) noexcept {
      if (this != &other) {
        reset();
        owner_ = std::exchange(other.owner_, nullptr);
      }
      return *this;
    }
    Reservation(const Reservation&) = delete;
    Reservation& operator=(const Reservation&) = delete;
    ~Reservation() { reset(); }

    void reset() {
      if (owner_ != nullptr) std::exchange(owner_, nullptr)->release();
    }

   private:
    friend class InHand;
    explicit Reservation(InHand* owner) : owner_(owner) {}
    InHand* owner_ = nullptr;
  };

  InHand(const Executor& executor, std::uint64_t limit) : limit_(limit), changed_(executor) {}

  bool full() const { return count_.load(std::memory_order_relaxed) >= limit_; }
  std::uint64_t count() const { return count_.load(std::memory_order_relaxed); }
  std::uint64_t peak() const { return peak_.load(std::memory_order_relaxed); }

  // Notified whenever a reservation is released.
  Signal& changed() { return changed_; }

  Reservation reserve() {
    const std::uint64_t n = count_.load(std::memory_order_relaxed) + 1;
    count_.store(n, std::memory_order_relaxed);
    if (n > peak_.load(std::memory_order_relaxed)) peak_.store(n, std::memory_order_relaxed);
    return Reservation(this);
  }

 private:
  void release() {
    count_.store(count_.load(std::memory_order_relaxed) - 1, std::memory_order_relaxed);
    changed_.notify_all();
  }

  std::uint64_t limit_;
  std::atomic<std::uint64_t> count_{0};
  std::atomic<std::uint64_t> peak_{0};
  Signal changed_;
};

// Jobs the collector said are gone, the most recent kMaxGoneJobs of them.
class GoneJobs {
 public:
  bool contains(std::uint64_t job) const { return jobs_.contains(job); }
  void add(std::uint64_t job) {
    if (!jobs_.insert(job).second) return;
    order_.push_back(job);
    if (order_.size() > kMaxGoneJobs) {
      jobs_.erase(order_.front());
      order_.pop_front();
    }
  }
  void remove(std::uint64_t job) {
    if (jobs_.erase(job) == 0) return;
    order_.erase(std::find(order_.begin(), order_.end(), job));
  }

 private:
  std::set<std::uint64_t> jobs_;
  std::deque<std::uint64_t> order_;
};

// A lease ready to render: its scene is built.
struct Work {
  protocol::Lease lease;
  ScenePtr scene;
  InHand::Reservation reservation;
};

// A rendered tile awaiting its acknowledgement.
struct HeldTile {
  std::uint64_t job = 0;
  std::uint32_t tile = 0;
  std::string payload;  // protocol::encode_tile_payload
  InHand::Reservation reservation;
};

struct SceneOutcome {
  ScenePtr scene;        // set on success
  bool stopped = false;  // the worker is stopping; nobody needs the scene now
  std::string error;     // why not, otherwise
};

// A fetch of one scene that other slots needing the same scene wait for.
struct PendingScene {
  explicit PendingScene(const Executor& executor) : done(executor) {}
  Signal done;
  bool finished = false;
  SceneOutcome outcome;
};

struct LeaseAnswer {
  bool stopped = false;
  std::optional<protocol::Lease> lease;
  std::optional<std::chrono::milliseconds> retry_after;
  std::string error;  // a failure, to retry with backoff
  bool token_rejected = false;
};

enum class SubmitVerdict {
  kAcknowledged,  // stored or already done: the tile is safe
  kJobGone,       // drop it and everything else of its job
  kRejected,      // the collector will never take it: drop it and say so
  kRetry,         // keep it and try again
};

struct SubmitAnswer {
  SubmitVerdict verdict = SubmitVerdict::kRetry;
  std::string message;
  bool token_rejected = false;
};

SubmitAnswer classify_submit(const http::ClientResult& result) {
  if (!result.ok()) return {SubmitVerdict::kRetry, result.message};
  const http::Response& response = result.response;
  const unsigned status = response.result_int();
  if (response.result() == http::Status::ok) {
    const auto decoded = protocol::decode_submit_result(response.body());
    if (!decoded) {
      // Probably stored, but it cannot be known: sending it again is harmless (already done).
      return {SubmitVerdict::kRetry, fmt::format("malformed answer: {}", decoded.error().to_string())};
    }
    if (decoded.value() == protocol::SubmitResult::kJobGone) return {SubmitVerdict::kJobGone, "job gone"};
    return {SubmitVerdict::kAcknowledged, std::string(protocol::to_string(decoded.value()))};
  }
  if (response.result() == http::Status::gone) return {SubmitVerdict::kJobGone, describe_answer(response)};
  if (response.result() == http::Status::unauthorized) {
    return {SubmitVerdict::kRetry, "token rejected (HTTP 401)", /*token_rejected=*/true};
  }
  // Timeouts and rate limits are the collector's state, not the tile's.
  if (response.result() == http::Status::request_timeout || response.result() == http::Status::too_many_requests ||
      status >= 500) {
    return {SubmitVerdict::kRetry, describe_answer(response)};
  }
  if (status >= 400) return {SubmitVerdict::kRejected, describe_answer(response)};
  return {SubmitVerdict::kRetry, fmt::format("unexpected answer: {}", describe_answer(response))};
}

std::uint64_t seed_from(std::uint64_t configured) {
  if (configured != 0) return configured;
  std::random_device device;
  return (std::uint64_t{device()} << 32) ^ device();
}

// `text` has passed validate(): it parses.
http::Url parse_url(const std::string& text) {
  std::string error;
  std::optional<http::Url> url = http::parse_base_url(text, error);
  assert(url);
  return *url;
}

}  // namespace

// Everything here lives on the event loop (io), except the counters read by stats() and the
// render pool's work, which sees only copies and the immutable scenes.
struct Worker::Impl {
  Impl(WorkerConfig resolved, const util::Clock& clock)
      : config(std::move(resolved)),
        clock(clock),
        url(parse_url(config.collector_url)),
        authorization("Bearer " + config.token),
        pool(config.threads),
        rng(seed_from(config.jitter_seed)),
        scenes(config.scene_cache),
        lease_gate(io.get_executor(), clock, Backoff(config.backoff_initial, config.backoff_max), rng),
        submit_gate(io.get_executor(), clock, Backoff(config.backoff_initial, config.backoff_max), rng),
        stop(io.get_executor()),
        abandon(io.get_executor()),
        in_hand(io.get_executor(), config.max_unacknowledged) {}

  // ---- the pipeline ----

  Awaitable<> main_loop(RunOptions options);
  Awaitable<> slot();
  Awaitable<std::optional<Work>> acquire();
  Awaitable<LeaseAnswer> request_lease();
  Awaitable<SceneOutcome> ensure_scene(std::string digest);
  Awaitable<SceneOutcome> fetch_scene(std::string digest);
  Awaitable<> render_and_hand_off(Work work);
  Awaitable<> submit(HeldTile tile);
  Awaitable<> watch_signals();
  Awaitable<> drain();

  void begin_stop();
  bool drained() const {
    return slots_live == 0 && in_hand.count() == 0 && tiles_held.load(std::memory_order_relaxed) == 0;
  }
  void note_lease_failure(RetryGate::Attempt& attempt, const std::string& message, bool token_rejected);
  void note_lease_success(RetryGate::Attempt& attempt);
  http::Request authorized(http::Request request) const {
    request.set(bhttp::field::authorization, authorization);
    return request;
  }
  static void count(std::atomic<std::uint64_t>& counter) { counter.fetch_add(1, std::memory_order_relaxed); }
  static std::uint64_t read(const std::atomic<std::uint64_t>& counter) {
    return counter.load(std::memory_order_relaxed);
  }

  // ---- state (declaration order is construction order) ----

  const WorkerConfig config;
  const util::Clock& clock;  // every time the worker reads and every sleep
  const http::Url url;
  const std::string authorization;

  net::io_context io{1};  // run by one thread: run()'s caller
  net::thread_pool pool;  // render threads
  std::mt19937_64 rng;    // retry jitter
  SceneCache scenes;
  std::map<std::string, std::shared_ptr<PendingScene>, std::less<>> fetching;
  RetryGate lease_gate;
  RetryGate submit_gate;
  Event stop;     // no more leases
  Event abandon;  // stop submitting: the grace period is over
  InHand in_hand;
  GoneJobs gone;
  std::optional<net::signal_set> signals;
  TimePoint stop_requested_at;
  std::uint32_t slots_live = 0;
  bool notify_systemd = false;
  bool ran = false;
  bool failed = false;

  std::atomic<bool> started{false};
  std::atomic<bool> stopping{false};
  std::atomic<std::uint64_t> tiles_rendered{0};
  std::atomic<std::uint64_t> tiles_submitted{0};
  std::atomic<std::uint64_t> tiles_dropped{0};
  std::atomic<std::uint64_t> tiles_rejected{0};
  std::atomic<std::uint64_t> tiles_abandoned{0};
  std::atomic<std::uint64_t> submit_retries{0};
  std::atomic<std::uint64_t> lease_failures{0};
  std::atomic<std::uint64_t> leases_dropped{0};
  std::atomic<std::uint64_t> scenes_fetched{0};
  std::atomic<std::uint64_t> scenes_rejected{0};
  std::atomic<std::uint64_t> tiles_held{0};
};

Awaitable<> Worker::Impl::main_loop(RunOptions options) {
  if (options.stop_on_signals) {
    signals.emplace(io, SIGTERM, SIGINT);
    net::co_spawn(io, watch_signals(), async::log_failure("the signal watcher"));
  }
  started = true;
  if (notify_systemd) util::sd_notify_state("READY=1");
  util::log_info(
      "worker {} started: collector {}, {} render threads ({} kernels), up to {} tiles in hand, {} scenes cached",
      config.name, url.to_string(), config.threads, accel::isa_name(config.isa), config.max_unacknowledged,
      config.scene_cache);
  if (config.max_unacknowledged < 2 * std::uint64_t{config.threads}) {
    util::log_warn("max_unacknowledged {} is below 2 x {} threads: some threads will wait for the network",
                   config.max_unacknowledged, config.threads);
  }

  for (std::uint32_t i = 0; i < config.threads; ++i) {
    ++slots_live;
    net::co_spawn(io, slot(), [this](std::exception_ptr e) {
      if (e) {
        async::log_exception("a render slot", e);
        failed = true;
        begin_stop();
      }
      --slots_live;
      in_hand.changed().notify_all();
    });
  }

  while (!stop.is_set()) co_await stop.wait();
  co_await (drain() || async::sleep_until(clock, stop_requested_at + config.grace, &abandon));
  if (!drained()) {
    if (!abandon.is_set()) {
      util::log_warn("the grace period of {} s is over: abandoning {} unacknowledged tiles ({} tiles in hand)",
                     config.grace.count(), read(tiles_held), in_hand.count());
      abandon.set();
    }
    co_await drain();
  }
  if (signals) {
    boost::system::error_code ignored;
    signals->cancel(ignored);
  }
  util::log_info(
      "worker {} stopped: {} tiles rendered, {} submitted, {} retries; {} dropped (job gone), {} rejected, "
      "{} abandoned; {} leases dropped, {} lease failures",
      config.name, read(tiles_rendered), read(tiles_submitted), read(submit_retries), read(tiles_dropped),
      read(tiles_rejected), read(tiles_abandoned), read(leases_dropped), read(lease_failures));
}

Awaitable<> Worker::Impl::drain() {
  while (!drained()) co_await in_hand.changed().wait();
}

void Worker::Impl::begin_stop() {
  if (stop.is_set()) return;
  stop_requested_at = clock.now();
  stopping = true;
  stop.set();
  if (notify_systemd) util::sd_notify_state("STOPPING=1");
  util::log_info("stopping: no more leases; {} tiles in hand ({} awaiting acknowledgement), {} s to submit them",
                 in_hand.count(), read(tiles_held), config.grace.count());
}

Awaitable<> Worker::Impl::watch_signals() {
  for (;;) {
    auto [ec, number] = co_await signals->async_wait(kAwaitTuple);
    if (ec) co_return;
    const char* name = number == SIGTERM ? "SIGTERM" : "SIGINT";
    if (!stop.is_set()) {
      util::log_info("{} received", name);
      begin_stop();
    } else if (!abandon.is_set()) {
      util::log_warn("{} received again: abandoning {} unacknowledged tiles now", name, read(tiles_held));
      abandon.set();
    }
  }
}

// One render thread's pipeline: while tile N renders on the pool, lease N + 1.
Awaitable<> Worker::Impl::slot() {
  std::optional<Work> next = co_await acquire();
  while (next && !stop.is_set()) {
    Work current = std::move(*next);
    next.reset();
    if (gone.contains(current.lease.job)) {
      count(leases_dropped);
      next = co_await acquire();
      continue;
    }
    next = co_await (render_and_hand_off(std::move(current)) && acquire());
  }
  // A lease held but not started is simply dropped: the collector offers it again.
  if (next) count(leases_dropped);
}

Awaitable<std::optional<Work>> Worker::Impl::acquire() {
  for (;;) {
    while (in_hand.full() && !stop.is_set()) co_await (in_hand.changed().wait() || stop.wait());
    std::optional<RetryGate::Attempt> attempt = co_await lease_gate.enter(stop);
    if (!attempt) co_return std::nullopt;
    if (in_hand.full()) continue;  // others filled it while this one waited at the gate

    InHand::Reservation reservation = in_hand.reserve();
    LeaseAnswer answer = co_await request_lease();
    if (answer.stopped) co_return std::nullopt;
    if (!answer.error.empty()) {
      note_lease_failure(*attempt, answer.error, answer.token_rejected);
      continue;
    }
    if (answer.retry_after) {
      note_lease_success(*attempt);
      lease_gate.idle_for(jittered_retry_after(*answer.retry_after, rng));
      continue;
    }
    lease_gate.busy();
    protocol::Lease lease = std::move(*answer.lease);
    // The collector is the authority: a job it leases out is not gone (any more).
    gone.remove(lease.job);
    SceneOutcome scene = co_await ensure_scene(lease.digest);
    if (!scene.scene) {
      count(leases_dropped);
      if (scene.stopped) co_return std::nullopt;
      note_lease_failure(*attempt, scene.error, /*token_rejected=*/false);
      continue;
    }
    note_lease_success(*attempt);
    co_return Work{std::move(lease), std::move(scene.scene), std::move(reservation)};
  }
}

void Worker::Impl::note_lease_failure(RetryGate::Attempt& attempt, const std::string& message, bool token_rejected) {
  count(lease_failures);
  const std::uint32_t in_a_row = lease_gate.failed(attempt);
  if (!should_log_failure(in_a_row)) return;
  if (token_rejected) {
    util::log_error("token rejected by the collector {} ({} failed attempts in a row); retrying with backoff",
                    url.to_string(), in_a_row);
  } else {
    util::log_warn("no lease from {} ({} failed attempts in a row): {}; retrying with backoff", url.to_string(),
                   in_a_row, message);
  }
}

void Worker::Impl::note_lease_success(RetryGate::Attempt& attempt) {
  if (const std::uint32_t ended = lease_gate.succeeded(attempt); ended > 0) {
    util::log_info("the collector {} answers leases again after {} failures", url.to_string(), ended);
  }
}

Awaitable<LeaseAnswer> Worker::Impl::request_lease() {
  LeaseAnswer answer;
  http::Request request = authorized(http::make_request(
      http::Verb::post, "/v1/lease", protocol::encode(protocol::LeaseRequest{config.name, config.threads}),
      http::kJsonContentType));
  auto raced =
      co_await (http::request(url, std::move(request), config.timeouts, protocol::kMaxMessageBytes) || stop.wait());
  if (raced.index() == 1 || stop.is_set()) {
    answer.stopped = true;
    co_return answer;
  }
  const http::ClientResult& result = std::get<0>(raced);
  if (!result.ok()) {
    answer.error = result.message;
    co_return answer;
  }
  if (result.response.result() == http::Status::unauthorized) {
    answer.error = "token rejected (HTTP 401)";
    answer.token_rejected = true;
    co_return answer;
  }
  if (result.response.result() != http::Status::ok) {
    answer.error = describe_answer(result.response);
    co_return answer;
  }
  auto reply = protocol::decode_lease_reply(result.response.body());
  if (!reply) {
    answer.error = fmt::format("malformed lease reply: {}", reply.error().to_string());
    co_return answer;
  }
  if (auto* lease = std::get_if<protocol::Lease>(&reply.value())) {
    answer.lease = std::move(*lease);
  } else {
    answer.retry_after = std::chrono::milliseconds{std::get<protocol::RetryAfter>(reply.value()).ms};
  }
  co_return answer;
}

// The scene named `digest`, from the cache, or fetched once however many slots need it at once.
Awaitable<SceneOutcome> Worker::Impl::ensure_scene(std::string digest) {
  if (ScenePtr cached = scenes.find(digest)) co_return SceneOutcome{std::move(cached), /*stopped=*/false, {}};
  if (const auto it = fetching.find(digest); it != fetching.end()) {
    const std::shared_ptr<PendingScene> pending = it->second;
    while (!pending->finished && !stop.is_set()) co_await (pending->done.wait() || stop.wait());
    if (!pending->finished) co_return SceneOutcome{nullptr, /*stopped=*/true, {}};
    co_return pending->outcome;
  }

  const auto pending = std::make_shared<PendingScene>(io.get_executor());
  fetching.emplace(digest, pending);
  SceneOutcome outcome;
  std::exception_ptr error;
  try {
    outcome = co_await fetch_scene(digest);
  } catch (...) {
    error = std::current_exception();
    outcome.error = "fetching the scene failed with an internal error";
  }
  if (outcome.scene) scenes.insert(digest, outcome.scene);
  pending->outcome = outcome;
  pending->finished = true;
  pending->done.notify_all();
  fetching.erase(digest);
  if (error) std::rethrow_exception(error);
  co_return outcome;
}

Awaitable<SceneOutcome> Worker::Impl::fetch_scene(std::string digest) {
  SceneOutcome outcome;
  http::Request request = authorized(http::make_request(http::Verb::get, fmt::format("/v1/scenes/{}", digest)));
  auto raced = co_await (http::request(url, std::move(request), config.timeouts, scene::kMaxSceneBytes) || stop.wait());
  if (raced.index() == 1 || stop.is_set()) {
    outcome.stopped = true;
    co_return outcome;
  }
  http::ClientResult& result = std::get<0>(raced);
  if (!result.ok()) {
    outcome.error = fmt::format("fetching scene {}: {}", digest, result.message);
    co_return outcome;
  }
  if (result.response.result() != http::Status::ok) {
    outcome.error = fmt::format("fetching scene {}: {}", digest, describe_answer(result.response));
    co_return outcome;
  }
  const std::size_t bytes = result.response.body().size();
  auto prepare = [body = std::move(result.response.body()), &digest, isa = config.isa] {
    return prepare_scene(body, digest, isa);
  };
  PreparedScene prepared = co_await async::on_pool(pool, std::move(prepare));
  if (!prepared.scene) {
    count(scenes_rejected);
    util::log_error("refusing scene {}: {}", digest, prepared.error);
    outcome.error = std::move(prepared.error);
    co_return outcome;
  }
  count(scenes_fetched);
  util::log_info("scene {} fetched ({} bytes), verified and built", digest, bytes);
  outcome.scene = std::move(prepared.scene);
  co_return outcome;
}

Awaitable<> Worker::Impl::render_and_hand_off(Work work) {
  const protocol::Lease& lease = work.lease;
  // The pool reads the lease and the scene while this coroutine waits: both outlive the wait.
  auto render = [&lease, &scene = *work.scene] {
    render::Tile tile = render::render_tile(scene, lease.settings, lease.rect);
    // With adaptive sampling the counts travel too (flag bit 0): the collector checks them and
    // keeps them with the pixels.
    return protocol::encode_tile_payload(
        protocol::TilePayload{lease.job, lease.tile, lease.rect, std::move(tile.rgb), std::move(tile.spp)});
  };
  std::string payload = co_await async::on_pool(pool, std::move(render));
  count(tiles_rendered);
  if (abandon.is_set()) {
    count(tiles_abandoned);
    co_return;
  }
  if (gone.contains(lease.job)) {
    count(tiles_dropped);
    co_return;
  }
  count(tiles_held);
  net::co_spawn(io, submit(HeldTile{lease.job, lease.tile, std::move(payload), std::move(work.reservation)}),
                [this](std::exception_ptr e) {
                  async::log_exception("submitting a tile", e);
                  tiles_held.fetch_sub(1, std::memory_order_relaxed);
                  in_hand.changed().notify_all();
                });
}

// Keeps one rendered tile until the collector acknowledges it, its job is gone, or the grace
// period after a stop is over.
Awaitable<> Worker::Impl::submit(HeldTile tile) {
  const std::string target = fmt::format("/v1/jobs/{}/tiles/{}", tile.job, tile.tile);
  for (;;) {
    if (gone.contains(tile.job)) {
      count(tiles_dropped);
      co_return;
    }
    std::optional<RetryGate::Attempt> attempt = co_await submit_gate.enter(abandon);
    if (!attempt) {
      count(tiles_abandoned);
      co_return;
    }
    if (gone.contains(tile.job)) {
      count(tiles_dropped);
      co_return;
    }
    http::Request request =
        authorized(http::make_request(http::Verb::put, target, tile.payload, http::kBinaryContentType));
    request.set(protocol::kWorkerHeader, config.name);
    auto raced = co_await (http::request(url, std::move(request), config.timeouts, protocol::kMaxMessageBytes) ||
                           abandon.wait());
    if (raced.index() == 1 || abandon.is_set()) {
      count(tiles_abandoned);
      co_return;
    }
    const SubmitAnswer answer = classify_submit(std::get<0>(raced));
    if (answer.verdict != SubmitVerdict::kRetry) {
      if (const std::uint32_t ended = submit_gate.succeeded(*attempt); ended > 0) {
        util::log_info("the collector {} takes tiles again after {} failures", url.to_string(), ended);
      }
    }
    switch (answer.verdict) {
      case SubmitVerdict::kAcknowledged:
        count(tiles_submitted);
        co_return;
      case SubmitVerdict::kJobGone:
        if (!gone.contains(tile.job)) {
          util::log_info("job {} is gone ({}): dropping its tiles and leases", tile.job, answer.message);
          gone.add(tile.job);
        }
        count(tiles_dropped);
        co_return;
      case SubmitVerdict::kRejected:
        count(tiles_rejected);
        util::log_error(
            "the collector refused tile {} of job {} ({}): dropping it; sending it again cannot help, so this is a "
            "bug in the worker or the collector",
            tile.tile, tile.job, answer.message);
        co_return;
      case SubmitVerdict::kRetry:
        break;
    }
    count(submit_retries);
    const std::uint32_t in_a_row = submit_gate.failed(*attempt);
    if (should_log_failure(in_a_row)) {
      util::log_warn("{} submitting to {} ({} failed attempts in a row); keeping {} tiles and retrying with backoff",
                     answer.token_rejected ? "token rejected" : answer.message, url.to_string(), in_a_row,
                     read(tiles_held));
    }
  }
}

// ---- Worker ----------------------------------------------------------------------------------

util::Result<std::unique_ptr<Worker>, util::Errors> Worker::create(const WorkerConfig& config,
                                                                   const util::Clock& clock) {
  util::Errors problems = validate(config);
  if (!problems.empty()) return problems;
  return std::unique_ptr<Worker>(new Worker(std::make_unique<Impl>(resolve_defaults(config), clock)));
}

Worker::Worker(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

Worker::~Worker() = default;

bool Worker::run(const RunOptions& options) {
  Impl& s = *impl_;
  assert(!s.ran);
  s.ran = true;
  s.notify_systemd = options.notify_systemd;
  net::co_spawn(s.io, s.main_loop(options), [&s](std::exception_ptr e) {
    if (!e) return;
    async::log_exception("the worker", e);
    s.failed = true;
    // Wind everything down: nothing is left to wait for it.
    s.begin_stop();
    s.abandon.set();
    if (s.signals) {
      boost::system::error_code ignored;
      s.signals->cancel(ignored);
    }
  });
  s.io.run();
  s.pool.join();
  return !s.failed;
}

void Worker::request_stop() {
  Impl* impl = impl_.get();
  net::post(impl->io, [impl] { impl->begin_stop(); });
}

WorkerStats Worker::stats() const {
  const Impl& s = *impl_;
  WorkerStats stats;
  stats.started = s.started.load();
  stats.stopping = s.stopping.load();
  stats.tiles_rendered = Impl::read(s.tiles_rendered);
  stats.tiles_submitted = Impl::read(s.tiles_submitted);
  stats.tiles_dropped = Impl::read(s.tiles_dropped);
  stats.tiles_rejected = Impl::read(s.tiles_rejected);
  stats.tiles_abandoned = Impl::read(s.tiles_abandoned);
  stats.submit_retries = Impl::read(s.submit_retries);
  stats.lease_failures = Impl::read(s.lease_failures);
  stats.leases_dropped = Impl::read(s.leases_dropped);
  stats.scenes_fetched = Impl::read(s.scenes_fetched);
  stats.scenes_rejected = Impl::read(s.scenes_rejected);
  stats.tiles_held = Impl::read(s.tiles_held);
  stats.tiles_in_hand = s.in_hand.count();
  stats.tiles_in_hand_peak = s.in_hand.peak();
  return stats;
}

const WorkerConfig& Worker::config() const { return impl_->config; }

int run_worker(const WorkerConfig& config) {
  try {
    auto worker = Worker::create(config);
    if (!worker) {
      for (const util::Error& problem : worker.error())
        util::log_error("worker configuration: {}", problem.to_string());
      return 2;
    }
    return worker.value()->run({.stop_on_signals = true, .notify_systemd = true}) ? 0 : 1;
  } catch (const std::exception& e) {
    util::log_error("worker: {}", e.what());
    return 1;
  }
}

}  // namespace dtraced::worker
