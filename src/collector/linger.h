// dtraced::collector linger: a finished one-shot collector telling its workers before it stops.
//
// Owns: the decision of when a one-shot collector with exit_when_done, its job ended (done or
// cancelled), may stop. It lingers so that its workers hear "finished" (protocol kFinishedHeader
// on the lease answer) instead of retrying against a dead address: until every worker seen
// recently (not quiet in the registry, workers.h) when the linger began has asked for a lease
// and been told, or until linger_bound() has passed, whichever comes first. With no recent
// worker there is nothing to wait for: the stop begins at once (stop.h, begin_linger).
//
// Pure: no clock reads, no I/O; the caller passes `now` and acts on the answers.
//
// Thread safety: none. One owner (the collector's event loop).
#pragma once

#include <chrono>
#include <cstddef>
#include <set>
#include <vector>

#include "collector/queue.h"
#include "collector/workers.h"

namespace dtraced::collector {

// The shortest linger. An idle worker was told to ask again within queue.max_retry_after (0.5 s
// by default) and comes back within 1.5 x that (its jitter, worker/backoff.h); 5 s covers that
// ten times over, and also a worker that was busy submitting a duplicate tile or waiting out a
// short backoff, while a farm whose job is over waits only a few seconds more for its exit.
inline constexpr Duration kFinishedLinger = std::chrono::seconds(5);

// How long a finished collector lingers at most: kFinishedLinger, or twice the longest
// retry-after it gives (so that a farm configured to poll slowly still hears it), whichever is
// longer. At most 2 x protocol::kMaxRetryAfterMs, since max_retry_after is bounded by it.
Duration linger_bound(const QueueConfig& queue);

// The workers to tell: those `registry` has not marked quiet as of `now`.
std::vector<WorkerId> workers_to_tell(const WorkerRegistry& registry, TimePoint now);

// Who is still to be told, and until when the collector waits for them.
class FinishedLinger {
 public:
  FinishedLinger(const std::vector<WorkerId>& to_tell, TimePoint deadline)
      : untold_(to_tell.begin(), to_tell.end()), deadline_(deadline) {}

  // `id` was answered "finished" (it may be one that was not waited for: nothing changes then).
  void told(const WorkerId& id) { untold_.erase(id); }
  bool everyone_told() const { return untold_.empty(); }
  std::size_t untold() const { return untold_.size(); }
  TimePoint deadline() const { return deadline_; }
  // Whether the stop may begin at `now`.
  bool over(TimePoint now) const { return everyone_told() || now >= deadline_; }

 private:
  std::set<WorkerId> untold_;
  TimePoint deadline_;
};

}  // namespace dtraced::collector
