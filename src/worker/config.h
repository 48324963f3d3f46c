// dtraced::worker configuration: what a worker daemon is told, its defaults and its limits.
//
// Owns: the worker's options as plain values, their validation (every problem named by its field:
// util::Error::path is the option's name in WorkerConfig) and the defaults that depend on the host (name, thread
// count). The command line fills a WorkerConfig from flags and a JSON file; the Worker takes a validated one.
//
// Stateless functions over values: thread-safe.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <random>
#include <string>

#include "accel/isa.h"
#include "http/client.h"
#include "util/result.h"

namespace dtraced::worker {

// ---- limits --------------------------------------------------------------------------------

inline constexpr std::size_t kMaxTokenBytes = 4096;
inline constexpr std::uint32_t kMaxSceneCache = 1024;        // scenes kept built in memory
inline constexpr std::size_t kMaxSceneCacheDirBytes = 4096;  // the length of scene_cache_dir (a path)
inline constexpr std::chrono::seconds kMaxGrace{3600};
inline constexpr std::chrono::milliseconds kMaxClientTimeout{10 * 60 * 1000};
inline constexpr std::chrono::milliseconds kMaxBackoff{10 * 60 * 1000};
// A slot holds up to two tiles (one rendering, the next leased), so the default leaves room for
// 14 more per thread waiting for their acknowledgement before leasing pauses. Small tiles need
// that many: a 32-px tile of a small frame renders in 1-2 ms, while its acknowledgement waits for
// a durable commit (an fsync, 4-10 ms on a VM's disk) plus a round trip; with 4 per thread the
// threads of a farm on one 2-core machine sat idle a third of the time
// (tests/bench/frames_farm_vs_local.sh).
inline constexpr std::uint32_t kInHandPerThread = 16;
// Whatever max_unacknowledged says, leasing also pauses while the rendered tiles awaiting their
// acknowledgement hold this many bytes of payload per render thread: about four of the largest
// tiles (protocol::kMaxTilePayloadBytes), what the earlier default of 4 tiles per thread allowed.
inline constexpr std::uint64_t kHeldBytesPerThread = std::uint64_t{64} << 20;
inline constexpr std::uint32_t kMaxUnacknowledged = 1u << 16;
// A CA file holds a few certificates; anything this large is the wrong file.
inline constexpr std::uint64_t kMaxCaFileBytes = 1 << 20;
// Idle kept-alive connections to the collector: two per render thread (a lease and a submission
// each), within these bounds.
inline constexpr std::size_t kMinIdleConnections = 4;
inline constexpr std::size_t kMaxIdleConnections = 64;
// Bounds of exit_when_idle and max_runtime: a month and a year.
inline constexpr std::chrono::seconds kMaxExitWhenIdle{30 * 24 * 3600};
inline constexpr std::chrono::seconds kMaxRuntime{366 * 24 * 3600};
// Bound of start_jitter: an hour.
inline constexpr std::chrono::milliseconds kMaxStartJitter{3600 * 1000};

// ---- configuration -------------------------------------------------------------------------

struct WorkerConfig {
  std::string collector_url;  // http(s)://host[:port] (http::parse_base_url)
  // PEM file of the CA the collector's certificate must chain to (its state directory's
  // tls/ca.pem, or the operator's --tls-ca); required for an https:// collector_url, read by
  // Worker::create (load_client_tls). Unused for http://.
  std::string ca_file;
  std::string token;  // bearer token: 1..kMaxTokenBytes visible ASCII characters, no spaces
  // Sent with every lease request; the collector logs it. Empty: default_worker_name().
  // Otherwise 1..protocol::kMaxWorkerNameBytes printable ASCII characters.
  std::string name;
  // Render threads; 0: the CPUs this process may run on (util::usable_cpus(): its affinity mask,
  // which a Slurm allocation, a cpuset or taskset narrows). At most protocol::kMaxWorkerThreads.
  std::uint32_t threads = 0;
  std::uint32_t scene_cache = 8;  // built scenes kept (least recently used evicted); [1, kMaxSceneCache]
  // Where static scenes are kept on disk in their render-ready binary form, by digest
  // (scene_cache.h, write_cached_scene), so that a restarted worker or the next job of the same
  // scene skips fetching and parsing its JSON. Empty: nowhere. Created at start when missing.
  // Holds at most scene_cache files (the least recently used are removed).
  std::string scene_cache_dir;
  // Instruction set of the traversal kernels; one of accel::supported_isas(). Every choice
  // renders the same bits, so workers of one farm may differ.
  accel::Isa isa = accel::best_isa();
  // After SIGTERM/SIGINT: how long to keep submitting what is in hand before abandoning it.
  std::chrono::seconds grace{60};  // [0, kMaxGrace]
  http::ClientTimeouts timeouts;   // each in [1 ms, kMaxClientTimeout]
  // Retry delays after a failed request: full jitter in [0, min(max, initial x 2^n)].
  std::chrono::milliseconds backoff_initial{100};  // > 0
  std::chrono::milliseconds backoff_max{10'000};   // [backoff_initial, kMaxBackoff]
  // Tiles in hand at once: lease requests in flight, leases held, tiles rendering, and rendered
  // tiles not yet acknowledged. At the bound the worker stops leasing until acknowledgements come
  // in; so it is also a bound on the pixels held in memory (kHeldBytesPerThread is the other).
  // 0: kInHandPerThread x threads.
  // Below 2 x threads some render threads wait while the collector is slow. [0, kMaxUnacknowledged]
  std::uint32_t max_unacknowledged = 0;
  // Seed of the retry jitter; 0: drawn from std::random_device (so that workers started together
  // do not retry together). Tests fix it.
  std::uint64_t jitter_seed = 0;
  // Stop (submitting what is in hand, then exiting 0) when the collector answers a lease request
  // "finished" (protocol::kFinishedHeader: a one-shot collector whose job has ended, going away).
  // Off: such an answer is a "retry after" like any other, and the worker waits for a collector
  // at that address for as long as it runs.
  bool exit_when_done = false;
  // For batch jobs (docs/scale-out.md), both 0 (off) by default; each stop is the drain of a
  // SIGTERM (no more leases, what is in hand rendered and submitted within `grace`), then exit 0.
  // exit_when_idle: stop once the collector has had no work for this worker for this long (every
  // lease answered "retry after" since, and nothing rendering or awaiting acknowledgement), so
  // an allocation is given back when the render is done. [0, kMaxExitWhenIdle]
  std::chrono::seconds exit_when_idle{0};
  // max_runtime: stop this long after the start, so that max_runtime + grace fits a fixed
  // allocation. [0, kMaxRuntime]
  std::chrono::seconds max_runtime{0};
  // Before its first request the worker waits a random time in [0, start_jitter] (drawn from
  // the jitter generator above: jitter_seed, else std::random_device), so that a farm started
  // at once (a pdsh loop, a restart of every host) does not reach the collector at once: each
  // new connection costs the collector a TLS handshake (docs/scale-out.md). A stop during the
  // wait ends it at once (nothing is in hand yet). 0: no wait. [0, kMaxStartJitter]
  std::chrono::milliseconds start_jitter{0};
};

// Looks up an environment variable: its value, or null when it is not set.
using EnvLookup = std::function<const char*(const char*)>;

// The process's environment (std::getenv).
const char* process_env(const char* name);

// "HOST-PID", or under Slurm "HOST-JOB_TASK" for a task of a job array (SLURM_ARRAY_JOB_ID,
// SLURM_ARRAY_TASK_ID) and "HOST-JOB" for another job (SLURM_JOB_ID), with ".STEP_TASK"
// (SLURM_PROCID) when the job step runs more than one task (SLURM_NTASKS > 1); so that the tasks
// of an array tell apart in the collector's worker list. Reduced to printable ASCII and to the
// protocol's name length (the host name is shortened first).
std::string default_worker_name(const EnvLookup& env = process_env);

// Every problem with `config`, each an Error whose path is the field named as in WorkerConfig (e.g.
// "collector_url", "timeouts.connect"), so that to_string() reads "field: problem"; empty when it
// is valid.
util::Errors validate(const WorkerConfig& config);

// What the worker trusts for an https:// collector_url: ca_file read and checked (an Error whose
// file is ca_file and whose path is "ca_file" says what is wrong); nullopt for http://. Requires
// validate(config) to be empty.
util::Result<std::optional<http::ClientTls>> load_client_tls(const WorkerConfig& config);

// The options of the worker's one http::Client: its timeouts, `tls`, and a pool sized for
// `config.threads` (resolved).
http::ClientOptions client_options(const WorkerConfig& config, std::optional<http::ClientTls> tls);

// The wait before the first request: uniform in [0, max] ms, drawn from `rng`; 0 when max is 0.
std::chrono::milliseconds start_delay(std::chrono::milliseconds max, std::mt19937_64& rng);

// `config` with its host-dependent defaults filled in: name, threads, max_unacknowledged.
// Requires validate(config) to be empty.
WorkerConfig resolve_defaults(WorkerConfig config);

}  // namespace dtraced::worker
