#include "collector/metrics.h"

#include <iterator>

#include <fmt/format.h>

namespace dtraced::collector {
namespace {

class Writer {
 public:
  template <typename T>
  void one(std::string_view name, std::string_view type, std::string_view help, T value) {
    header(name, type, help);
    fmt::format_to(std::back_inserter(out_), "{} {}\n", name, value);
  }
  void header(std::string_view name, std::string_view type, std::string_view help) {
    fmt::format_to(std::back_inserter(out_), "# HELP {} {}\n# TYPE {} {}\n", name, help, name, type);
  }
  template <typename T>
  void labelled(std::string_view name, std::string_view label, std::string_view label_value, T value) {
    fmt::format_to(std::back_inserter(out_), "{}{{{}=\"{}\"}} {}\n", name, label, label_value, value);
  }
  std::string take() { return std::move(out_); }

 private:
  std::string out_;
};

}  // namespace

std::string format_metrics(const MetricsSnapshot& m) {
  Writer w;
  const CollectorCounters& c = m.counters;
  w.one("dtraced_collector_epoch", "gauge", "Which start of the collector on this state directory this is.", m.epoch);
  w.one("dtraced_restored_tiles", "gauge", "Tiles of unfinished jobs already stored when this process started.",
        m.restored_tiles);
  w.one("dtraced_restored_tile_leases_total", "counter",
        "Leases of tiles that were already stored at start (must stay 0).", c.restored_tile_leases);
  w.one("dtraced_restored_tile_submissions_total", "counter",
        "Uploads of tiles that were already stored at start (answered already_done).", c.restored_tile_submissions);

  w.header("dtraced_jobs", "gauge", "Jobs known to the collector, by state.");
  constexpr std::string_view kStates[] = {"queued", "rendering", "done", "cancelled"};
  for (std::size_t i = 0; i < m.jobs_by_state.size(); ++i)
    w.labelled("dtraced_jobs", "state", kStates[i], m.jobs_by_state[i]);
  w.one("dtraced_jobs_submitted_total", "counter", "Jobs accepted by POST /v1/jobs.", c.jobs_submitted);
  w.one("dtraced_jobs_cancelled_total", "counter", "Jobs cancelled.", c.jobs_cancelled);
  w.one("dtraced_images_written_total", "counter", "Finished images written to the output directory.",
        c.images_written);
  w.one("dtraced_image_write_failures_total", "counter", "Attempts to write a finished image that failed.",
        c.image_write_failures);

  w.one("dtraced_tiles_stored_total", "counter", "Tiles durably stored and acknowledged by this process.",
        c.tiles_stored);
  w.one("dtraced_tile_duplicates_total", "counter", "Tile uploads answered already_done.", c.tile_duplicates);
  w.one("dtraced_faulty_results_total", "counter", "Duplicate tiles whose pixels differ from the stored ones.",
        c.faulty_results);
  w.one("dtraced_tiles_refused_total", "counter", "Tile uploads refused with 400.", c.tiles_refused);
  w.one("dtraced_tiles_job_gone_total", "counter", "Tile uploads answered job_gone.", c.tiles_job_gone);

  w.one("dtraced_leases_total", "counter", "Tiles leased to workers.", m.queue.leases);
  w.one("dtraced_reoffers_total", "counter", "Leases of a tile that had been leased before.", m.queue.reoffers);
  w.one("dtraced_lease_retry_total", "counter", "Lease requests answered with retry_after_ms.", c.lease_retries);
  w.one("dtraced_active_jobs", "gauge", "Jobs with tiles left to lease or store.", m.queue.active_jobs);

  w.one("dtraced_http_requests_total", "counter", "HTTP responses sent.", m.http.requests);
  w.header("dtraced_http_responses_total", "counter", "HTTP error responses, by class.");
  w.labelled("dtraced_http_responses_total", "class", "4xx", m.http.responses_4xx);
  w.labelled("dtraced_http_responses_total", "class", "5xx", m.http.responses_5xx);
  w.one("dtraced_http_read_timeouts_total", "counter", "Connections dropped at the read deadline.",
        m.http.read_timeouts);
  w.one("dtraced_http_rejected_connections_total", "counter", "Connections refused over the connection cap.",
        m.http.rejected_connections);
  w.one("dtraced_http_open_connections", "gauge", "Open HTTP connections.", m.http.open_connections);
  w.one("dtraced_http_evicted_connections_total", "counter",
        "Unauthenticated connections closed to make room for a new one.", m.http.evicted_connections);
  w.one("dtraced_http_held_response_bytes", "gauge", "Bytes of large answers waiting for their readers.",
        m.http.held_response_bytes);
  w.one("dtraced_http_refused_large_responses_total", "counter",
        "Large answers replaced by 503 because too many bytes were waiting for slow readers.",
        m.http.refused_large_responses);
  w.one("dtraced_auth_failures_total", "counter", "Requests refused for a missing or wrong token.", c.auth_failures);

  w.one("dtraced_store_commit_batches_total", "counter", "Tile transactions attempted by the store writer.",
        m.store.batches);
  w.one("dtraced_store_largest_batch", "gauge", "Most tiles committed in one transaction.", m.store.largest_batch);
  w.one("dtraced_store_write_seconds_total", "counter", "Time spent inside tile transactions.", m.store.write_seconds);
  w.one("dtraced_store_tiles_failed_total", "counter", "Tiles whose transaction failed.", m.store.tiles_failed);
  w.one("dtraced_store_busy_total", "counter", "Requests answered 503 because the store was busy or failing.",
        c.store_busy);
  w.one("dtraced_store_pending_tiles", "gauge", "Tiles waiting for the store writer.", m.store.pending_tiles);
  return w.take();
}

}  // namespace dtraced::collector
