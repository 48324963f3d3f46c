// dtraced::worker daemon: leases tiles from a collector, renders them with every thread, and
// submits the pixels until the collector acknowledges them.
//
// Owns: the worker's whole life (README.md, "HTTP API" for the endpoints it speaks).
//  - Pipeline. One slot per render thread. A slot leases a tile (POST /v1/lease), makes sure the
//    scene it names is built (cache by digest, else GET /v1/scenes/{digest}, verified against
//    the digest, built once and shared), renders it on the render pool (render::render_tile, so
//    the pixels are those of a local render, bit for bit), and hands the result to submission.
//    While a tile renders, its slot already leases the next one, so the threads do not wait on
//    the network between tiles.
//  - Submission. Each rendered tile is PUT to /v1/jobs/{job}/tiles/{tile} (protocol tile payload)
//    and kept until the collector answers: "stored" or "already done" ends it; "job gone" (410)
//    drops it and every other tile and lease of that job; a 4xx saying the tile is bad is logged
//    as the bug it is and dropped. Network errors, 5xx, 401, 408 and 429 are retried with
//    exponential backoff and full jitter, across collector restarts, for as long as it takes.
//  - Back-pressure. At most max_unacknowledged tiles are in hand (lease requests in flight,
//    leases held, tiles rendering, tiles awaiting acknowledgement), and at most
//    kHeldBytesPerThread x threads bytes of rendered tiles await acknowledgement; at either bound
//    the worker stops leasing until acknowledgements come in.
//  - Failures. A collector that is not there yet, restarting, refusing the token (401) or
//    answering 5xx is retried with backoff; while it fails, one request at a time probes it (one
//    for leases, one for submissions), so a farm of waiting workers stays quiet. A worker started
//    before its collector simply waits.
//  - Connections. Every request goes through one http::Client on the event loop: kept-alive
//    connections (two idle per render thread at most), TLS to an https:// collector whose
//    certificate chains to the CA in WorkerConfig::ca_file (read by create()).
//  - Stop (request_stop, or SIGTERM/SIGINT when asked to handle them): no more leases; leases held
//    but not started are dropped (the collector re-offers them); tiles rendering are finished;
//    everything rendered is submitted within the grace period, after which what is left is
//    abandoned and logged. A second signal abandons at once. Counters are logged at exit.
//  - Batch jobs. With exit_when_idle, once every lease answer for that long said "no work" and
//    nothing is rendering or awaiting acknowledgement, the worker stops as after request_stop;
//    with max_runtime it stops that long after its start. Either way run() returns true (exit 0).
//  - Finished collector. With exit_when_done, a lease answer saying the collector has finished all
//    its work and is going away (protocol::kFinishedHeader) is a stop like request_stop: what is
//    in hand is finished and submitted, then run() returns (exit code 0). Without it, that answer
//    is a "retry after" like any other.
//
// Time: the worker reads time only through the util::Clock it is given, and sleeps only through
// async::sleep_until on it: backoff delays, "retry after" waits, the grace period after a stop.
// Tests give it a util::ManualClock and decide when a backoff or a grace period is over. The
// socket deadlines inside http::Client (connect, write, read timeouts) stay in real time: they
// bound what the kernel does with a connection, not a decision of the worker.
//
// Threading: run() turns the calling thread into the worker's event loop (all networking, all
// state) and starts `threads` render threads that only render tiles and build scenes. The worker
// shares nothing with other workers in the process: no global state.
#pragma once

#include <cstdint>
#include <memory>

#include "util/clock.h"
#include "util/result.h"
#include "worker/config.h"

namespace dtraced::worker {

// Counters since construction; a snapshot, each field read atomically (not all together).
struct WorkerStats {
  bool started = false;   // run() is under way: signal handling installed, READY=1 sent
  bool stopping = false;  // a stop was requested
  // The stop came from the collector's "finished" answer (exit_when_done).
  bool collector_finished = false;
  bool stopped_idle = false;     // the stop came from exit_when_idle
  bool stopped_runtime = false;  // the stop came from max_runtime
  std::uint64_t tiles_rendered = 0;
  std::uint64_t tiles_submitted = 0;  // acknowledged: "stored" or "already done"
  std::uint64_t tiles_dropped = 0;    // their job is gone (410, or known gone before submission)
  std::uint64_t tiles_rejected = 0;   // refused as malformed by the collector (a bug somewhere)
  std::uint64_t tiles_abandoned = 0;  // still unacknowledged when the grace period ran out
  std::uint64_t submit_retries = 0;   // failed submissions (the tile is kept and sent again)
  std::uint64_t lease_failures = 0;   // lease requests (or their scene fetch) that failed
  std::uint64_t leases_dropped = 0;   // leases given up unrendered (stop, job gone, bad scene)
  std::uint64_t upload_leases = 0;    // leases that came in the answer to an upload (one request a tile)
  std::uint64_t scenes_fetched = 0;   // scenes fetched, verified and built
  std::uint64_t scenes_rejected = 0;  // fetched scene bodies that failed verification
  std::uint64_t tiles_held = 0;       // now: rendered, awaiting acknowledgement
  std::uint64_t tiles_in_hand = 0;    // now: see max_unacknowledged in config.h
  std::uint64_t tiles_in_hand_peak = 0;
  // Where a tile's time goes besides rendering: the sum over acknowledged tiles of the time from
  // the end of the render to the acknowledgement (so ack_ms / tiles_submitted is the mean submit
  // round trip, durable commit included), and the time render slots waited for room in hand
  // (max_unacknowledged, or kHeldBytesPerThread), summed over slots. A large wait means the
  // threads idle while tiles await acknowledgement: a higher max_unacknowledged would keep them
  // busy.
  std::uint64_t ack_ms = 0;
  std::uint64_t in_hand_wait_ms = 0;
};

struct RunOptions {
  bool stop_on_signals = false;  // SIGTERM and SIGINT request a stop (a second one abandons)
  bool notify_systemd = false;   // sd_notify READY=1 once running, STOPPING=1 on stop
};

class Worker {
 public:
  // A worker for `config`, or every problem validate() finds in it (each Error's path names the
  // option), or the problem with its ca_file (load_client_tls). Host-dependent defaults are
  // resolved here (see config()). `clock` (which must outlive the worker) is all the time the
  // worker reads and sleeps on; see "Time" above.
  static util::Result<std::unique_ptr<Worker>, util::Errors> create(const WorkerConfig& config,
                                                                    const util::Clock& clock = util::real_clock());
  ~Worker();
  Worker(const Worker&) = delete;
  Worker& operator=(const Worker&) = delete;

  // Runs the worker on the calling thread until a stop has been requested and everything in hand
  // is acknowledged or abandoned. At most once per Worker. Returns false when an internal error
  // (logged) ended it rather than a stop.
  bool run(const RunOptions& options = {});

  // Asks run() to stop as described above. Any thread, any time (before run() too); idempotent.
  void request_stop();

  // Any thread.
  WorkerStats stats() const;

  // The configuration with its defaults resolved.
  const WorkerConfig& config() const;

 private:
  struct Impl;
  explicit Worker(std::unique_ptr<Impl> impl);

  std::unique_ptr<Impl> impl_;
};

// The daemon: validates `config` (each problem logged), then runs a Worker with SIGTERM/SIGINT
// handling and systemd notification until it stops. Blocks. Returns the process exit code: 0
// after a stop (a signal, or a finished collector with exit_when_done; even if the grace period
// ran out and tiles were abandoned), 2 when the configuration is invalid, 1 after an internal
// error.
int run_worker(const WorkerConfig& config);

}  // namespace dtraced::worker
