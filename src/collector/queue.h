// dtraced::collector work queue: which tile a worker gets next, and when a tile is done.
//
// Owns: the scheduling rules of the farm (README.md, "Work queue"), as a pure data structure. No
// sockets, no SQL, no clock reads: every call that depends on time takes `now`, a
// std::chrono::steady_clock time point (monotonic: worker and collector wall clocks may disagree,
// and a lease must not be re-offered because someone set the date), which the collector reads from
// its util::Clock. Tests drive it with a fake clock.
//
// Rules.
//  - Jobs are served by priority (higher first), then by id (lower first: submission order).
//  - Per job, a circular queue of unfinished tiles, in the lease order add_job was given (the
//    costliest tiles of each frame first, collector/jobs.h lease_order), else ascending index
//    (row order). lease() looks at the front tile; if it may be
//    leased it is handed out, otherwise skipped; either way it is rotated to the back. The scan
//    goes on through that job's whole queue, then to the next job; so a lower-priority job gets
//    work while a higher one has only tiles out.
//  - A tile may be leased when it has no lease outstanding, or when its last lease is at least
//    reoffer_bound(job) old AND fewer than max_copies of its leases are outstanding. A lease counts
//    as outstanding until it is copy_expiry_factor x reoffer_bound old: after that its worker is
//    presumed gone; without expiry, a tile whose max_copies holders all died would never be
//    offered again.
//  - reoffer_bound(job) = clamp(factor x p90 of the job's recent lease->result times, floor,
//    ceiling). Those times are measured from the tile's oldest outstanding lease: when several
//    copies were out it is not known which one answered, and overestimating is the safe side
//    (a higher bound means fewer duplicates), while underestimating would feed back (a bound
//    below the true tile time re-offers every tile, and every short measurement lowers it more).
//  - A lease may name its holder (a worker credential's name). release_holder() forgets every
//    outstanding lease of a holder (a revoked worker) and moves those tiles to the front of
//    their jobs' queues, so they are leased again at once, not after the re-offer bound.
//  - A tile leaves the queue only through complete(), which the caller invokes after the pixels
//    are durably stored. The first completion wins (kStored); later ones are kAlreadyDone.
//  - Nothing eligible: lease() suggests when to ask again, the time until the first tile becomes
//    eligible, clamped to [min_retry_after, max_retry_after].
//
// Memory per job: O(tiles) while it runs (a few dozen bytes per tile, at most max_copies lease
// times each) plus a window of window_size durations; O(1) once done or cancelled. lease() costs
// O(1) while a job has tiles never leased (they sit at the front) and at most the queue length
// per job in the tail of a job, when everything left is out.
//
// Thread safety: none. One owner (the collector's event-loop strand) calls everything.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <map>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "util/clock.h"
#include "util/result.h"

namespace dtraced::collector {

// Monotonic time, as util::Clock::now() reads it (the collector's injected clock).
using TimePoint = util::TimePoint;
using Duration = util::SteadyClock::duration;
using JobId = std::uint64_t;
using TileIndex = std::uint32_t;

// Largest job add_job accepts (protocol::kMaxTilesPerJob is the tighter bound on the wire): at
// about 36 bytes a tile, 150 MiB of queue state.
inline constexpr TileIndex kMaxQueueTiles = 1u << 22;

// Upper bounds on the configuration itself (check_queue_config).
inline constexpr std::uint32_t kMaxCopiesLimit = 16;
inline constexpr std::size_t kMaxWindowSize = 4096;
inline constexpr double kMaxReofferFactor = 100;
inline constexpr double kMaxCopyExpiryFactor = 1000;

struct QueueConfig {
  // reoffer_bound = clamp(reoffer_factor x p90 of recent tile times, reoffer_floor, reoffer_ceiling)
  Duration reoffer_floor = std::chrono::seconds(2);
  double reoffer_factor = 3.0;
  // Past this a slow tile is covered anyway: a worker silent for hours is not coming back.
  Duration reoffer_ceiling = std::chrono::hours(6);
  std::uint32_t max_copies = 3;      // outstanding leases per tile, first one included
  double copy_expiry_factor = 10.0;  // a lease stops counting toward max_copies at this x bound
  std::size_t window_size = 64;      // recent tile times kept per job for the p90
  Duration min_retry_after = std::chrono::milliseconds(50);
  // An idle worker asks again at most this much later (--max-idle-wait-ms). It is how long a new
  // job waits for idle workers to notice it (stateless leases have no push), and it bounds what
  // an idle farm costs: N idle workers ask about N / (1.25 x this) times a second. The lease
  // handler shortens it to 5 ms x the workers known (handlers/lease.cpp, idle_wait), so a farm of
  // up to 100 workers waits at most 0.5 s, as before this ceiling was raised from 0.5 s, and one
  // of up to 1,000 polls ~200 times a second in all; 5 s keeps 10,000 idle workers at ~1,600
  // polls a second (~5 % of a core on kept-alive connections at ~32 us a lease) instead of the
  // 16,000 a 0.5 s ceiling made them send, and a new job reaches them within 7.5 s.
  Duration max_retry_after = std::chrono::milliseconds(5000);
};

// Every problem of the configuration, none when it is usable; each Error's path names the field.
util::Errors check_queue_config(const QueueConfig& config);

struct LeaseGrant {
  JobId job = 0;
  TileIndex tile = 0;
  bool operator==(const LeaseGrant&) const = default;
};

struct LeaseResult {
  std::optional<LeaseGrant> grant;
  // When grant is empty: ask again after this long, in [min_retry_after, max_retry_after]
  // (rounded up to whole milliseconds). Zero when a grant is given.
  std::chrono::milliseconds retry_after{0};
};

enum class CompleteResult { kStored, kAlreadyDone, kJobGone };

enum class TileStatus {
  kJobGone,     // unknown, removed or cancelled job
  kNoSuchTile,  // index past the job's last tile
  kPending,     // not stored yet
  kStored,      // a result was stored: a new one is a duplicate
};

struct JobProgress {
  TileIndex tiles_total = 0;
  TileIndex tiles_done = 0;
  std::uint32_t leases_outstanding = 0;  // unexpired leases of unfinished tiles
  bool cancelled = false;
  bool done() const { return tiles_done == tiles_total; }
};

// Totals since construction, for /metrics.
struct QueueStats {
  std::uint64_t leases = 0;      // grants handed out
  std::uint64_t reoffers = 0;    // grants of a tile that had been leased before
  std::uint64_t stored = 0;      // kStored completions
  std::uint64_t duplicates = 0;  // kAlreadyDone completions
  std::size_t active_jobs = 0;   // jobs with unfinished tiles, not cancelled, not paused
};

class WorkQueue {
 public:
  explicit WorkQueue(QueueConfig config = {});  // asserts check_queue_config(config) is empty

  // Adds a job of `tile_count` tiles, or restores one after a restart: `already_stored` tiles
  // (from the store) count as done and are never leased. `skipped` tiles (those outside a
  // cropped job's region) are no part of the job: never leased, not counted in its progress, and
  // tile_status says kNoSuchTile and complete() kJobGone for them while the job runs; the other
  // tiles keep their indices. False, changing nothing, when the id is in use, tile_count is 0 or
  // above kMaxQueueTiles, an index is out of range, a tile is both stored and skipped, every
  // tile is skipped, or `order` is neither empty nor a permutation of [0, tile_count). `order` is
  // the order in which the tiles are first leased (stored and skipped ones are passed over);
  // empty: ascending index.
  bool add_job(JobId job, std::int32_t priority, TileIndex tile_count, std::span<const TileIndex> already_stored = {},
               std::span<const TileIndex> skipped = {}, std::span<const TileIndex> order = {});

  // The next tile to render, or nothing and when to ask again. `holder` names who takes it (a
  // worker credential), "" for nobody in particular.
  LeaseResult lease(TimePoint now, std::string_view holder = {});

  // Forgets the outstanding leases of `holder` and puts their tiles at the front of their jobs'
  // queues, so the next lease() hands them out (no re-offer bound to wait for). Returns how many
  // leases were forgotten. O(tiles of the unfinished jobs). "" releases nothing.
  std::size_t release_holder(std::string_view holder);

  // Records that the tile's pixels are durably stored. Call only after the store committed them.
  // kJobGone for an unknown, removed or cancelled job and for an index out of range.
  CompleteResult complete(JobId job, TileIndex tile, TimePoint now);

  // For duplicate handling before touching the store.
  TileStatus tile_status(JobId job, TileIndex tile) const;

  // True when every tile of a known, not cancelled job is stored.
  bool is_done(JobId job) const;

  // Stops handing out the job's tiles and frees them; later completions get kJobGone. The job
  // stays known (progress() reports it cancelled) until remove_job. False when the job is
  // unknown, already cancelled or done.
  bool cancel(JobId job);

  // Pausing stops handing out the job's tiles; leases already out stay outstanding, and their
  // results complete tiles as usual (the last one completes the job). Resuming puts it back in the
  // order, its leases and re-offer bound as they were. False when the job is unknown, cancelled
  // or already in that state; a done job may be paused (it has nothing left to hand out anyway).
  bool set_paused(JobId job, bool paused);

  // Changes a job's priority; an active job moves to its new place in the order at once. False
  // when the job is unknown.
  bool set_priority(JobId job, std::int32_t priority);
  // Moves those of `tiles` that are unfinished, have no lease outstanding and are part of the job
  // to the front of the job's queue, in the order given (a tile named twice counts once), so the
  // job's next leases are exactly those tiles in that order. Changes order only; other jobs are
  // untouched. Returns how many moved (0 for an unknown, cancelled or done job). O(queue length).
  std::size_t focus(JobId job, std::span<const TileIndex> tiles);

  // Whether the tile of an unfinished job has a lease outstanding (unexpired) at `now`.
  bool has_lease(JobId job, TileIndex tile, TimePoint now) const;

  // Forgets the job entirely (done and written, or cancelled). False when unknown.
  bool remove_job(JobId job);

  std::optional<JobProgress> progress(JobId job, TimePoint now) const;

  // The job's current re-offer bound; the floor for an unknown job.
  Duration reoffer_bound(JobId job) const;

  QueueStats stats() const;
  const QueueConfig& config() const { return config_; }

 private:
  struct OutLease {
    TimePoint at;
    std::uint32_t holder = 0;  // 1 + index in holders_; 0 for none
  };
  struct Tile {
    std::vector<OutLease> leases;  // outstanding (unexpired) leases, oldest first, at most max_copies
    bool stored = false;
    bool ever_leased = false;
    bool skipped = false;  // no part of the job (add_job's `skipped`)
  };

  struct Job {
    std::int32_t priority = 0;
    TileIndex tile_count = 0;   // indices [0, tile_count), skipped ones included
    TileIndex tiles_total = 0;  // tiles of the job: tile_count less the skipped ones
    TileIndex tiles_done = 0;
    bool cancelled = false;
    bool paused = false;
    std::vector<Tile> tiles;  // empty once done or cancelled
    // Unfinished tiles in lease order. A stored tile is dropped when it next reaches the front,
    // not searched for at completion.
    std::deque<TileIndex> ring;
    std::vector<Duration> window;  // recent lease->result times, a ring of window_size
    std::size_t window_next = 0;
    Duration bound{};

    bool done() const { return tiles_done == tiles_total; }
  };

  // Priority descending, then id ascending.
  using OrderKey = std::pair<std::int64_t, JobId>;
  static OrderKey order_key(JobId id, const Job& job) { return {-std::int64_t{job.priority}, id}; }

  Duration lease_lifetime(const Job& job) const;
  // Forgets the tile's leases that no longer count toward max_copies.
  void drop_expired(Tile& tile, const Job& job, TimePoint now) const;
  // How long until `tile` may be leased (<= 0: now). Drops expired leases first.
  Duration until_eligible(Tile& tile, const Job& job, TimePoint now) const;
  void record_duration(Job& job, Duration d);
  void release_tiles(Job& job);

  QueueConfig config_;
  std::map<JobId, Job> jobs_;
  std::set<OrderKey> active_;  // jobs with unfinished tiles, not cancelled, not paused
  // Names of lease holders, interned (at most kMaxHolders; past that, leases name nobody).
  std::vector<std::string> holders_;
  static constexpr std::size_t kMaxHolders = 1 << 16;
  std::uint32_t holder_id(std::string_view holder);
  QueueStats stats_;
};

}  // namespace dtraced::collector
