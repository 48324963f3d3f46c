// dtraced::collector workers: the registry of workers, built from their stateless requests.
//
// Owns: what the collector knows of each worker without heartbeats (DESIGN.md: "every request
// stands alone"): every lease request and tile upload updates its sender's entry. A worker is
// named by the name it sends (the lease request's "worker", the tile upload's X-Dtraced-Worker
// header) and the peer address its request came from, so two hosts that share a name stay apart.
// Per worker: first and last seen, its instruction set and render threads (from its last lease
// request), counts since it was first seen (leases, tiles stored, duplicates, faulty duplicates,
// refused tiles), and the tiles and camera rays (one per sample) it delivered in the last
// kRecentWindow, kept in a fixed ring of kRecentBuckets buckets.
//
// A worker unseen for quiet_after is "quiet"; unseen for forget_after it is forgotten. At most
// max_workers are kept: a new worker past the cap evicts the least recently seen one, found in
// O(1) from a recency list that every request moves its sender to the front of (so a farm larger
// than the cap costs a map lookup and an eviction per request, not a scan of the registry). So
// memory is bounded whatever connects: about kWorkerEntryBytes a worker.
//
// Pure: no sockets, no clock reads (every call takes `now`, the collector's monotonic clock), no
// logging; the caller logs what the results say (a first request, a worker going quiet).
//
// Thread safety: none. One owner (the collector's event loop) calls everything.
#pragma once

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <list>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>
#include <vector>

#include <boost/container_hash/hash.hpp>

#include "collector/queue.h"

namespace dtraced::collector {

// Heap bytes one known worker costs, measured on the hashed registry (node, recency list entry
// and its share of the bucket array): 100,000 entries with 21-byte names and IPv4 peers
// (Slurm-style HOST-JOB_TASK names), malloc's in-use bytes (mallinfo2) before and after, divided.
// The longest names and peers (protocol::kMaxWorkerNameBytes, kMaxPeerBytes) add 192 more.
inline constexpr std::size_t kWorkerEntryBytes = 512;
// The default cap: six times a 10,000-worker farm, so that a farm that size, its restarts and
// further arrays under new names (Slurm names are HOST-JOB_TASK: a new array is new names) stay
// listed until forget_after instead of evicting each other; 65,536 x kWorkerEntryBytes = 32 MiB
// at most (44 MiB with the longest names).
inline constexpr std::size_t kDefaultMaxWorkers = 65'536;
// The largest cap the configuration accepts (--max-workers): about 0.5 GiB of registry at most.
inline constexpr std::size_t kMaxMaxWorkers = 1'000'000;

struct WorkerLimits {
  Duration quiet_after = std::chrono::seconds(60);
  Duration forget_after = std::chrono::hours(1);
  std::size_t max_workers = kDefaultMaxWorkers;  // [1, kMaxMaxWorkers]
};

// The window of "recent" counts, and its resolution.
inline constexpr std::size_t kRecentBuckets = 10;
inline constexpr Duration kRecentBucket = std::chrono::seconds(30);
inline constexpr Duration kRecentWindow = kRecentBucket * kRecentBuckets;
// Longest instruction-set name kept (longer ones are cut; names are short identifiers).
inline constexpr std::size_t kMaxIsaNameBytes = 16;

struct WorkerId {
  std::string name;  // as sent, already checked printable and bounded
  std::string peer;  // the request's source address, "" when unknown
  auto operator<=>(const WorkerId&) const = default;
};

// What a tile upload came to, as far as the registry counts it.
enum class TileOutcome {
  kStored,           // stored and acknowledged
  kDuplicate,        // already stored, same pixels
  kFaultyDuplicate,  // already stored, different pixels: a faulty worker?
  kRefused,          // 400: a bad payload or rectangle
  kJobGone,          // 410
};

// One worker as GET /v1/workers shows it.
struct WorkerView {
  WorkerId id;
  std::string isa;            // "" until a lease request named one
  std::uint32_t threads = 0;  // 0 until a lease request gave them
  bool quiet = false;
  Duration since_first_seen{};
  Duration since_last_seen{};
  std::uint64_t leases = 0;
  std::uint64_t tiles = 0;  // stored
  std::uint64_t duplicates = 0;
  std::uint64_t faulty_duplicates = 0;
  std::uint64_t refused = 0;
  std::uint64_t recent_tiles = 0;  // stored in the last kRecentWindow
  std::uint64_t recent_rays = 0;
};

class WorkerRegistry {
 public:
  explicit WorkerRegistry(WorkerLimits limits = {});
  // recency_ points into workers_: moved, never copied.
  WorkerRegistry(const WorkerRegistry&) = delete;
  WorkerRegistry& operator=(const WorkerRegistry&) = delete;
  WorkerRegistry(WorkerRegistry&&) = default;
  WorkerRegistry& operator=(WorkerRegistry&&) = default;

  // A lease request. True when this worker was not known (its first request; past the cap,
  // making room for it evicted another, which evicted() counts).
  bool on_lease(const WorkerId& id, std::string_view isa, std::uint32_t threads, TimePoint now);
  // A tile upload and what came of it; `rays` counts only for kStored. True on a first request.
  bool on_tile(const WorkerId& id, TileOutcome outcome, std::uint64_t rays, TimePoint now);

  // Marks the workers unseen for quiet_after as quiet and returns those that just became so (to
  // be logged once each); forgets those unseen for forget_after.
  std::vector<WorkerId> sweep(TimePoint now);

  // Every worker, most recently seen first; quiet ones as of `now`.
  std::vector<WorkerView> list(TimePoint now) const;
  std::size_t size() const { return workers_.size(); }
  // Workers evicted to stay under max_workers, since construction.
  std::uint64_t evicted() const { return evicted_; }
  // The counts of every worker forgotten or evicted so far, summed (so that totals over the
  // listed workers plus these never go down).
  const WorkerView& retired() const { return retired_; }
  const WorkerLimits& limits() const { return limits_; }

 private:
  struct Bucket {
    std::int64_t slot = -1;  // which kRecentBucket since the clock's epoch; -1: empty
    std::uint64_t tiles = 0;
    std::uint64_t rays = 0;
  };
  using Recency = std::list<const WorkerId*>;  // keys of workers_ (stable while in the map)
  struct Entry {
    Recency::iterator recency;  // its place in recency_
    std::string isa;
    std::uint32_t threads = 0;
    TimePoint first_seen;
    TimePoint last_seen;
    bool quiet = false;
    std::uint64_t leases = 0;
    std::uint64_t tiles = 0;
    std::uint64_t duplicates = 0;
    std::uint64_t faulty_duplicates = 0;
    std::uint64_t refused = 0;
    std::array<Bucket, kRecentBuckets> recent{};
  };
  struct IdHash {
    std::size_t operator()(const WorkerId& id) const {
      std::size_t h = std::hash<std::string>{}(id.name);
      boost::hash_combine(h, id.peer);
      return h;
    }
  };
  // Hashed: every request looks its sender up (a std::map's string compares showed in profiles).
  // Its order is not the registry's: list() and sweep() sort what they return.
  using Map = std::unordered_map<WorkerId, Entry, IdHash>;

  // The entry of `id`, created (evicting the least recently seen past the cap) when new; `fresh`
  // says which. Marks it seen at `now` and moves it to the front of recency_.
  Entry& touch(const WorkerId& id, TimePoint now, bool& fresh);
  // Adds an entry's counts to retired_ and drops it.
  Map::iterator retire(Map::iterator it);

  WorkerLimits limits_;
  Map workers_;
  // Every entry of workers_, the one touched last first: the back is the one to evict.
  Recency recency_;
  std::uint64_t evicted_ = 0;
  WorkerView retired_;
};

}  // namespace dtraced::collector
