#include "collector/queue.h"

#include <algorithm>
#include <cassert>

#include <fmt/format.h>

namespace dtraced::collector {
namespace {

using std::chrono::milliseconds;

constexpr Duration kMaxConfigDuration = std::chrono::hours(24 * 7);

// `factor` x `d`, saturating well below Duration's range: the product of a large bound and a
// large factor must not wrap around into a negative duration.
Duration scaled(Duration d, double factor) {
  const double ticks = static_cast<double>(d.count()) * factor;
  const double cap = static_cast<double>(kMaxConfigDuration.count()) * kMaxCopyExpiryFactor;
  return Duration(static_cast<Duration::rep>(std::min(ticks, cap)));
}

// Whether `order` holds each of [0, n) exactly once.
bool is_permutation_of_range(std::span<const TileIndex> order, TileIndex n) {
  if (order.size() != n) return false;
  std::vector<bool> seen(n, false);
  for (const TileIndex t : order) {
    if (t >= n || seen[t]) return false;
    seen[t] = true;
  }
  return true;
}

}  // namespace

util::Errors check_queue_config(const QueueConfig& c) {
  util::Errors errors;
  const auto positive = [](Duration d) { return d > Duration::zero() && d <= kMaxConfigDuration; };
  if (!positive(c.reoffer_floor)) errors.push_back({"must be > 0 and at most a week", "reoffer_floor"});
  if (!positive(c.reoffer_ceiling) || c.reoffer_ceiling < c.reoffer_floor) {
    errors.push_back({"must be >= reoffer_floor and at most a week", "reoffer_ceiling"});
  }
  if (!(c.reoffer_factor >= 1 && c.reoffer_factor <= kMaxReofferFactor)) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxReofferFactor), "reoffer_factor"});
  }
  if (c.max_copies < 1 || c.max_copies > kMaxCopiesLimit) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxCopiesLimit), "max_copies"});
  }
  if (!(c.copy_expiry_factor >= 1 && c.copy_expiry_factor <= kMaxCopyExpiryFactor)) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxCopyExpiryFactor), "copy_expiry_factor"});
  }
  if (c.window_size < 1 || c.window_size > kMaxWindowSize) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxWindowSize), "window_size"});
  }
  if (!positive(c.min_retry_after) || !positive(c.max_retry_after) || c.min_retry_after > c.max_retry_after) {
    errors.push_back(
        {"min_retry_after and max_retry_after must be > 0, at most a week, and min <= max", "min_retry_after"});
  }
  return errors;
}

WorkQueue::WorkQueue(QueueConfig config) : config_(config) { assert(check_queue_config(config_).empty()); }

bool WorkQueue::add_job(JobId id, std::int32_t priority, TileIndex tile_count,
                        std::span<const TileIndex> already_stored, std::span<const TileIndex> skipped,
                        std::span<const TileIndex> order) {
  if (tile_count == 0 || tile_count > kMaxQueueTiles || jobs_.contains(id)) return false;
  if (!order.empty() && !is_permutation_of_range(order, tile_count)) return false;
  const auto out_of_range = [&](TileIndex t) { return t >= tile_count; };
  if (std::any_of(already_stored.begin(), already_stored.end(), out_of_range) ||
      std::any_of(skipped.begin(), skipped.end(), out_of_range)) {
    return false;
  }
  Job job;
  job.priority = priority;
  job.tile_count = tile_count;
  job.tiles_total = tile_count;
  job.bound = config_.reoffer_floor;
  job.tiles.resize(tile_count);
  for (const TileIndex t : skipped) {
    if (!job.tiles[t].skipped) --job.tiles_total;
    job.tiles[t].skipped = true;
  }
  for (const TileIndex t : already_stored) {
    if (job.tiles[t].skipped) return false;
    if (!job.tiles[t].stored) ++job.tiles_done;
    job.tiles[t].stored = true;
  }
  if (job.tiles_total == 0) return false;
  if (job.done()) {
    release_tiles(job);
  } else {
    const auto unfinished = [&job](TileIndex t) { return !job.tiles[t].stored && !job.tiles[t].skipped; };
    if (order.empty()) {
      for (TileIndex t = 0; t < tile_count; ++t) {
        if (unfinished(t)) job.ring.push_back(t);
      }
    } else {
      for (const TileIndex t : order) {
        if (unfinished(t)) job.ring.push_back(t);
      }
    }
    active_.insert(order_key(id, job));
  }
  jobs_.emplace(id, std::move(job));
  return true;
}

LeaseResult WorkQueue::lease(TimePoint now, std::string_view holder) {
  Duration soonest = Duration::max();
  for (const auto& [key, id] : active_) {
    Job& job = jobs_.at(id);
    // Bounded by the queue's length at the start: every tile is looked at once at most.
    for (std::size_t n = job.ring.size(); n > 0; --n) {
      const TileIndex t = job.ring.front();
      job.ring.pop_front();
      Tile& tile = job.tiles[t];
      if (tile.stored) continue;  // completed since it was last here: it leaves the ring now
      job.ring.push_back(t);
      const Duration wait = until_eligible(tile, job, now);
      if (wait <= Duration::zero()) {
        ++stats_.leases;
        if (tile.ever_leased) ++stats_.reoffers;
        tile.ever_leased = true;
        tile.leases.push_back(OutLease{now, holder_id(holder)});
        return {LeaseGrant{id, t}, milliseconds(0)};
      }
      soonest = std::min(soonest, wait);
    }
  }
  const Duration wait = std::clamp(soonest, config_.min_retry_after, config_.max_retry_after);
  return {std::nullopt, std::chrono::ceil<milliseconds>(wait)};
}

CompleteResult WorkQueue::complete(JobId id, TileIndex t, TimePoint now) {
  const auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled || t >= it->second.tile_count) return CompleteResult::kJobGone;
  Job& job = it->second;
  if (!job.done() && job.tiles[t].skipped) return CompleteResult::kJobGone;
  if (job.done() || job.tiles[t].stored) {
    ++stats_.duplicates;
    return CompleteResult::kAlreadyDone;
  }
  Tile& tile = job.tiles[t];
  drop_expired(tile, job, now);
  // A result for a lease that expired, or that a previous collector process handed out, has no
  // start time here: it teaches nothing about tile times.
  if (!tile.leases.empty()) {
    const TimePoint oldest =
        std::min_element(tile.leases.begin(), tile.leases.end(), [](const OutLease& a, const OutLease& b) {
          return a.at < b.at;
        })->at;
    record_duration(job, std::max(Duration::zero(), now - oldest));
  }
  tile.stored = true;
  tile.leases = {};  // frees the vector
  ++job.tiles_done;
  ++stats_.stored;
  if (job.done()) {
    active_.erase(order_key(id, job));
    release_tiles(job);
  }
  return CompleteResult::kStored;
}

TileStatus WorkQueue::tile_status(JobId id, TileIndex t) const {
  const auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled) return TileStatus::kJobGone;
  const Job& job = it->second;
  if (t >= job.tile_count) return TileStatus::kNoSuchTile;
  if (!job.done() && job.tiles[t].skipped) return TileStatus::kNoSuchTile;
  if (job.done() || job.tiles[t].stored) return TileStatus::kStored;
  return TileStatus::kPending;
}

bool WorkQueue::is_done(JobId id) const {
  const auto it = jobs_.find(id);
  return it != jobs_.end() && !it->second.cancelled && it->second.done();
}

bool WorkQueue::cancel(JobId id) {
  const auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled || it->second.done()) return false;
  active_.erase(order_key(id, it->second));
  it->second.cancelled = true;
  release_tiles(it->second);
  return true;
}

bool WorkQueue::set_paused(JobId id, bool paused) {
  auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled || it->second.paused == paused) return false;
  Job& job = it->second;
  job.paused = paused;
  if (paused) {
    active_.erase(order_key(id, job));
  } else if (!job.done()) {
    active_.insert(order_key(id, job));
  }
  return true;
}

bool WorkQueue::set_priority(JobId id, std::int32_t priority) {
  auto it = jobs_.find(id);
  if (it == jobs_.end()) return false;
  Job& job = it->second;
  // Re-keyed only if it was in the order: a cancelled or finished job is not.
  const bool active = active_.erase(order_key(id, job)) == 1;
  job.priority = priority;
  if (active) active_.insert(order_key(id, job));
  return true;
}

bool WorkQueue::remove_job(JobId id) {
  const auto it = jobs_.find(id);
  if (it == jobs_.end()) return false;
  active_.erase(order_key(id, it->second));
  jobs_.erase(it);
  return true;
}

std::optional<JobProgress> WorkQueue::progress(JobId id, TimePoint now) const {
  const auto it = jobs_.find(id);
  if (it == jobs_.end()) return std::nullopt;
  const Job& job = it->second;
  JobProgress p;
  p.tiles_total = job.tiles_total;
  p.tiles_done = job.tiles_done;
  p.cancelled = job.cancelled;
  const Duration lifetime = lease_lifetime(job);
  for (const Tile& tile : job.tiles) {
    if (tile.stored) continue;
    for (const OutLease& l : tile.leases) {
      if (now - l.at < lifetime) ++p.leases_outstanding;
    }
  }
  return p;
}

std::size_t WorkQueue::focus(JobId id, std::span<const TileIndex> tiles) {
  const auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled || it->second.done()) return 0;
  Job& job = it->second;
  std::vector<bool> chosen(job.tile_count, false);
  std::deque<TileIndex> ring;
  for (const TileIndex t : tiles) {
    if (t >= job.tile_count || chosen[t]) continue;
    const Tile& tile = job.tiles[t];
    if (tile.stored || tile.skipped || !tile.leases.empty()) continue;
    chosen[t] = true;
    ring.push_back(t);
  }
  const std::size_t moved = ring.size();
  if (moved == 0) return 0;
  for (const TileIndex t : job.ring) {
    if (!chosen[t]) ring.push_back(t);
  }
  job.ring = std::move(ring);
  return moved;
}

bool WorkQueue::has_lease(JobId id, TileIndex t, TimePoint now) const {
  const auto it = jobs_.find(id);
  if (it == jobs_.end() || it->second.cancelled || it->second.done() || t >= it->second.tile_count) return false;
  const Job& job = it->second;
  const Tile& tile = job.tiles[t];
  if (tile.stored) return false;
  const Duration lifetime = lease_lifetime(job);
  return std::any_of(tile.leases.begin(), tile.leases.end(), [&](const OutLease& l) { return now - l.at < lifetime; });
}

Duration WorkQueue::reoffer_bound(JobId id) const {
  const auto it = jobs_.find(id);
  return it == jobs_.end() ? config_.reoffer_floor : it->second.bound;
}

QueueStats WorkQueue::stats() const {
  QueueStats s = stats_;
  s.active_jobs = active_.size();
  return s;
}

Duration WorkQueue::lease_lifetime(const Job& job) const { return scaled(job.bound, config_.copy_expiry_factor); }

void WorkQueue::drop_expired(Tile& tile, const Job& job, TimePoint now) const {
  const Duration lifetime = lease_lifetime(job);
  std::erase_if(tile.leases, [&](const OutLease& l) { return now - l.at >= lifetime; });
}

Duration WorkQueue::until_eligible(Tile& tile, const Job& job, TimePoint now) const {
  drop_expired(tile, job, now);
  if (tile.leases.empty()) return Duration::min();
  const Duration lifetime = lease_lifetime(job);
  // Leases are appended as time goes on, so the last is the newest.
  TimePoint eligible_at = tile.leases.back().at + job.bound;
  if (tile.leases.size() >= config_.max_copies) {
    // At the copy cap: wait also for enough of the oldest leases to expire.
    eligible_at = std::max(eligible_at, tile.leases[tile.leases.size() - config_.max_copies].at + lifetime);
  }
  return eligible_at - now;
}

void WorkQueue::record_duration(Job& job, Duration d) {
  if (job.window.size() < config_.window_size) {
    job.window.push_back(d);
  } else {
    job.window[job.window_next] = d;
    job.window_next = (job.window_next + 1) % config_.window_size;
  }
  // p90 by the nearest-rank method: the smallest sample with at least 90% of samples <= it.
  std::vector<Duration> sorted = job.window;
  const std::size_t rank = (sorted.size() * 9 + 9) / 10;  // ceil(0.9 n), >= 1
  std::nth_element(sorted.begin(), sorted.begin() + static_cast<std::ptrdiff_t>(rank - 1), sorted.end());
  const Duration p90 = sorted[rank - 1];
  job.bound = std::clamp(scaled(p90, config_.reoffer_factor), config_.reoffer_floor, config_.reoffer_ceiling);
}

std::uint32_t WorkQueue::holder_id(std::string_view holder) {
  if (holder.empty()) return 0;
  const auto it = std::find(holders_.begin(), holders_.end(), holder);
  if (it != holders_.end()) return static_cast<std::uint32_t>(1 + (it - holders_.begin()));
  if (holders_.size() >= kMaxHolders) return 0;
  holders_.emplace_back(holder);
  return static_cast<std::uint32_t>(holders_.size());
}

std::size_t WorkQueue::release_holder(std::string_view holder) {
  const auto it = std::find(holders_.begin(), holders_.end(), holder);
  if (holder.empty() || it == holders_.end()) return 0;
  const auto id = static_cast<std::uint32_t>(1 + (it - holders_.begin()));
  std::size_t released = 0;
  for (auto& [job_id, job] : jobs_) {
    std::vector<bool> freed(job.tiles.size(), false);
    bool any = false;
    for (std::size_t t = 0; t < job.tiles.size(); ++t) {
      Tile& tile = job.tiles[t];
      const std::size_t before = tile.leases.size();
      std::erase_if(tile.leases, [id](const OutLease& l) { return l.holder == id; });
      if (tile.leases.size() != before) {
        released += before - tile.leases.size();
        freed[t] = !tile.stored;
        any = any || freed[t];
      }
    }
    // Those tiles first, in their present order: the next leases hand them out.
    if (any) {
      std::stable_partition(job.ring.begin(), job.ring.end(), [&freed](TileIndex t) { return freed[t]; });
    }
  }
  return released;
}

void WorkQueue::release_tiles(Job& job) {
  job.tiles = {};
  job.ring = {};
  job.window = {};
  job.window_next = 0;
}

}  // namespace dtraced::collector
