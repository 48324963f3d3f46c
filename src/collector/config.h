// dtraced::collector configuration: everything a collector process is started with.
//
// Owns: the option values the CLI fills in (from flags and the --config file) and their
// validation. Plain values; check_collector_config is a pure function: thread-safe.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "collector/queue.h"
#include "collector/tls_setup.h"
#include "collector/workers.h"
#include "http/server.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "store/tile_writer.h"
#include "util/result.h"

namespace dtraced::collector {

// Bounds on the configuration itself.
inline constexpr std::size_t kMaxTokenBytes = 4096;
inline constexpr std::size_t kMaxCpuThreads = 256;
inline constexpr std::chrono::milliseconds kMaxShutdownGrace{10 * 60 * 1000};
// Unfinished jobs (queued or rendering) at once; a submission past this gets 503.
inline constexpr std::size_t kDefaultMaxUnfinishedJobs = 1000;
// Pixels of unfinished jobs at once (2^28: one 16384^2 image). The pixels are in the store (12
// bytes a pixel on disk), not in memory: an image is assembled from it a frame at a time on the
// thread pool. This bounds the work the collector holds and the per-tile state of its queue.
inline constexpr std::uint64_t kDefaultMaxUnfinishedPixels = std::uint64_t{1} << 28;
// Bytes of the frames assembled from the store at once (written, served or put into a GIF), 12 a
// pixel: by default one frame of kDefaultMaxUnfinishedPixels (3 GiB), or many smaller ones. A
// frame larger than the budget is still assembled, alone. Without it the bound was the thread
// pool's size times the largest frame.
inline constexpr std::uint64_t kDefaultImageMemoryBytes = kDefaultMaxUnfinishedPixels * 12;

// The seed's one-shot use: `dtraced --role collector --scene S --output O` enqueues this job at
// start. A restart with the same arguments finds the job by a key derived from them (the scene's
// digest, the effective settings, the tile size and the output name) and resumes it.
struct OneShotJob {
  std::string scene_path;  // a scene file, loaded with the scene loader's limits
  // A plain file name written under output_dir (protocol::check_output_name); the CLI splits a
  // path given on the command line into output_dir and this name.
  std::string output;
  // Of the scene's render block, the tile size and the PNG bit depth, as in a job submission
  // (checked with the scene, by the job decoder, at start).
  scene::Overrides overrides;
  std::int32_t priority = 0;
};

struct CollectorConfig {
  std::string listen_address = "127.0.0.1";  // an IPv4 or IPv6 address, not a name
  std::uint16_t port = 7878;                 // 0: any free port (tests; see Collector::port())
  std::string state_dir;                     // holds dtraced.db and collector.epoch; required
  std::string output_dir;                    // finished images; empty means state_dir/output
  std::string token;                         // the bearer token itself (the CLI reads it from a file)
  // Connection limits and deadlines. max_body_bytes caps every route's own limit (tile payloads
  // protocol::kMaxTilePayloadBytes, job submissions protocol::kMaxJobSubmitBytes, other bodies
  // protocol::kMaxMessageBytes); the server is given the largest route limit under that cap.
  http::ServerLimits limits;
  QueueConfig queue;
  store::WriterLimits writer;
  std::chrono::milliseconds shutdown_grace{10000};  // for requests and image writes in flight
  std::size_t cpu_threads = 2;                      // image encoding, scene parsing, large payloads
  std::size_t max_unfinished_jobs = kDefaultMaxUnfinishedJobs;
  std::uint64_t max_unfinished_pixels = kDefaultMaxUnfinishedPixels;
  std::uint64_t image_memory_bytes = kDefaultImageMemoryBytes;

  // The worker registry's limits (a stopped worker shows quiet, then leaves the list).
  WorkerLimits workers;
  // Serve the web page (`/` and `/ui/...`); --no-web-ui turns them all into 404.
  bool web_ui = true;
  // HTTPS (tls_setup.h; the CLI decides `enabled` from --tls and the listen address).
  TlsSettings tls;

  std::optional<OneShotJob> one_shot;
  // With one_shot: stop and exit 0 once that job's image is written (at once if it already was).
  bool exit_when_done = false;

  // output_dir, or state_dir/output when it is empty.
  std::string effective_output_dir() const;
};

// Name of the start counter's file in the state directory.
inline constexpr std::string_view kEpochFileName = "collector.epoch";

// Every problem of the configuration, none when it is usable; each Error's path names the option
// ("token", "limits.read_timeout") and its message what is wrong.
util::Errors check_collector_config(const CollectorConfig& config);

}  // namespace dtraced::collector
