// dtraced::protocol worker messages: GET /v1/workers, and the headers a worker describes itself
// with.
//
// Owns: the wire form of the collector's worker registry (collector/workers.h) and its limits.
// A worker names itself in kWorkerHeader (messages.h) and the lease request; it also sends its
// instruction set in kIsaHeader and its pixel version in kPixelVersionHeader on lease requests,
// and the time a tile took to render in kRenderMsHeader (and its pixel version) on tile uploads.
// The collector, going away, says so in kFinishedHeader on its lease answers. A worker that
// uploads a tile may ask for its next lease in the same exchange (kNextLeaseHeader): the answer to
// the upload (UploadAnswer) then carries what POST /v1/lease would have answered, so a tile costs
// one request instead of two. Headers rather than
// body fields, so that a peer that does not know them ignores them (an unknown body key is
// refused); the pixel version is the one a collector insists on.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/messages.h"

namespace dtraced::protocol {

// On POST /v1/lease: the worker's instruction set (accel::isa_name), 1..kMaxIsaHeaderBytes of
// [a-z0-9_]. Anything else is ignored by the collector.
inline constexpr std::string_view kIsaHeader = "X-Dtraced-Isa";
inline constexpr std::size_t kMaxIsaHeaderBytes = 16;
// On PUT /v1/jobs/{id}/tiles/{tile}: milliseconds the tile took to render, a decimal integer in
// [0, kMaxRenderMs]. Anything else is ignored by the collector.
inline constexpr std::string_view kRenderMsHeader = "X-Dtraced-Render-Ms";
inline constexpr std::uint64_t kMaxRenderMs = 24ull * 3600 * 1000;
// On a "retry after" answer to POST /v1/lease: "1" when the collector has finished all its work
// and is going away (a one-shot collector with exit_when_done whose job has ended); a worker
// started with exit_when_done then stops. "0" or no header: it has not. Any other value is
// ignored (read as "0"), so a garbled header never ends a worker.
inline constexpr std::string_view kFinishedHeader = "X-Dtraced-Collector-Finished";
// On PUT /v1/jobs/{id}/tiles/{tile}: "the next lease too, please". The value is the worker's
// render thread count, a decimal integer in [1, kMaxWorkerThreads] (LeaseRequest::threads); its
// name is kWorkerHeader's (or its credential's), its instruction set kIsaHeader's, its pixel
// version kPixelVersionHeader's, as on POST /v1/lease. An answer to the upload that is a verdict
// on the tile (stored, already_done, job_gone) then carries UploadAnswer::next, exactly what
// POST /v1/lease would have answered (a lease, or a retry-after with kFinishedHeader when the
// collector is going away); a refused or failed upload (4xx but 410, 5xx) carries none, and
// neither does an answer when the lease itself would have been refused (no pixel version): the
// worker then asks POST /v1/lease. Without the header (older workers) the answer is
// encode(SubmitResult) as before; a garbled value counts as no header.
inline constexpr std::string_view kNextLeaseHeader = "X-Dtraced-Next-Lease";
// On POST /v1/lease (required) and tile uploads: the worker's pixel version, a decimal integer.
// Two builds of the same pixel version give the same bits for the same scene and settings on
// every host and instruction set; a change to the renderer that alters any pixel bumps
// kPixelVersion (tests/test_pixel_version.cpp pins a digest of reference renders to it, so such a
// change cannot land without the bump). The collector leases only to workers of its own pixel
// version and refuses tiles that name another, so a farm in the middle of an upgrade never mixes
// two renderers' pixels in one image.
inline constexpr std::string_view kPixelVersionHeader = "X-Dtraced-Pixel-Version";
inline constexpr std::uint32_t kPixelVersion = 5;
// GET /v1/workers lists at most this many (the collector's registry cap is below it).
inline constexpr std::size_t kMaxListedWorkers = 10'000;
inline constexpr std::size_t kMaxWorkerListBytes = 16 << 20;
// Longest peer address shown (an IPv6 address with scope is under 64).
inline constexpr std::size_t kMaxPeerBytes = 64;

// The instruction set named by a kIsaHeader value, or nullopt when it is not one.
std::optional<std::string> parse_isa_header(std::string_view value);
// The render time named by a kRenderMsHeader value, or nullopt when it is not one.
std::optional<std::uint64_t> parse_render_ms_header(std::string_view value);
// The pixel version named by a kPixelVersionHeader value (1..2^32-1), or nullopt when it is not one.
std::optional<std::uint32_t> parse_pixel_version_header(std::string_view value);
// The thread count named by a kNextLeaseHeader value, or nullopt when it is not one.
std::optional<std::uint32_t> parse_next_lease_header(std::string_view value);
// Whether a kFinishedHeader value says "finished" ("1") or not ("0"); nullopt for anything else.
std::optional<bool> parse_finished_header(std::string_view value);

// The answer to a tile upload that asked for its next lease (kNextLeaseHeader):
// {"result": "stored", "next": {"lease": {...}}} or {..., "next": {"retry_after_ms": N}}; "next"
// is absent when the collector did not lease (an older collector, or a lease it would refuse), and
// the body is then the plain encode(SubmitResult). Status 200, or 410 for job_gone.
struct UploadAnswer {
  SubmitResult result = SubmitResult::kStored;
  std::optional<LeaseReply> next;
  bool operator==(const UploadAnswer&) const = default;
};
std::string encode(const UploadAnswer& m);
// Reads both forms (with and without "next").
Decoded<UploadAnswer> decode_upload_answer(std::string_view body);

struct WorkerInfo {
  std::string name;           // as in LeaseRequest::worker
  std::string peer;           // source address of its requests; "" when unknown
  std::string isa;            // "" when it never sent one
  std::uint32_t threads = 0;  // 0 when it never leased
  bool quiet = false;         // unseen for the collector's quiet interval
  double last_seen_s = 0;     // seconds since its last request
  double first_seen_s = 0;    // seconds since its first request (as far as the collector remembers)
  std::uint64_t leases = 0;
  std::uint64_t tiles = 0;  // stored
  std::uint64_t duplicates = 0;
  std::uint64_t faulty_duplicates = 0;  // duplicates whose pixels differed from the stored ones
  std::uint64_t refused = 0;            // tiles refused with 400
  std::uint64_t recent_tiles = 0;       // stored in the last recent_window_s
  std::uint64_t recent_rays = 0;        // camera rays (samples) of those tiles
  bool operator==(const WorkerInfo&) const = default;
};

struct WorkerList {
  double recent_window_s = 0;
  double quiet_after_s = 0;
  std::vector<WorkerInfo> workers;  // most recently seen first; at most kMaxListedWorkers
  bool operator==(const WorkerList&) const = default;
};
std::string encode(const WorkerList& m);
Decoded<WorkerList> decode_worker_list(std::string_view body);

}  // namespace dtraced::protocol
