#include "collector/metrics.h"

#include <unistd.h>

#include <algorithm>
#include <cassert>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>

#include <fmt/format.h>

#include "protocol/messages.h"

#ifndef DTRACED_VERSION
#define DTRACED_VERSION "unknown"
#endif
#ifndef DTRACED_BUILD_ISA
#define DTRACED_BUILD_ISA "unknown"
#endif

namespace dtraced::collector {
namespace {

// Open descriptors are counted up to this (a runaway leak still reads as "at least this many").
constexpr std::size_t kMaxCountedFds = 1 << 20;

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
  // One series with any labels, already formatted as `a="x",b="y"`.
  template <typename T>
  void series(std::string_view name, std::string_view labels, T value) {
    fmt::format_to(std::back_inserter(out_), "{}{{{}}} {}\n", name, labels, value);
  }
  void histogram(std::string_view name, std::string_view help, const Histogram& h) {
    header(name, "histogram", help);
    for (std::size_t i = 0; i < h.buckets(); ++i) {
      fmt::format_to(std::back_inserter(out_), "{}_bucket{{le=\"{}\"}} {}\n", name, h.bound(i), h.cumulative(i));
    }
    fmt::format_to(std::back_inserter(out_), "{}_bucket{{le=\"+Inf\"}} {}\n{}_sum {}\n{}_count {}\n", name, h.count(),
                   name, h.sum(), name, h.count());
  }
  std::string take() { return std::move(out_); }

 private:
  std::string out_;
};

// A label value as the exposition format wants it: backslash, quote and newline escaped.
std::string label_value(std::string_view v) {
  std::string out;
  out.reserve(v.size());
  for (const char c : v) {
    if (c == '\\' || c == '"') out += '\\';
    if (c == '\n') {
      out += "\\n";
      continue;
    }
    out += c;
  }
  return out;
}

std::string read_small_file(const char* path) {
  std::ifstream in(path);
  std::string text;
  std::getline(in, text, '\0');
  return text.substr(0, 64 << 10);
}

// The per-worker counters: the kMetricsWorkers most recently seen by "name@peer", the rest summed
// as worker="other" (with the forgotten ones, so that "other" never goes down).
void write_workers(Writer& w, const MetricsSnapshot& m) {
  std::size_t active = 0;
  for (const WorkerView& v : m.workers) active += v.quiet ? 0 : 1;
  w.header("dtraced_workers", "gauge", "Workers the collector remembers, by state (quiet: unseen for a while).");
  w.labelled("dtraced_workers", "state", "active", active);
  w.labelled("dtraced_workers", "state", "quiet", m.workers.size() - active);
  w.one("dtraced_workers_evicted_total", "counter", "Workers forgotten early to keep the registry under its cap.",
        m.workers_evicted);

  struct Family {
    std::string_view name;
    std::string_view help;
    std::uint64_t WorkerView::*field;
  };
  constexpr Family kFamilies[] = {
      {"dtraced_worker_leases_total", "Leases given to each worker (the most recent ones; the rest as other).",
       &WorkerView::leases},
      {"dtraced_worker_tiles_total", "Tiles stored from each worker (the most recent ones; the rest as other).",
       &WorkerView::tiles},
      {"dtraced_worker_faulty_duplicates_total",
       "Duplicate tiles from each worker whose pixels differed (the most recent ones; the rest as other).",
       &WorkerView::faulty_duplicates},
  };
  const std::size_t named = std::min(m.workers.size(), kMetricsWorkers);
  for (const Family& f : kFamilies) {
    w.header(f.name, "counter", f.help);
    for (std::size_t i = 0; i < named; ++i) {
      const WorkerView& v = m.workers[i];
      w.series(f.name, fmt::format("worker=\"{}\"", label_value(v.id.name + "@" + v.id.peer)), v.*f.field);
    }
    std::uint64_t other = m.retired_workers.*f.field;
    for (std::size_t i = named; i < m.workers.size(); ++i) other += m.workers[i].*f.field;
    w.series(f.name, "worker=\"other\"", other);
  }
}

void write_process(Writer& w, const MetricsSnapshot& m) {
  w.series("dtraced_build_info",
           fmt::format("version=\"{}\",isa=\"{}\"", label_value(build_version()), label_value(build_isa())), 1);
  const ProcessStats& p = m.process;
  if (p.start_time_seconds >= 0) {
    w.one("process_start_time_seconds", "gauge", "Start time of the process since the Unix epoch in seconds.",
          p.start_time_seconds);
  }
  if (p.resident_bytes >= 0) {
    w.one("process_resident_memory_bytes", "gauge", "Resident memory size in bytes.", p.resident_bytes);
  }
  if (p.open_fds >= 0) w.one("process_open_fds", "gauge", "Number of open file descriptors.", p.open_fds);
}

}  // namespace

Histogram::Histogram(std::initializer_list<double> bounds) {
  assert(bounds.size() <= kMaxBuckets && std::is_sorted(bounds.begin(), bounds.end()));
  size_ = std::min(bounds.size(), kMaxBuckets);
  std::copy_n(bounds.begin(), size_, bounds_.begin());
}

void Histogram::observe(double value) {
  ++count_;
  sum_ += value;
  const auto it = std::lower_bound(bounds_.begin(), bounds_.begin() + size_, value);  // first bound >= value
  if (it != bounds_.begin() + size_) ++counts_[static_cast<std::size_t>(it - bounds_.begin())];
}

std::uint64_t Histogram::cumulative(std::size_t i) const {
  std::uint64_t sum = 0;
  for (std::size_t j = 0; j <= i && j < size_; ++j) sum += counts_[j];
  return sum;
}

std::string_view build_version() { return DTRACED_VERSION; }
std::string_view build_isa() { return DTRACED_BUILD_ISA; }

ProcessStats read_process_stats() {
  ProcessStats p;
  const long ticks = ::sysconf(_SC_CLK_TCK);
  const long page = ::sysconf(_SC_PAGESIZE);
  // /proc/self/stat: the command name (field 2) may hold spaces and parentheses; fields resume
  // after the last ')'. starttime is field 22: clock ticks after boot.
  const std::string stat = read_small_file("/proc/self/stat");
  const std::size_t close = stat.rfind(')');
  std::uint64_t boot = 0;
  {
    std::istringstream in(read_small_file("/proc/stat"));
    for (std::string key; in >> key;) {
      if (key == "btime") {
        in >> boot;
        break;
      }
    }
  }
  if (close != std::string::npos && ticks > 0 && boot > 0) {
    std::istringstream in(stat.substr(close + 1));
    std::string field;
    for (int i = 3; i <= 22 && in >> field; ++i) {
      if (i == 22) p.start_time_seconds = double(boot) + std::strtod(field.c_str(), nullptr) / double(ticks);
    }
  }
  std::istringstream statm(read_small_file("/proc/self/statm"));
  std::uint64_t size = 0;
  std::uint64_t resident = 0;
  if (page > 0 && statm >> size >> resident) p.resident_bytes = double(resident) * double(page);
  std::error_code ec;
  std::size_t fds = 0;
  for (std::filesystem::directory_iterator it("/proc/self/fd", ec), end; !ec && it != end && fds < kMaxCountedFds;
       it.increment(ec)) {
    ++fds;
  }
  if (!ec) p.open_fds = double(fds);
  return p;
}

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
  for (std::size_t i = 0; i < m.jobs_by_state.size(); ++i) {
    w.labelled("dtraced_jobs", "state", protocol::to_string(static_cast<protocol::JobState>(i)), m.jobs_by_state[i]);
  }
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
  w.one("dtraced_upload_lease_requests_total", "counter",
        "Tile uploads answered with a verdict that asked for the next lease in the same exchange.", c.upload_leases);
  w.one("dtraced_pixel_version_refusals_total", "counter",
        "Leases and tiles refused (409) because the worker renders another pixel version.", c.pixel_version_refusals);
  w.one("dtraced_active_jobs", "gauge", "Jobs with tiles left to lease or store.", m.queue.active_jobs);

  // One family for every response: the server counts all of them and the 4xx and 5xx among them,
  // and sends no 1xx final answers or 3xx, so the rest are 2xx.
  w.header("dtraced_http_responses_total", "counter", "HTTP responses sent, by status class.");
  const std::uint64_t errors = m.http.responses_4xx + m.http.responses_5xx;
  w.labelled("dtraced_http_responses_total", "class", "2xx", m.http.requests >= errors ? m.http.requests - errors : 0);
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
  w.one("dtraced_http_keepalive_reuses_total", "counter",
        "Requests that arrived on a kept-alive connection (not the connection's first).", m.http.keepalive_reuses);
  w.one("dtraced_http_evicted_idle_connections_total", "counter",
        "Idle kept-alive connections closed because more than the idle cap were open.",
        m.http.evicted_idle_connections);
  w.one("dtraced_http_tls_handshakes_total", "counter", "TLS handshakes completed.", m.http.tls_handshakes);
  w.one("dtraced_http_tls_handshake_failures_total", "counter",
        "TLS handshakes refused or failed (garbage, foreign or expired certificate, timeout).",
        m.http.tls_handshake_failures);
  w.one("dtraced_http_plain_on_tls_total", "counter", "Plain HTTP requests refused on the TLS port.",
        m.http.plain_on_tls);
  w.one("dtraced_auth_failures_total", "counter", "Requests refused for a missing or wrong token.", c.auth_failures);
  w.one("dtraced_web_sign_in_failures_total", "counter", "Web page sign-ins refused (wrong token or too many).",
        c.sign_in_failures);
  w.header("dtraced_credentials", "gauge", "Live (not revoked) credentials, by role.");
  for (const Role r : {Role::kViewer, Role::kClient, Role::kWorker}) {
    w.labelled("dtraced_credentials", "role", role_name(r), m.credentials_by_role[static_cast<std::size_t>(r)]);
  }
  w.one("dtraced_enrollments_total", "counter", "Workers enrolled with a join code.", c.enrollments);
  w.one("dtraced_enroll_failures_total", "counter", "Enrollments refused (unknown, used or expired code, or too many).",
        c.enroll_failures);
  w.one("dtraced_credentials_created_total", "counter", "Credentials created by POST /v1/credentials.",
        c.credentials_created);
  w.one("dtraced_revocations_total", "counter", "Credentials revoked.", c.revocations);
  w.header("dtraced_role_refusals_total", "counter", "Requests refused with 403 because of the credential's role.");
  for (const Role r : {Role::kViewer, Role::kClient, Role::kWorker, Role::kOperator}) {
    w.labelled("dtraced_role_refusals_total", "role", role_name(r), c.role_refusals[static_cast<std::size_t>(r)]);
  }
  w.one("dtraced_focus_requests_total", "counter", "Web page requests to render a region of a job first.",
        c.focus_requests);
  w.one("dtraced_focus_tiles_total", "counter", "Tiles moved to the front of their job's queue by those requests.",
        c.focus_tiles);

  w.one("dtraced_store_commit_batches_total", "counter", "Tile transactions attempted by the store writer.",
        m.store.batches);
  w.one("dtraced_store_largest_batch", "gauge", "Most tiles committed in one transaction.", m.store.largest_batch);
  w.one("dtraced_store_write_seconds_total", "counter", "Time spent inside tile transactions.", m.store.write_seconds);
  w.one("dtraced_store_checkpoints_total", "counter",
        "WAL checkpoints attempted by the store writer (each a few fsyncs besides the commits').", m.store.checkpoints);
  w.one("dtraced_store_checkpoints_background_total", "counter",
        "Of those, checkpoints run on the store's checkpoint thread while commits went on.",
        m.store.checkpoints_background);
  w.one("dtraced_store_checkpoints_failed_total", "counter",
        "Checkpoints that failed with an I/O error (retried; no tile is lost).", m.store.checkpoints_failed);
  w.one("dtraced_store_checkpoint_seconds_total", "counter",
        "Time the store writer spent checkpointing or waiting for a checkpoint instead of committing.",
        m.store.checkpoint_seconds);
  // With tiles arriving the writer waits up to 1.5 ms for a batch as large as the last one; many
  // timeouts against waits means it waits for tiles that do not come (acknowledgements pay that).
  w.one("dtraced_store_gather_waits_total", "counter",
        "Tile transactions the store writer delayed to gather a larger batch.", m.store.gather_waits);
  w.one("dtraced_store_gather_timeouts_total", "counter",
        "Of those, the ones whose wait ended before the batch was as large as the last one.", m.store.gather_timeouts);
  w.one("dtraced_store_tiles_failed_total", "counter", "Tiles whose transaction failed.", m.store.tiles_failed);
  w.one("dtraced_store_busy_total", "counter", "Requests answered 503 because the store was busy or failing.",
        c.store_busy);
  w.one("dtraced_store_pending_tiles", "gauge", "Tiles waiting for the store writer.", m.store.pending_tiles);

  w.histogram("dtraced_lease_duration_seconds", "Time the collector took to answer a lease request, in seconds.",
              c.lease_seconds);
  w.histogram("dtraced_tile_upload_bytes", "Size of tile uploads (request bodies), in bytes.", c.tile_upload_bytes);
  w.histogram("dtraced_tile_render_seconds", "Time a tile took to render, as its worker reports it, in seconds.",
              c.tile_render_seconds);
  write_workers(w, m);
  write_process(w, m);
  return w.take();
}

}  // namespace dtraced::collector
