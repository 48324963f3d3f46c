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
// Thread safety: plain values and a pure function.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "collector/queue.h"
#include "http/server.h"
#include "store/tile_writer.h"

namespace dtraced::collector {

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
  std::uint64_t restored_tile_leases = 0;
  std::uint64_t restored_tile_submissions = 0;
  std::uint64_t auth_failures = 0;  // 401
  std::uint64_t store_busy = 0;     // 503 because the store's queue was full or a write failed
  std::uint64_t images_written = 0;
  std::uint64_t image_write_failures = 0;
};

struct MetricsSnapshot {
  std::int64_t epoch = 0;
  std::uint64_t restored_tiles = 0;
  // Jobs by protocol::JobState, in enum order (queued, rendering, done, cancelled).
  std::array<std::uint64_t, 4> jobs_by_state{};
  CollectorCounters counters;
  QueueStats queue;
  http::ServerMetrics http;
  store::WriterStats store;
};

// Prometheus text exposition format 0.0.4, every metric with HELP and TYPE lines.
std::string format_metrics(const MetricsSnapshot& m);

// The Content-Type of format_metrics' output.
inline constexpr std::string_view kMetricsContentType = "text/plain; version=0.0.4; charset=utf-8";

}  // namespace dtraced::collector
