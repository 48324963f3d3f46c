#include "collector/config.h"

#include <filesystem>

#include <boost/asio/ip/address.hpp>
#include <fmt/format.h>

namespace dtraced::collector {
namespace {

void check_token(const std::string& token, util::Errors& errors) {
  if (token.empty()) {
    errors.push_back({"must not be empty (the collector never runs without authentication)", "token"});
    return;
  }
  if (token.size() > kMaxTokenBytes) errors.push_back({fmt::format("longer than {} bytes", kMaxTokenBytes), "token"});
  for (const char ch : token) {
    // Header field values: visible ASCII only, so the token survives every HTTP stack unchanged.
    if (ch < 0x21 || ch > 0x7e) {
      errors.push_back({"must be printable ASCII without spaces", "token"});
      return;
    }
  }
}

void check_limits(const http::ServerLimits& l, util::Errors& errors) {
  if (l.max_header_bytes == 0) errors.push_back({"must be > 0", "limits.max_header_bytes"});
  if (l.max_body_bytes < protocol::kMaxMessageBytes) {
    errors.push_back({fmt::format("must be at least {} (the control messages)", protocol::kMaxMessageBytes),
                      "limits.max_body_bytes"});
  }
  if (l.read_timeout.count() <= 0) errors.push_back({"must be > 0", "limits.read_timeout"});
  if (l.write_timeout.count() <= 0) errors.push_back({"must be > 0", "limits.write_timeout"});
  if (l.idle_keepalive_timeout.count() <= 0) errors.push_back({"must be > 0", "limits.idle_keepalive_timeout"});
  if (l.unauthenticated_timeout.count() <= 0) errors.push_back({"must be > 0", "limits.unauthenticated_timeout"});
  if (l.max_held_response_bytes == 0) errors.push_back({"must be > 0", "limits.max_held_response_bytes"});
  if (l.max_connections == 0) errors.push_back({"must be > 0", "limits.max_connections"});
  if (l.max_idle_connections == 0) errors.push_back({"must be > 0", "limits.max_idle_connections"});
}

void check_queue_and_writer(const CollectorConfig& c, util::Errors& errors) {
  for (util::Error& e : check_queue_config(c.queue)) errors.push_back({std::move(e.message), "queue." + e.path});
  if (c.queue.max_retry_after > std::chrono::milliseconds(protocol::kMaxRetryAfterMs)) {
    errors.push_back({fmt::format("must be at most {} ms (the protocol's limit)", protocol::kMaxRetryAfterMs),
                      "queue.max_retry_after"});
  }
  const store::WriterLimits& w = c.writer;
  if (w.max_batch_tiles == 0) errors.push_back({"must be > 0", "writer.max_batch_tiles"});
  if (w.max_pending_tiles == 0) errors.push_back({"must be > 0", "writer.max_pending_tiles"});
  if (w.max_pending_tasks == 0) errors.push_back({"must be > 0", "writer.max_pending_tasks"});
  if (w.max_pending_bytes < protocol::kMaxTilePayloadBytes) {
    errors.push_back({fmt::format("must hold at least one largest tile ({} bytes)", protocol::kMaxTilePayloadBytes),
                      "writer.max_pending_bytes"});
  }
}

void check_one_shot(const CollectorConfig& c, util::Errors& errors) {
  if (!c.one_shot) {
    if (c.exit_when_done) errors.push_back({"needs a one-shot job (a scene and an output)", "exit_when_done"});
    return;
  }
  const OneShotJob& j = *c.one_shot;
  if (j.scene_path.empty()) errors.push_back({"must name a scene file", "scene"});
  if (util::Status ok = protocol::check_output_name(j.output); !ok) errors.push_back({ok.error().message, "output"});
  if (j.priority < protocol::kMinPriority || j.priority > protocol::kMaxPriority) {
    errors.push_back({fmt::format("must be in [{}, {}]", protocol::kMinPriority, protocol::kMaxPriority), "priority"});
  }
  // The overrides are checked with the scene, by the job decoder, at start.
}

}  // namespace

std::string CollectorConfig::effective_output_dir() const {
  if (!output_dir.empty()) return output_dir;
  return (std::filesystem::path(state_dir) / "output").string();
}

util::Errors check_collector_config(const CollectorConfig& c) {
  util::Errors errors;
  boost::system::error_code ec;
  boost::asio::ip::make_address(c.listen_address, ec);
  if (ec) errors.push_back({fmt::format("'{}' is not an IPv4 or IPv6 address", c.listen_address), "listen_address"});
  if (c.state_dir.empty()) errors.push_back({"must not be empty", "state_dir"});
  check_token(c.token, errors);
  check_limits(c.limits, errors);
  check_queue_and_writer(c, errors);
  if (c.shutdown_grace.count() <= 0 || c.shutdown_grace > kMaxShutdownGrace) {
    errors.push_back({fmt::format("must be > 0 and at most {} ms", kMaxShutdownGrace.count()), "shutdown_grace"});
  }
  if (c.cpu_threads == 0 || c.cpu_threads > kMaxCpuThreads) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxCpuThreads), "cpu_threads"});
  }
  if (c.max_unfinished_jobs == 0) errors.push_back({"must be > 0", "max_unfinished_jobs"});
  if (c.max_unfinished_pixels == 0) errors.push_back({"must be > 0", "max_unfinished_pixels"});
  if (c.image_memory_bytes == 0) errors.push_back({"must be > 0", "image_memory_bytes"});
  if (c.workers.quiet_after <= Duration::zero()) errors.push_back({"must be > 0", "workers.quiet_after"});
  if (c.workers.forget_after < c.workers.quiet_after) {
    errors.push_back({"must be at least workers.quiet_after", "workers.forget_after"});
  }
  if (c.workers.max_workers == 0 || c.workers.max_workers > kMaxMaxWorkers) {
    errors.push_back({fmt::format("must be in [1, {}]", kMaxMaxWorkers), "workers.max_workers"});
  }
  check_one_shot(c, errors);
  return errors;
}

}  // namespace dtraced::collector
