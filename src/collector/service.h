// dtraced::collector service: the collector daemon, wired together.
//
// Owns: the collector's Context (context.h: one io_context, the event loop, and everything that
// lives on it: the WorkQueue, the job table, the HTTP server, the metrics counters; beside the
// loop a store::TileWriter, SQLite on its own thread, a second SQLite connection used from the
// thread pool, and a small thread pool for CPU work), and the entry points around it. The work is
// done by free functions of the Context, one concern a file: restore.h (start-up), admission.h
// and handlers.h (requests), lifecycle.h (finishing and cancelling jobs), stop.h. There is no
// rendering here: the collector never builds a RenderScene.
//
// Construction: create() validates the configuration (every problem, each naming its option)
// before anything else, as Worker::create does; nothing is opened until open().
//
// Time: everything the collector decides in time (job creation and finish times, the ETA, lease
// re-offers, the finish retry, the stop's grace) reads the injected util::Clock and sleeps only
// through async::sleep_until on it. Socket deadlines stay in real time (http/server.h).
//
// Lifecycle: open() (start-up, blocking, before the loop runs) -> listen() -> run() on one
// thread until stop(). run_collector binds first (listen() before open()) when the state
// directory does not exist yet, so a port in use leaves nothing behind; otherwise it locks and
// opens the directory first, so a second collector on it is refused before it takes a port.
// Start-up takes an exclusive lock on the state directory (restore.h: one collector per
// directory; a second one fails to open, naming the directory and the PID holding it), opens the
// database (a bad one stops start-up with a message and is left as it was), increments the start
// counter ("epoch", kept in <state_dir>/collector.epoch), and restores every unfinished job: its
// scene and settings from the store, its stored tiles counted (their pixels stay in the store)
// and put into the queue as already done, so they are never leased again. Jobs whose tiles are all stored but whose
// image was not written get it written. A one-shot job (config.h) is then found by its key and resumed, or stored and
// enqueued. listen() binds, then tells systemd READY=1.
//
// Durability: a job is stored (scene and row, one transaction) before its 201; a tile is
// acknowledged "stored" only after its transaction committed; a job is marked done in the store
// only after its image was renamed into place. Each stored tile records the epoch that
// acknowledged it, in its `worker` column ("epoch=N worker=NAME").
//
// Stop: stop() (any thread; run_collector calls it on SIGINT/SIGTERM through a signal_set on the
// loop) sends STOPPING=1, stops the server gracefully (no new connections; requests in flight
// finish within shutdown_grace), waits for image writes in flight within the same grace (both on
// the clock), drains the TileWriter (everything accepted is committed and answered), closes the
// database, releases the state directory's lock and ends run().
//
// Threading: open(), listen(), run(), handle_sync() and run_until_idle() from one thread, never
// concurrently; handle() on the loop; stop() and port() from any thread.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include <boost/asio/awaitable.hpp>
#include <boost/asio/io_context.hpp>

#include "collector/config.h"
#include "collector/metrics.h"
#include "http/types.h"
#include "util/clock.h"
#include "util/result.h"

namespace dtraced::collector {

struct Context;

class Collector {
 public:
  // A collector for `config`, or every problem check_collector_config finds in it (each Error's
  // path names the option). `clock` must outlive the collector.
  static util::Result<std::unique_ptr<Collector>, util::Errors> create(CollectorConfig config,
                                                                       const util::Clock& clock = util::real_clock());
  ~Collector();
  Collector(const Collector&) = delete;
  Collector& operator=(const Collector&) = delete;

  // Start-up (see the top of this file); the error is a message for the operator. Blocking; call
  // once, before anything else.
  util::Status open();

  // Binds and listens, then sends READY=1. Does nothing when the collector is already stopping
  // (a one-shot job that was finished before this start). May be called once before open() too:
  // it then only binds (requests wait until run()), and the call after open() sends READY=1.
  util::Status listen();

  // Runs the loop on the calling thread until the stop sequence has ended. The exit code: 0, or
  // 1 when the one-shot job of an exit_when_done collector was cancelled.
  int run();

  // Begins the graceful stop. Any thread, any number of times.
  void stop();

  // The bound port once listen() succeeded (the real one when port 0 was asked for), else 0.
  std::uint16_t port() const;

  // The request handler the server calls, on the loop.
  boost::asio::awaitable<http::Response> handle(http::Request req);

  // For tests and tools, while run() is not running and nothing listens: answers one request by
  // running the loop on the calling thread until it is idle, so background work the request
  // started (an image being written) is over too.
  http::Response handle_sync(http::Request req);
  void run_until_idle();

  // The CA that workers must trust (TLS wiring): GET /v1/ca answers `ca_pem`, and join codes
  // carry `fingerprint` (SHA-256 of the CA certificate's DER bytes). Without a call (plain HTTP)
  // GET /v1/ca is 404 and join codes have an empty fingerprint. Call before run().
  void set_certificate_authority(std::string ca_pem, std::optional<std::array<std::uint8_t, 32>> fingerprint);

  // A snapshot of every metric, as GET /metrics shows it. On the loop, or while it does not run.
  MetricsSnapshot metrics() const;

  boost::asio::io_context& io_context();

 private:
  explicit Collector(std::unique_ptr<Context> context);
  util::Status bind();
  std::unique_ptr<Context> context_;
  bool ready_ = false;  // READY=1 sent
};

// The collector role, blocking: open, listen, run until SIGINT or SIGTERM (or the one-shot job is
// written), stop. Logs every failure; returns the process exit code (0 on a clean stop).
int run_collector(const CollectorConfig& config);

}  // namespace dtraced::collector
