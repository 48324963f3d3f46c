#include "collector/config.h"

#include <filesystem>

#include <boost/asio/ip/address.hpp>
#include <fmt/format.h>

namespace dtraced::collector {

std::string CollectorConfig::effective_output_dir() const {
  if (!output_dir.empty()) return output_dir;
  return (std::filesystem::path(state_dir) / "output").string();
}

std::optional<std::string> check_collector_config(const CollectorConfig& c) {
  boost::system::error_code ec;
  boost::asio::ip::make_address(c.listen_address, ec);
  if (ec) return fmt::format("listen_address: '{}' is not an IPv4 or IPv6 address", c.listen_address);
  if (c.state_dir.empty()) return "state_dir: must not be empty";
  if (c.token.empty()) return "token: must not be empty (the collector never runs without authentication)";
  if (c.token.size() > kMaxTokenBytes) return fmt::format("token: longer than {} bytes", kMaxTokenBytes);
  for (const char ch : c.token) {
    // Header field values: visible ASCII only, so the token survives every HTTP stack unchanged.
    if (ch < 0x21 || ch > 0x7e) return "token: must be printable ASCII without spaces";
  }
  const http::ServerLimits& l = c.limits;
  if (l.max_header_bytes == 0) return "limits.max_header_bytes: must be > 0";
  if (l.max_body_bytes < protocol::kMaxMessageBytes) {
    return fmt::format("limits.max_body_bytes: must be at least {} (the control messages)", protocol::kMaxMessageBytes);
  }
  if (l.read_timeout.count() <= 0 || l.write_timeout.count() <= 0 || l.idle_keepalive_timeout.count() <= 0) {
    return "limits: read, write and keep-alive timeouts must be > 0";
  }
  if (l.max_connections == 0) return "limits.max_connections: must be > 0";
  if (auto q = check_queue_config(c.queue)) return "queue: " + *q;
  if (c.queue.max_retry_after > std::chrono::milliseconds(protocol::kMaxRetryAfterMs)) {
    return fmt::format("queue: max_retry_after must be at most {} ms (the protocol's limit)",
                       protocol::kMaxRetryAfterMs);
  }
  const store::WriterLimits& w = c.writer;
  if (w.max_batch_tiles == 0 || w.max_pending_tiles == 0 || w.max_pending_tasks == 0) {
    return "writer: batch and pending limits must be > 0";
  }
  if (w.max_pending_bytes < protocol::kMaxTilePayloadBytes) {
    return fmt::format("writer.max_pending_bytes: must hold at least one largest tile ({} bytes)",
                       protocol::kMaxTilePayloadBytes);
  }
  if (c.shutdown_grace.count() <= 0 || c.shutdown_grace > kMaxShutdownGrace) {
    return fmt::format("shutdown_grace: must be > 0 and at most {} ms", kMaxShutdownGrace.count());
  }
  if (c.cpu_threads == 0 || c.cpu_threads > kMaxCpuThreads) {
    return fmt::format("cpu_threads: must be in [1, {}]", kMaxCpuThreads);
  }
  if (c.max_unfinished_jobs == 0) return "max_unfinished_jobs: must be > 0";
  if (c.max_unfinished_pixels == 0) return "max_unfinished_pixels: must be > 0";
  if (c.one_shot) {
    const OneShotJob& j = *c.one_shot;
    if (j.scene_path.empty()) return "scene: must name a scene file";
    if (auto why = protocol::check_output_name(j.output)) return "output: output name " + *why;
    if (j.priority < protocol::kMinPriority || j.priority > protocol::kMaxPriority) {
      return fmt::format("priority: must be in [{}, {}]", protocol::kMinPriority, protocol::kMaxPriority);
    }
    // The overrides are checked with the scene, by the job decoder, at start.
  } else if (c.exit_when_done) {
    return "exit_when_done: needs a one-shot job (a scene and an output)";
  }
  return std::nullopt;
}

}  // namespace dtraced::collector
