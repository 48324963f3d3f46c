// The worker's life: start the render slots, wait for a stop (request_stop, or a signal), then
// give what is in hand the grace period, on the worker's clock, to be acknowledged.

#include <signal.h>

#include <cstdint>
#include <exception>

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/experimental/awaitable_operators.hpp>

#include "util/log.h"
#include "util/sd_notify.h"
#include "worker/worker_impl.h"

namespace dtraced::worker {

using namespace async::net::experimental::awaitable_operators;

async::Awaitable<> Worker::Impl::main_loop(RunOptions options) {
  if (options.stop_on_signals) {
    signals.emplace(io, SIGTERM, SIGINT);
    async::net::co_spawn(io, watch_signals(), async::log_failure("the signal watcher"));
  }
  started = true;
  if (config.max_runtime.count() > 0) {
    async::net::co_spawn(io, watch_runtime(clock.now()), async::log_failure("the run-time watcher"));
  }
  // Ready before the start delay, so that a long one does not look like a start that hangs.
  if (notify_systemd) util::sd_notify_state("READY=1");
  // A staggered start: nothing is in hand yet, so a stop during the wait ends the worker at once.
  if (const auto delay = start_delay(config.start_jitter, rng); delay.count() > 0) {
    util::log_info("worker {}: waiting {} ms before the first request (--start-jitter-ms {})", config.name,
                   delay.count(), config.start_jitter.count());
    co_await async::sleep_for(clock, delay, &stop);
  }
  last_work_at = clock.now();
  util::log_info(
      "worker {} started: collector {}, {} render threads ({} kernels), up to {} tiles in hand, {} scenes cached",
      config.name, url.to_string(), config.threads, accel::isa_name(config.isa), config.max_unacknowledged,
      config.scene_cache);
  if (config.max_unacknowledged < 2 * std::uint64_t{config.threads}) {
    util::log_warn("max_unacknowledged {} is below 2 x {} threads: some threads will wait for the network",
                   config.max_unacknowledged, config.threads);
  }

  for (std::uint32_t i = 0; i < config.threads && !stop.is_set(); ++i) {
    ++slots_live;
    async::net::co_spawn(io, slot(), [this](std::exception_ptr e) {
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
                     config.grace.count(), tiles_held.get(), in_hand.count());
      abandon.set();
    }
    co_await drain();
  }
  if (signals) {
    boost::system::error_code ignored;
    signals->cancel(ignored);
  }
  const std::uint64_t submitted = tiles_submitted.get();
  util::log_info(
      "worker {} stopped: {} tiles rendered, {} submitted, {} retries; {} dropped (job gone), {} rejected, "
      "{} abandoned; {} leases dropped, {} lease failures, {} leases in upload answers; acknowledged {:.1f} ms after "
      "rendering on average, "
      "render slots waited {:.1f} s for room in hand (--max-unacknowledged {})",
      config.name, tiles_rendered.get(), submitted, submit_retries.get(), tiles_dropped.get(), tiles_rejected.get(),
      tiles_abandoned.get(), leases_dropped.get(), lease_failures.get(), upload_leases.get(),
      submitted == 0 ? 0.0 : double(ack_ms.get()) / double(submitted), double(in_hand_wait_ms.get()) / 1000.0,
      config.max_unacknowledged);
}

async::Awaitable<> Worker::Impl::watch_runtime(util::TimePoint started_at) {
  co_await async::sleep_until(clock, started_at + config.max_runtime, &stop);
  if (stop.is_set()) co_return;
  util::log_info("the run time of {} s is over: stopping (--max-runtime)", config.max_runtime.count());
  stopped_runtime = true;
  begin_stop();
}

async::Awaitable<> Worker::Impl::drain() {
  while (!drained()) co_await in_hand.changed().wait();
}

void Worker::Impl::begin_stop() {
  if (stop.is_set()) return;
  stop_requested_at = clock.now();
  stopping = true;
  stop.set();
  if (notify_systemd) util::sd_notify_state("STOPPING=1");
  util::log_info("stopping: no more leases; {} tiles in hand ({} awaiting acknowledgement), {} s to submit them",
                 in_hand.count(), tiles_held.get(), config.grace.count());
}

async::Awaitable<> Worker::Impl::watch_signals() {
  for (;;) {
    auto [ec, number] = co_await signals->async_wait(async::kAwaitTuple);
    if (ec) co_return;
    const char* name = number == SIGTERM ? "SIGTERM" : "SIGINT";
    if (!stop.is_set()) {
      util::log_info("{} received", name);
      begin_stop();
    } else if (!abandon.is_set()) {
      util::log_warn("{} received again: abandoning {} unacknowledged tiles now", name, tiles_held.get());
      abandon.set();
    }
  }
}

}  // namespace dtraced::worker
