// dtraced::cli client verbs: submit, list, status, fetch, cancel, priority, requeue and workers,
// spoken to a collector over its HTTP API, plain or TLS (one blocking request at a time on a
// private io_context; the requests of one verb share a kept-alive connection). Results go to
// stdout, diagnostics to stderr; each function returns the process exit code (0 ok, 1 failed).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <utility>

#include "scene/overrides.h"
#include "util/result.h"

namespace dtraced::cli {

struct ClientArgs {
  std::string collector = "http://127.0.0.1:7878";
  std::string token_file;  // empty: no Authorization header
  // PEM file of the CA the collector's certificate must chain to; required for an https://
  // collector, unused for http://.
  std::string ca_file;
  std::uint32_t timeout_ms = 30000;
};

struct SubmitArgs {
  std::string scene;
  std::string output;  // empty: the collector picks job-<id>.png
  std::int32_t priority = 0;
  scene::Overrides overrides;  // of the scene's render block, plus tile size and PNG bit depth
  // Send each tile's estimated cost (render/cost_map.h) so the collector leases the costliest
  // tiles first; false (--no-cost-pass) leaves them in row order.
  bool cost_pass = true;
};
int run_submit(const ClientArgs& client, const SubmitArgs& args);

struct ListArgs {
  bool json = false;
  std::string state;        // empty: every state; else queued, rendering, paused, done or cancelled
  std::uint32_t limit = 0;  // 0: as many as the collector lists; else the newest `limit`
};
int run_list(const ClientArgs& client, const ListArgs& args);

struct StatusArgs {
  std::uint64_t id = 0;
  bool json = false;  // print the status as JSON (machine-readable)
  bool wait = false;  // poll until the job is done or cancelled (a progress bar on a terminal)
  std::uint32_t poll_ms = 500;
  // With --wait: how long an unreachable or restarting collector (no answer, or 503) is retried,
  // with backoff, before giving up; 0 gives up at the first failure.
  std::uint32_t retry_for_s = 300;
};
int run_status(const ClientArgs& client, const StatusArgs& args);

// The job's image (partial while it renders) into `output`; with `frame`, that frame of a
// sequence (without it, the frame being rendered).
int run_fetch(const ClientArgs& client, std::uint64_t id, const std::string& output,
              std::optional<std::uint32_t> frame = std::nullopt);

int run_cancel(const ClientArgs& client, std::uint64_t id);

// Sets a job's priority (higher runs first); prints its status.
int run_priority(const ClientArgs& client, std::uint64_t id, std::int32_t priority);

// Puts a cancelled job back in the queue, keeping its stored tiles; prints its status.
int run_requeue(const ClientArgs& client, std::uint64_t id);

// The collector's workers (GET /v1/workers): aligned columns, or the JSON answer with `json`.
int run_workers(const ClientArgs& client, bool json);

// Pauses (or with pause = false resumes) a job; prints its status.
int run_pause(const ClientArgs& client, std::uint64_t id, bool pause);

// Deletes a done or cancelled job and its stored tiles, and with `delete_image` its image file;
// prints what was removed. Exit 1 when the image could not be removed (the job is gone anyway).
int run_delete(const ClientArgs& client, std::uint64_t id, bool delete_image);

// Reads a bearer token from a file: the first line, without surrounding whitespace; empty or
// over 4096 bytes is an error (its message names the file).
util::Result<std::string> read_token_file(const std::string& path);

}  // namespace dtraced::cli
