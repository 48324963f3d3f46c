// GET /v1/workers, and what every lease and tile upload tells the worker registry (workers.h):
// who sent it, the first request of a worker and a worker going quiet (both logged).
#include <algorithm>
#include <chrono>
#include <utility>

#include <boost/beast/core/string.hpp>

#include "collector/handlers.h"
#include "http/server.h"
#include "protocol/worker_messages.h"
#include "util/log.h"

namespace dtraced::collector {
namespace {

// How often the registry is swept for quiet and forgotten workers: at the first request after
// this interval (no timer of its own, so a quiet worker is noticed at most this late after the
// collector next hears from anyone, a Prometheus scrape included).
constexpr Duration kSweepInterval = std::chrono::seconds(5);

std::string_view header_value(const http::Request& req, std::string_view name) {
  const auto it = req.find(boost::beast::string_view(name.data(), name.size()));
  if (it == req.end()) return {};
  return std::string_view(it->value().data(), it->value().size());
}

double seconds(Duration d) { return std::chrono::duration<double>(d).count(); }

// A worker's first request, at info level; at debug level when admitting it evicted another
// (the registry is full: under churn that is once per request), with a throttled warning instead.
void log_first(Context& c, const WorkerId& id, std::string_view isa, std::uint32_t threads, bool evicted) {
  if (evicted) {
    util::log_debug("collector: worker '{}' from {} sent its first request (another worker evicted)", id.name,
                    peer_text(id));
    std::uint64_t held_back = 0;
    if (!c.eviction_log.allow(c.clock.now(), held_back)) return;
    util::log_warn(
        "collector: the worker registry is full ({} workers, --max-workers): the least recently seen worker is "
        "forgotten at each new worker's first request ({} evictions so far, {} since the last such line); raise "
        "--max-workers above the farm's size",
        c.workers.limits().max_workers, c.workers.evicted(), held_back + 1);
    return;
  }
  if (threads == 0) {
    util::log_info("collector: worker '{}' from {} sent its first request", id.name, peer_text(id));
  } else {
    util::log_info("collector: worker '{}' from {} sent its first request ({} threads, isa {})", id.name, peer_text(id),
                   threads, isa.empty() ? "not sent" : isa);
  }
}

}  // namespace

std::string recorded_worker_name(const Principal& who, std::string sent) {
  return who.role == Role::kWorker ? who.name : std::move(sent);
}

std::string peer_text(const WorkerId& id) { return id.peer.empty() ? std::string("an unknown address") : id.peer; }

std::string request_peer(const http::Request& req) {
  const std::string_view peer = header_value(req, http::kPeerHeader);
  return std::string(peer.substr(0, protocol::kMaxPeerBytes));
}

WorkerId worker_id(const http::Request& req, std::string name) { return WorkerId{std::move(name), request_peer(req)}; }

void note_lease_request(Context& c, const http::Request& req, const std::string& name,
                        const protocol::LeaseRequest& lease) {
  const WorkerId id = worker_id(req, name);
  const std::string isa = protocol::parse_isa_header(header_value(req, protocol::kIsaHeader)).value_or("");
  const std::uint64_t evicted = c.workers.evicted();
  if (c.workers.on_lease(id, isa, lease.threads, c.clock.now())) {
    log_first(c, id, isa, lease.threads, c.workers.evicted() != evicted);
  }
}

void note_tile_upload(Context& c, const WorkerId& id, TileOutcome outcome, std::uint64_t rays) {
  const std::uint64_t evicted = c.workers.evicted();
  if (c.workers.on_tile(id, outcome, rays, c.clock.now())) log_first(c, id, {}, 0, c.workers.evicted() != evicted);
}

void note_job_served(Context& c, JobId job) { c.job_served[job] = c.clock.now(); }

protocol::JobStatus with_worker_gap(const Context& c, protocol::JobStatus s) {
  const JobRecord* job = c.find_job(s.id);
  // A paused job has no worker on purpose.
  if (job == nullptr || !job->unfinished() || job->state == protocol::JobState::kPaused) return s;
  const TimePoint now = c.clock.now();
  // Since the later of: this process's start, the job's submission, its last worker.
  const auto age = std::chrono::seconds(std::max<std::int64_t>(0, c.clock.unix_seconds() - job->created_unix));
  TimePoint since = std::max(c.started, now - std::chrono::duration_cast<Duration>(age));
  if (const auto it = c.job_served.find(s.id); it != c.job_served.end()) since = std::max(since, it->second);
  const double gap = seconds(now - since);
  if (gap >= protocol::kNoWorkerAfterS) s.no_worker_s = gap;
  return s;
}

void sweep_workers(Context& c) {
  const TimePoint now = c.clock.now();
  if (c.workers_swept && now - *c.workers_swept < kSweepInterval) return;
  c.workers_swept = now;
  std::erase_if(c.job_served, [&c](const auto& entry) {
    const JobRecord* job = c.find_job(entry.first);
    return job == nullptr || !job->unfinished();
  });
  for (const WorkerId& id : c.workers.sweep(now)) {
    util::log_warn("collector: worker '{}' from {} has gone quiet (no request for {:.0f}s)", id.name, peer_text(id),
                   seconds(c.workers.limits().quiet_after));
  }
}

http::Response list_workers(Context& c) {
  sweep_workers(c);
  protocol::WorkerList list;
  list.recent_window_s = seconds(kRecentWindow);
  list.quiet_after_s = seconds(c.workers.limits().quiet_after);
  for (const WorkerView& v : c.workers.list(c.clock.now())) {
    protocol::WorkerInfo w;
    w.name = v.id.name;
    w.peer = v.id.peer;
    w.isa = v.isa;
    w.threads = v.threads;
    w.quiet = v.quiet;
    w.last_seen_s = seconds(v.since_last_seen);
    w.first_seen_s = seconds(v.since_first_seen);
    w.leases = v.leases;
    w.tiles = v.tiles;
    w.duplicates = v.duplicates;
    w.faulty_duplicates = v.faulty_duplicates;
    w.refused = v.refused;
    w.recent_tiles = v.recent_tiles;
    w.recent_rays = v.recent_rays;
    list.workers.push_back(std::move(w));
  }
  return json_answer(http::Status::ok, protocol::encode(list));
}

std::optional<Refusal> pixel_version_refusal(Context& c, const http::Request& req, bool required) {
  const std::string_view value = header_value(req, protocol::kPixelVersionHeader);
  if (value.empty() && !required) return std::nullopt;
  const std::optional<std::uint32_t> version = protocol::parse_pixel_version_header(value);
  if (version == protocol::kPixelVersion) return std::nullopt;
  ++c.counters.pixel_version_refusals;
  const std::string theirs =
      version ? fmt::format("renders pixel version {}", *version)
              : (value.empty() ? std::string("does not say its pixel version (an older dtraced, or not a worker)")
                               : fmt::format("sent a malformed pixel version '{}'", value.substr(0, 32)));
  return Refusal{http::Status::conflict,
                 util::Error(fmt::format("{}: this worker {}, and this collector's images are rendered with pixel "
                                         "version {}: run the same dtraced release on the collector and its workers",
                                         protocol::kPixelVersionHeader, theirs, protocol::kPixelVersion)),
                 {}};
}

}  // namespace dtraced::collector
