// Submission: a rendered tile is kept and sent through the submit gate until the collector
// acknowledges it, its job is gone, or the grace period after a stop is over.
#include <cstdint>
#include <optional>
#include <string>

#include <boost/asio/experimental/awaitable_operators.hpp>
#include <fmt/format.h>

#include "protocol/worker_messages.h"
#include "util/log.h"
#include "worker/log_limiter.h"
#include "worker/worker_impl.h"

namespace dtraced::worker {

using namespace async::net::experimental::awaitable_operators;

// Keeps one rendered tile until the collector acknowledges it, its job is gone, or the grace
// period after a stop is over.
async::Awaitable<> Worker::Impl::submit(HeldTile tile) {
  const std::string target = fmt::format("/v1/jobs/{}/tiles/{}", tile.job, tile.tile);
  // However this ends, the slot waiting for the next lease hears that no more is coming.
  struct FinishOffer {
    OfferPtr& offer;
    ~FinishOffer() {
      if (offer) offer->finish(std::nullopt);
    }
  } finish_offer{tile.offer};
  for (;;) {
    if (gone.contains(tile.job)) {
      tiles_dropped.add();
      co_return;
    }
    std::optional<RetryGate::Attempt> attempt = co_await submit_gate.enter(abandon);
    if (!attempt) {
      tiles_abandoned.add();
      co_return;
    }
    if (gone.contains(tile.job)) {
      tiles_dropped.add();
      co_return;
    }
    http::Request request =
        authorized(http::make_request(http::Verb::put, target, tile.payload, http::kBinaryContentType));
    request.set(protocol::kWorkerHeader, config.name);
    request.set(protocol::kRenderMsHeader, std::to_string(tile.render_ms));
    request.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
    // Only the first attempt asks: a retry's answer may come after backoff, and the slot asks
    // POST /v1/lease rather than wait for it.
    const bool asks = tile.offer && !tile.offer->finished;
    if (asks) {
      request.set(protocol::kNextLeaseHeader, std::to_string(config.threads));
      request.set(protocol::kIsaHeader, accel::isa_name(config.isa));
    }
    auto raced = co_await (client.request(url, std::move(request), protocol::kMaxMessageBytes) || abandon.wait());
    if (raced.index() == 1 || abandon.is_set()) {
      tiles_abandoned.add();
      co_return;
    }
    SubmitAnswer answer = classify_submit(std::get<0>(raced));
    if (asks) {
      if (answer.next) {
        // The tile is done with (acknowledged or its job gone): its place in hand goes to the lease.
        tile.reservation.unhold();
        tile.offer->reservation = std::move(tile.reservation);
      }
      tile.offer->finish(std::move(answer.next));
    }
    if (answer.verdict != SubmitVerdict::kRetry) {
      if (const std::uint32_t ended = submit_gate.succeeded(*attempt); ended > 0) {
        util::log_info("the collector {} takes tiles again after {} failures", url.to_string(), ended);
      }
    }
    switch (answer.verdict) {
      case SubmitVerdict::kAcknowledged:
        tiles_submitted.add();
        ack_ms.add(ms_between(tile.rendered_at, clock.now()));
        if (const std::uint32_t ended = lease_gate.accepted(); ended > 0) {
          util::log_info("the collector {} takes tiles again after {} refused in a row", url.to_string(), ended);
        }
        co_return;
      case SubmitVerdict::kJobGone:
        // Refused only if the collector leased the job again after saying it is gone.
        if (gone_answers.refusal(tile.job, /*marked=*/gone.contains(tile.job))) lease_gate.refused();
        if (!gone.contains(tile.job)) {
          if (const auto held_back = log_limiter.admit(fmt::format("gone {}", tile.job), clock.now())) {
            util::log_info("job {} is gone ({}): dropping its tiles and leases{}", tile.job, answer.message,
                           held_back_suffix(*held_back));
          }
          gone.add(tile.job);
        }
        tiles_dropped.add();
        co_return;
      case SubmitVerdict::kRejected: {
        tiles_rejected.add();
        const std::uint32_t in_a_row = lease_gate.refused();
        if (const auto held_back = log_limiter.admit(fmt::format("refused {}", tile.job), clock.now())) {
          util::log_error(
              "the collector refused tile {} of job {} ({}): dropping it; sending it again cannot help, so this is a "
              "bug in the worker or the collector; {} tiles refused in a row, leasing with backoff{}",
              tile.tile, tile.job, answer.message, in_a_row, held_back_suffix(*held_back));
        }
        co_return;
      }
      case SubmitVerdict::kRetry:
        break;
    }
    submit_retries.add();
    const std::uint32_t in_a_row = submit_gate.failed(*attempt);
    if (should_log_failure(in_a_row)) {
      util::log_warn("{} submitting to {} ({} failed attempts in a row); keeping {} tiles and retrying with backoff",
                     answer.message, url.to_string(), in_a_row, tiles_held.get());
    }
  }
}

}  // namespace dtraced::worker
