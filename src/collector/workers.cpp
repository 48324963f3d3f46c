#include "collector/workers.h"

#include <algorithm>

namespace dtraced::collector {
namespace {

std::int64_t bucket_slot(TimePoint t) { return t.time_since_epoch() / kRecentBucket; }

}  // namespace

WorkerRegistry::WorkerRegistry(WorkerLimits limits) : limits_(limits) {
  if (limits_.max_workers == 0) limits_.max_workers = 1;
}

WorkerRegistry::Entry& WorkerRegistry::touch(const WorkerId& id, TimePoint now, bool& fresh) {
  auto it = workers_.find(id);
  fresh = it == workers_.end();
  if (fresh) {
    if (workers_.size() >= limits_.max_workers) {
      retire(workers_.find(*recency_.back()));
      ++evicted_;
    }
    it = workers_.emplace(id, Entry{}).first;
    it->second.first_seen = now;
    recency_.push_front(&it->first);
    it->second.recency = recency_.begin();
  } else {
    recency_.splice(recency_.begin(), recency_, it->second.recency);
  }
  Entry& e = it->second;
  // The clock is monotonic, but a caller may hand in an earlier `now` after a later one (a
  // handler that read the clock before it suspended): last seen never goes back.
  e.last_seen = std::max(e.last_seen, now);
  e.quiet = false;
  return e;
}

WorkerRegistry::Map::iterator WorkerRegistry::retire(Map::iterator it) {
  const Entry& e = it->second;
  retired_.leases += e.leases;
  retired_.tiles += e.tiles;
  retired_.duplicates += e.duplicates;
  retired_.faulty_duplicates += e.faulty_duplicates;
  retired_.refused += e.refused;
  recency_.erase(e.recency);
  return workers_.erase(it);
}

bool WorkerRegistry::on_lease(const WorkerId& id, std::string_view isa, std::uint32_t threads, TimePoint now) {
  bool fresh = false;
  Entry& e = touch(id, now, fresh);
  ++e.leases;
  if (!isa.empty()) e.isa = std::string(isa.substr(0, kMaxIsaNameBytes));
  if (threads != 0) e.threads = threads;
  return fresh;
}

bool WorkerRegistry::on_tile(const WorkerId& id, TileOutcome outcome, std::uint64_t rays, TimePoint now) {
  bool fresh = false;
  Entry& e = touch(id, now, fresh);
  switch (outcome) {
    case TileOutcome::kStored: {
      ++e.tiles;
      const std::int64_t slot = bucket_slot(now);
      Bucket& b = e.recent[static_cast<std::size_t>(slot % static_cast<std::int64_t>(kRecentBuckets))];
      if (b.slot != slot) b = Bucket{slot, 0, 0};
      ++b.tiles;
      b.rays += rays;
      break;
    }
    case TileOutcome::kDuplicate:
      ++e.duplicates;
      break;
    case TileOutcome::kFaultyDuplicate:
      ++e.duplicates;
      ++e.faulty_duplicates;
      break;
    case TileOutcome::kRefused:
      ++e.refused;
      break;
    case TileOutcome::kJobGone:
      break;
  }
  return fresh;
}

std::vector<WorkerId> WorkerRegistry::sweep(TimePoint now) {
  std::vector<WorkerId> went_quiet;
  for (auto it = workers_.begin(); it != workers_.end();) {
    Entry& e = it->second;
    const Duration unseen = now - e.last_seen;
    if (unseen >= limits_.forget_after) {
      it = retire(it);
      continue;
    }
    if (unseen >= limits_.quiet_after && !e.quiet) {
      e.quiet = true;
      went_quiet.push_back(it->first);
    }
    ++it;
  }
  std::sort(went_quiet.begin(), went_quiet.end());
  return went_quiet;
}

std::vector<WorkerView> WorkerRegistry::list(TimePoint now) const {
  std::vector<WorkerView> out;
  out.reserve(workers_.size());
  const std::int64_t current = bucket_slot(now);
  for (const auto& [id, e] : workers_) {
    WorkerView v;
    v.id = id;
    v.isa = e.isa;
    v.threads = e.threads;
    v.since_first_seen = std::max(Duration::zero(), now - e.first_seen);
    v.since_last_seen = std::max(Duration::zero(), now - e.last_seen);
    v.quiet = v.since_last_seen >= limits_.quiet_after;
    v.leases = e.leases;
    v.tiles = e.tiles;
    v.duplicates = e.duplicates;
    v.faulty_duplicates = e.faulty_duplicates;
    v.refused = e.refused;
    for (const Bucket& b : e.recent) {
      // A bucket counts while it is one of the last kRecentBuckets slots, the current one included.
      if (b.slot >= 0 && b.slot <= current && current - b.slot < static_cast<std::int64_t>(kRecentBuckets)) {
        v.recent_tiles += b.tiles;
        v.recent_rays += b.rays;
      }
    }
    out.push_back(std::move(v));
  }
  std::sort(out.begin(), out.end(), [](const WorkerView& a, const WorkerView& b) {
    return a.since_last_seen != b.since_last_seen ? a.since_last_seen < b.since_last_seen : a.id < b.id;
  });
  return out;
}

}  // namespace dtraced::collector
