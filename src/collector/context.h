// dtraced::collector context: the collector daemon's state, owned by its event loop.
//
// Owns: one io_context (the event loop) and everything that lives on it: the WorkQueue, the job
// table (jobs.h), the scene texts of unfinished jobs, the HTTP server, the counters. Beside the
// loop: the store writer (store::TileWriter, SQLite on its own thread; results are posted back to
// the loop), the StoreReader (a second connection, used from the thread pool), and a small thread
// pool for CPU work (parsing and digesting submitted scenes, decoding large tile payloads,
// encoding and writing images). Time comes from the injected clock only.
//
// Everything that acts on this state is a free function of a Context&, in a file of its own
// concern: start-up and restore (restore.h), admission and the handlers (admission.h,
// handlers.h), the job lifecycle (lifecycle.h) and the stop sequence (stop.h). None of them
// keeps state of its own, so there is one owner of every piece of mutable state: the loop.
//
// Thread safety: the members belong to the loop's thread, except the immutable ones, `pool` (work
// is posted to it from the loop), `reader` (any thread, locked inside) and `clock` (any thread).
// Before the loop runs (open(), tests between requests), the thread that will run it may use
// them.
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/io_context.hpp>
#include <boost/asio/thread_pool.hpp>

#include "async/async.h"
#include "collector/admission.h"
#include "collector/config.h"
#include "collector/credentials.h"
#include "collector/jobs.h"
#include "collector/linger.h"
#include "collector/metrics.h"
#include "collector/queue.h"
#include "collector/routes.h"
#include "collector/store_reader.h"
#include "collector/workers.h"
#include "http/server.h"
#include "store/tile_writer.h"
#include "util/clock.h"
#include "util/lock_file.h"

namespace dtraced::collector {

struct Context {
  // Requires check_collector_config(config) to be empty.
  Context(CollectorConfig config, const util::Clock& clock);
  ~Context();
  Context(const Context&) = delete;
  Context& operator=(const Context&) = delete;

  JobRecord* find_job(JobId id);
  const JobRecord* find_job(JobId id) const;
  // The shared text of a scene by digest, stored once for every unfinished job that uses it.
  std::shared_ptr<const std::string> intern_scene(const std::string& digest, std::string json);
  std::size_t unfinished_jobs() const;
  std::uint64_t unfinished_pixels() const;
  // Whether writes may be queued: the store writer runs and no stop has begun.
  bool accepting_writes() const { return writer != nullptr && !stopping; }
  MetricsSnapshot metrics() const;

  // Immutable after construction.
  const CollectorConfig config;
  const util::Clock& clock;
  const TokenCheck token;
  std::string output_dir;  // set by open_collector

  // The exclusive lock on the state directory (restore.h), taken by open_collector before the
  // database opens. Declared before everything that uses the directory, so it is released last.
  std::optional<util::LockFile> state_lock;

  // The loop and what lives on it. The io_context is destroyed last but one (see ~Context).
  std::unique_ptr<async::net::io_context> ioc;
  async::net::thread_pool pool;
  std::optional<async::Event> stop_begun;      // set when the stop begins: ends the finish retry's sleep
  async::Event* finish_ended_event = nullptr;  // set when an image write ends, while the stop waits for it
  std::unique_ptr<http::Server> server;
  std::unique_ptr<store::TileWriter> writer;
  store::WriterStats last_writer_stats;  // once the writer is gone
  StoreReader reader;

  WorkQueue queue;
  std::map<JobId, JobRecord> jobs;
  // Canonical scene text by digest, shared by the unfinished jobs that use it.
  std::map<std::string, std::weak_ptr<const std::string>, std::less<>> scenes;
  std::vector<JobId> to_finish;  // found complete at start-up
  std::vector<JobId> to_count;   // finished adaptive jobs whose mean spp is read after start-up
  CollectorCounters counters;
  std::int64_t epoch = 0;
  std::uint64_t restored_tiles = 0;
  std::optional<JobId> one_shot_id;
  std::size_t finishes_in_flight = 0;
  bool retry_armed = false;
  bool opened = false;
  bool stopping = false;
  std::optional<int> exit_code;
  // A finished one-shot collector telling its workers before it stops (stop.h, begin_linger), and
  // what ends its wait early (everyone told, or a stop begun).
  std::optional<FinishedLinger> linger;
  std::optional<async::Event> linger_wake;

  // Who has been asking for work (handlers/workers.cpp) and when it was last swept.
  WorkerRegistry workers;
  std::optional<TimePoint> workers_swept;
  // A full registry evicts a worker at each first request past the cap: one warning a minute
  // (with the count held back) instead of an info line per eviction (handlers/workers.cpp).
  LogThrottle eviction_log{std::chrono::seconds(60)};
  // When a worker last leased or returned a tile of each unfinished job (handlers/workers.cpp),
  // and when this process started: a job's status says when it has had no worker for a minute.
  std::map<JobId, TimePoint> job_served;
  TimePoint started;
  // Refused tokens are logged at most this often (router.cpp).
  LogThrottle auth_failure_log;
  // The web page's sessions and its failed sign-ins (web_session.h).
  SessionStore sessions;
  SignInLimiter sign_ins;

  // Roles and enrollment (credentials.h): every credential (loaded from the store by
  // open_collector, kept in step with it by handlers/credentials.cpp), and failed enrollments
  // (POST /v1/enroll with a wrong, used or expired code), limited like sign-ins.
  CredentialTable credentials;
  SignInLimiter enroll_attempts;
  // The CA that workers trust, set by the wiring before the loop runs (Collector::
  // set_certificate_authority): GET /v1/ca answers ca_pem (404 when empty: plain HTTP), and join
  // codes carry ca_fingerprint (SHA-256 of the CA certificate's DER; none on plain HTTP).
  std::string ca_pem;
  std::optional<CaFingerprint> ca_fingerprint;
};

}  // namespace dtraced::collector
