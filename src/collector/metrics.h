// dtraced::collector metrics: the counters behind GET /metrics and their Prometheus text form.
//
// Owns: the names and meanings of every metric the collector exports (all prefixed dtraced_).
// Counters count since this process started, except where a name says otherwise. The crash-test
// figures:
//   dtraced_collector_epoch            which start of the collector this is (1, 2, ...)
//   dtraced_restored_tiles             tiles of unfinished jobs already stored at this start
//   dtraced_restored_tile_leases_total leases of such tiles in this process: 0 by construction,
//                                      measured so an end-to-end test can assert that no tile
//                                      acknowledged before a crash is handed out again
//   dtraced_restored_tile_submissions_total  uploads of such tiles (a worker retrying a result
//                                      whose acknowledgement the crash swallowed): answered
//                                      "already_done", nothing rendered
//
// Also: dtraced_build_info, process metrics read from /proc/self (process_start_time_seconds,
// process_resident_memory_bytes, process_open_fds, under the names Prometheus' client libraries
// use), histograms (lease handling time, tile upload size, tile render time as the workers report
// it), and per-worker counters whose label set is bounded: the kMetricsWorkers most recently seen
// workers by name, the rest (and every forgotten one) summed as worker="other".
//
// Roles and enrollment: dtraced_credentials{role} (live credentials), dtraced_enrollments_total,
// dtraced_enroll_failures_total, dtraced_credentials_created_total, dtraced_revocations_total,
// dtraced_role_refusals_total{role} (403: a credential outside its role).
//
// Thread safety: plain values and pure functions (read_process_stats reads /proc/self).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <initializer_list>
#include <string>
#include <string_view>
#include <vector>

#include "collector/credentials.h"
#include "collector/queue.h"
#include "collector/workers.h"
#include "http/server.h"
#include "store/tile_writer.h"

namespace dtraced::collector {

// A Prometheus histogram with fixed upper bounds (at most kMaxBuckets, ascending; +Inf implied).
class Histogram {
 public:
  static constexpr std::size_t kMaxBuckets = 16;
  Histogram(std::initializer_list<double> bounds);
  void observe(double value);
  std::size_t buckets() const { return size_; }
  double bound(std::size_t i) const { return bounds_[i]; }
  // Observations <= bound(i), cumulative as Prometheus writes them.
  std::uint64_t cumulative(std::size_t i) const;
  std::uint64_t count() const { return count_; }
  double sum() const { return sum_; }

 private:
  std::array<double, kMaxBuckets> bounds_{};
  std::array<std::uint64_t, kMaxBuckets> counts_{};  // per bucket; above the last: count_ - sum
  std::size_t size_ = 0;
  std::uint64_t count_ = 0;
  double sum_ = 0;
};

// Owned and updated by the collector's event loop.
struct CollectorCounters {
  std::uint64_t jobs_submitted = 0;
  std::uint64_t jobs_cancelled = 0;
  std::uint64_t tiles_stored = 0;     // acknowledged "stored" (committed by this process)
  std::uint64_t tile_duplicates = 0;  // answered "already_done"
  std::uint64_t faulty_results = 0;   // duplicates whose pixels differ from the stored ones
  std::uint64_t tiles_refused = 0;    // 400: bad payload, wrong rectangle, non-finite pixels
  std::uint64_t tiles_job_gone = 0;   // 410
  std::uint64_t lease_retries = 0;    // "retry after" answers
  std::uint64_t upload_leases = 0;    // tile uploads answered with a verdict that asked for the next lease
  // 409: a lease or a tile of another pixel version (protocol::kPixelVersionHeader).
  std::uint64_t pixel_version_refusals = 0;
  std::uint64_t restored_tile_leases = 0;
  std::uint64_t restored_tile_submissions = 0;
  std::uint64_t auth_failures = 0;                        // 401
  std::uint64_t sign_in_failures = 0;                     // POST /ui/session with a wrong token, or refused (429)
  std::uint64_t focus_requests = 0;                       // POST /ui/api/jobs/{id}/focus answered 200
  std::uint64_t focus_tiles = 0;                          // tiles those requests moved to the front
  std::uint64_t store_busy = 0;                           // 503 because the store's queue was full or a write failed
  std::uint64_t enrollments = 0;                          // POST /v1/enroll answered 201
  std::uint64_t enroll_failures = 0;                      // refused: unknown, used or expired code, or rate-limited
  std::uint64_t credentials_created = 0;                  // POST /v1/credentials answered 201
  std::uint64_t revocations = 0;                          // credentials revoked by this process
  std::array<std::uint64_t, kRoleCount> role_refusals{};  // 403 by the role refused (Role's order)
  std::uint64_t images_written = 0;
  std::uint64_t image_write_failures = 0;
  Histogram lease_seconds{0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 1};
  Histogram tile_upload_bytes{1 << 10, 4 << 10, 16 << 10, 64 << 10, 256 << 10, 1 << 20, 4 << 20, 16 << 20, 64 << 20};
  Histogram tile_render_seconds{0.01, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 60, 300, 1800};
};

// Per-worker series are written for this many workers at most (the most recently seen).
inline constexpr std::size_t kMetricsWorkers = 20;

// What /proc/self says of this process; -1 where it could not be read.
struct ProcessStats {
  double start_time_seconds = -1;  // since the Unix epoch
  double resident_bytes = -1;
  double open_fds = -1;
};
ProcessStats read_process_stats();

// The binary's version and the architecture it was built for.
std::string_view build_version();
std::string_view build_isa();

struct MetricsSnapshot {
  std::int64_t epoch = 0;
  std::uint64_t restored_tiles = 0;
  // Jobs by protocol::JobState, in enum order (queued, rendering, done, cancelled, paused).
  std::array<std::uint64_t, 5> jobs_by_state{};
  std::array<std::uint64_t, kRoleCount> credentials_by_role{};  // live ones (operator: always 0)
  CollectorCounters counters;
  QueueStats queue;
  http::ServerMetrics http;
  store::WriterStats store;
  ProcessStats process;
  std::vector<WorkerView> workers;  // most recently seen first
  WorkerView retired_workers;       // counts of forgotten workers
  std::uint64_t workers_evicted = 0;
};

// Prometheus text exposition format 0.0.4, every metric with HELP and TYPE lines.
std::string format_metrics(const MetricsSnapshot& m);

// The Content-Type of format_metrics' output.
inline constexpr std::string_view kMetricsContentType = "text/plain; version=0.0.4; charset=utf-8";

}  // namespace dtraced::collector
