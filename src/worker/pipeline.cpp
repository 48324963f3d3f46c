// A render slot's pipeline: lease a tile, make sure its scene is built (by digest, fetched once
// however many slots need it), render it on the pool, and hand the pixels to submission.

#include <algorithm>
#include <chrono>
#include <exception>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <variant>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/experimental/awaitable_operators.hpp>
#include <fmt/format.h>

#include "protocol/tile_payload.h"
#include "protocol/worker_messages.h"
#include "render/tile.h"
#include "scene/load.h"
#include "util/log.h"
#include "worker/backoff.h"
#include "worker/worker_impl.h"

namespace dtraced::worker {

using namespace async::net::experimental::awaitable_operators;

// One render thread's pipeline: while tile N renders on the pool, lease N + 1. The upload of
// tile N - 1 (spawned as N starts) asks for that lease in its answer, so that a tile costs one
// request; POST /v1/lease asks only when the answer brought none.
async::Awaitable<> Worker::Impl::slot() {
  OfferPtr offered;  // the next lease the last hand-off's upload asks for
  std::optional<Work> next = co_await acquire(nullptr);
  while (next && !stop.is_set()) {
    Work current = std::move(*next);
    next.reset();
    if (gone.contains(current.lease.job)) {
      leases_dropped.add();
      next = co_await acquire(std::exchange(offered, nullptr));
      continue;
    }
    OfferPtr from_upload = std::exchange(offered, nullptr);
    next = co_await (render_and_hand_off(std::move(current), offered) && acquire(std::move(from_upload), &offered));
  }
  // A lease held but not started is simply dropped: the collector offers it again.
  if (next) leases_dropped.add();
  if (offered && offered->answer && offered->answer->lease) leases_dropped.add();
}

async::Awaitable<std::optional<Work>> Worker::Impl::take_offer(OfferPtr offered, bool& stopped) {
  while (!offered->finished && !stop.is_set()) co_await (offered->done.wait() || stop.wait());
  stopped = stop.is_set();
  if (stopped || !offered->answer) co_return std::nullopt;
  LeaseAnswer& answer = *offered->answer;
  if (answer.retry_after) {
    // As the same answer to POST /v1/lease: nothing now.
    if (answer.collector_finished && note_collector_finished()) stopped = true;
    if (!stopped && note_no_work()) stopped = true;
    if (!stopped) lease_gate.idle_for(jittered_retry_after(*answer.retry_after, rng));
    co_return std::nullopt;
  }
  upload_leases.add();
  auto [lease, scene] = co_await begin_lease(std::move(*answer.lease));
  if (!scene.scene) {
    leases_dropped.add();
    stopped = scene.stopped;
    // POST /v1/lease asks next, and counts a failure that repeats (with its backoff).
    if (const auto held_back = log_limiter.admit(fmt::format("scene {}", lease.digest), clock.now())) {
      util::log_warn("dropping a lease of job {} from {}: {}{}", lease.job, url.to_string(), scene.error,
                     held_back_suffix(*held_back));
    }
    co_return std::nullopt;
  }
  co_return Work{std::move(lease), std::move(scene.scene), std::move(offered->reservation)};
}

async::Awaitable<std::pair<protocol::Lease, SceneOutcome>> Worker::Impl::begin_lease(protocol::Lease lease) {
  lease_gate.busy();
  last_work_at = clock.now();
  // The collector is the authority: a job it leases out is not gone (any more).
  gone.remove(lease.job);
  SceneOutcome scene = co_await ensure_scene(lease.digest);
  co_return std::pair{std::move(lease), std::move(scene)};
}

async::Awaitable<std::optional<Work>> Worker::Impl::acquire(OfferPtr offered, OfferPtr* pending) {
  if (offered) {
    bool stopped = false;
    std::optional<Work> work = co_await take_offer(std::move(offered), stopped);
    if (work || stopped) co_return work;
  }
  // The lease that the upload of the tile this slot renders asks for (set once the render ends).
  auto watched = [pending]() -> OfferedLease* { return pending != nullptr ? pending->get() : nullptr; };
  std::optional<util::TimePoint> waiting_since;  // for room in hand
  auto waited = [&] {
    if (waiting_since) in_hand_wait_ms.add(ms_between(*std::exchange(waiting_since, std::nullopt), clock.now()));
  };
  for (;;) {
    // That lease holds the place of the tile its upload acknowledged, and only this slot takes
    // it: taken as soon as it comes, full hand or not (a hand with room would otherwise ask the
    // collector for more while the lease it already holds waits, and the collector, having leased
    // the last tiles to this worker, would answer "retry" for as long as that lasts).
    if (OfferedLease* offer = watched(); offer != nullptr && offer->finished) {
      bool stopped = false;
      std::optional<Work> work = co_await take_offer(std::exchange(*pending, nullptr), stopped);
      if (work || stopped) {
        waited();
        co_return work;
      }
      continue;
    }
    if (stop.is_set()) co_return std::nullopt;
    if (in_hand.full()) {
      if (!waiting_since) waiting_since = clock.now();
      if (OfferedLease* offer = watched()) {
        co_await (in_hand.changed().wait() || offer->done.wait() || stop.wait());
      } else {
        co_await (in_hand.changed().wait() || stop.wait());
      }
      continue;
    }
    waited();
    std::optional<RetryGate::Attempt> attempt = co_await enter_lease_gate(watched());
    if (!attempt) {
      if (stop.is_set()) co_return std::nullopt;
      continue;  // the watched lease came while the gate held this request
    }
    if (in_hand.full()) continue;  // others filled it while this one waited at the gate

    InHand::Reservation reservation = in_hand.reserve();
    std::optional<LeaseAnswer> answered = co_await request_lease();
    if (!answered) co_return std::nullopt;
    LeaseAnswer& answer = *answered;
    if (!answer.error.empty()) {
      note_lease_failure(*attempt, answer.error, answer.token_rejected);
      continue;
    }
    if (answer.retry_after) {
      note_lease_success(*attempt);
      if (answer.collector_finished && note_collector_finished()) co_return std::nullopt;
      if (note_no_work()) co_return std::nullopt;
      lease_gate.idle_for(jittered_retry_after(*answer.retry_after, rng));
      continue;
    }
    auto [lease, scene] = co_await begin_lease(std::move(*answer.lease));
    if (!scene.scene) {
      leases_dropped.add();
      if (scene.stopped) co_return std::nullopt;
      note_lease_failure(*attempt, scene.error, /*token_rejected=*/false);
      continue;
    }
    note_lease_success(*attempt);
    co_return Work{std::move(lease), std::move(scene.scene), std::move(reservation)};
  }
}

async::Awaitable<std::optional<RetryGate::Attempt>> Worker::Impl::enter_lease_gate(OfferedLease* offer) {
  if (offer == nullptr) co_return co_await lease_gate.enter(stop);
  // An idle or failing collector holds requests at the gate; the offered lease may come meanwhile.
  auto raced = co_await (lease_gate.enter(stop) || offer->done.wait());
  if (raced.index() == 1) co_return std::nullopt;
  co_return std::move(std::get<0>(raced));
}

void Worker::Impl::note_lease_failure(RetryGate::Attempt& attempt, const std::string& message, bool token_rejected) {
  lease_failures.add();
  const std::uint32_t in_a_row = lease_gate.failed(attempt);
  if (!should_log_failure(in_a_row)) return;
  if (token_rejected) {
    util::log_error("{} by the collector {} ({} failed attempts in a row); retrying with backoff", message,
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

bool Worker::Impl::note_collector_finished() {
  if (!config.exit_when_done) {
    if (!told_finished) {
      util::log_info(
          "the collector {} says it has finished all its work and is going away; without --exit-when-done this "
          "worker keeps asking for work at that address",
          url.to_string());
    }
    told_finished = true;
    return false;
  }
  if (!stop.is_set()) {
    util::log_info("the collector {} has finished all its work and is going away: stopping (--exit-when-done)",
                   url.to_string());
    collector_finished = true;
    begin_stop();
  }
  return true;
}

bool Worker::Impl::note_no_work() {
  if (config.exit_when_idle.count() == 0 || stop.is_set()) return stop.is_set();
  if (rendering > 0 || tiles_held.get() > 0) return false;
  const util::TimePoint now = clock.now();
  if (now - last_work_at < config.exit_when_idle) return false;
  util::log_info("no work from the collector {} for {} s: stopping (--exit-when-idle {})", url.to_string(),
                 std::chrono::duration_cast<std::chrono::seconds>(now - last_work_at).count(),
                 config.exit_when_idle.count());
  stopped_idle = true;
  begin_stop();
  return true;
}

async::Awaitable<std::optional<LeaseAnswer>> Worker::Impl::request_lease() {
  http::Request request = authorized(http::make_request(
      http::Verb::post, "/v1/lease", protocol::encode(protocol::LeaseRequest{config.name, config.threads}),
      http::kJsonContentType));
  request.set(protocol::kIsaHeader, accel::isa_name(config.isa));
  request.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
  auto raced = co_await (client.request(url, std::move(request), protocol::kMaxMessageBytes) || stop.wait());
  if (raced.index() == 1 || stop.is_set()) co_return std::nullopt;
  co_return classify_lease(std::get<0>(raced));
}

// The scene named `digest`, from the cache, or fetched once however many slots need it at once.
async::Awaitable<SceneOutcome> Worker::Impl::ensure_scene(std::string digest) {
  if (FramesPtr cached = scenes.find(digest)) co_return SceneOutcome{std::move(cached), /*stopped=*/false, {}};
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

async::Awaitable<SceneOutcome> Worker::Impl::fetch_scene(std::string digest) {
  SceneOutcome outcome;
  // A static scene this worker has prepared before (this run or an earlier one) is on disk in its
  // render-ready form: no fetch, no parse. A file that does not read is reported and replaced.
  if (!config.scene_cache_dir.empty()) {
    const std::string path = cached_scene_path(config.scene_cache_dir, digest);
    std::error_code ec;
    if (std::filesystem::exists(path, ec)) {
      auto read = [&path, &digest, isa = config.isa, threads = config.threads] {
        PreparedScene prepared;
        if (util::Result<FramesPtr> cached = read_cached_scene(path, digest, isa, threads)) {
          prepared.scene = std::move(*cached);
          // Recently used: the last to be pruned.
          std::error_code touch_ec;
          std::filesystem::last_write_time(path, std::filesystem::file_time_type::clock::now(), touch_ec);
        } else {
          prepared.error = cached.error().to_string();
        }
        return prepared;
      };
      PreparedScene cached = co_await async::on_pool(pool, std::move(read));
      if (cached.scene) {
        scenes_fetched.add();
        util::log_info("scene {} read from its cache file {} and built", digest, path);
        outcome.scene = std::move(cached.scene);
        co_return outcome;
      }
      util::log_warn("{}; fetching the scene instead", cached.error);
    }
  }
  http::Request request = authorized(http::make_request(http::Verb::get, fmt::format("/v1/scenes/{}", digest)));
  auto raced = co_await (client.request(url, std::move(request), scene::kMaxSceneBytes) || stop.wait());
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
  // On the pool with the parse: the disk cache, written there, is pruned there too (a directory
  // listing and removals are file-system work the event loop should not wait for). It holds as
  // many scenes as the memory cache (--scene-cache).
  auto prepare = [body = std::move(result.response.body()), &digest, isa = config.isa, threads = config.threads,
                  &cache_dir = config.scene_cache_dir, keep = config.scene_cache] {
    PreparedScene prepared = prepare_scene(body, digest, isa, threads, cache_dir);
    if (!cache_dir.empty()) prune_scene_cache(cache_dir, keep);
    return prepared;
  };
  PreparedScene prepared = co_await async::on_pool(pool, std::move(prepare));
  if (!prepared.warning.empty()) util::log_warn("scene {}: {}", digest, prepared.warning);
  if (!prepared.scene) {
    scenes_rejected.add();
    util::log_error("refusing scene {}: {}", digest, prepared.error);
    outcome.error = std::move(prepared.error);
    co_return outcome;
  }
  scenes_fetched.add();
  util::log_info("scene {} fetched ({} bytes), verified and {}", digest, bytes,
                 prepared.scene->scene().animated() ? "its static part built" : "built");
  outcome.scene = std::move(prepared.scene);
  co_return outcome;
}

async::Awaitable<> Worker::Impl::render_and_hand_off(Work work, OfferPtr& offered) {
  const protocol::Lease& lease = work.lease;
  // The pool reads the lease and the scene while this coroutine waits: both outlive the wait.
  // Timed on the render thread itself, so that waiting for a free thread does not count. The
  // lease's settings.frame picks the frame of an animated scene (built here, on the render
  // thread, by the first tile of that frame; the scene keeps the latest few).
  auto render = [&lease, &scene = *work.scene, &clock = clock] {
    const util::TimePoint start = clock.now();
    render::Tile tile = scene.render(lease.settings, lease.rect);
    const auto took = std::chrono::duration_cast<std::chrono::milliseconds>(clock.now() - start);
    // With adaptive sampling the counts travel too (flag bit 0): the collector checks them and
    // keeps them with the pixels.
    return std::pair(protocol::encode_tile_payload(protocol::TilePayload{lease.job, lease.tile, lease.rect,
                                                                         std::move(tile.rgb), std::move(tile.spp)}),
                     static_cast<std::uint64_t>(std::max<std::int64_t>(took.count(), 0)));
  };
  std::pair<std::string, std::uint64_t> rendered;
  {
    // Counted while on the pool, and uncounted even if the render throws, so that exit_when_idle
    // is not disabled for good by one failed tile.
    ++rendering;
    struct Uncount {
      std::uint32_t& n;
      ~Uncount() { --n; }
    } uncount{rendering};
    rendered = co_await async::on_pool(pool, std::move(render));
  }
  auto& [payload, render_ms] = rendered;
  last_work_at = clock.now();
  tiles_rendered.add();
  if (abandon.is_set()) {
    tiles_abandoned.add();
    co_return;
  }
  if (gone.contains(lease.job)) {
    tiles_dropped.add();
    co_return;
  }
  tiles_held.add();
  work.reservation.hold(payload.size());
  // The next lease rides on this upload when a POST /v1/lease could go out freely now; it takes
  // this tile's place in hand once the tile is acknowledged.
  OfferPtr offer;
  if (!stop.is_set() && lease_gate.open()) {
    offer = std::make_shared<OfferedLease>(io.get_executor());
    offered = offer;
  }
  async::net::co_spawn(io,
                       submit(HeldTile{lease.job, lease.tile, std::move(payload), std::move(work.reservation),
                                       render_ms, clock.now(), std::move(offer)}),
                       [this](std::exception_ptr e) {
                         async::log_exception("submitting a tile", e);
                         tiles_held.remove();
                         in_hand.changed().notify_all();
                       });
}

}  // namespace dtraced::worker
