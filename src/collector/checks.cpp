#include "collector/checks.h"

#include <bit>
#include <cmath>
#include <cstdint>
#include <span>
#include <string_view>
#include <utility>
#include <variant>

#include <fmt/format.h>

namespace dtraced::collector {
namespace {

// Whether every value is finite and not below 0 (-0.0 passes), in one pass without an early exit
// so that the compiler vectorises it: as bits, those are 0 to the largest finite float, and -0.0.
bool all_radiance(std::span<const float> values) {
  constexpr std::uint32_t kLargestFinite = 0x7f7fffffu;
  constexpr std::uint32_t kNegativeZero = 0x80000000u;
  std::uint32_t bad = 0;
  for (const float v : values) {
    const auto bits = std::bit_cast<std::uint32_t>(v);
    bad |= static_cast<std::uint32_t>(bits > kLargestFinite && bits != kNegativeZero);
  }
  return bad == 0;
}

}  // namespace

util::Result<void, Refusal> check_job_slots(const Load& load, const CollectorConfig& config) {
  if (load.unfinished_jobs < config.max_unfinished_jobs) return {};
  return busy(fmt::format("too many unfinished jobs (limit {}); retry later", config.max_unfinished_jobs));
}

util::Result<void, Refusal> check_job_room(std::uint32_t width, std::uint32_t height, const Load& load,
                                           const CollectorConfig& config) {
  const std::uint64_t pixels = std::uint64_t{width} * height;
  if (pixels > config.max_unfinished_pixels) {
    return Refusal{http::Status::payload_too_large,
                   util::Error(fmt::format("a {}x{} image is more than the collector's limit of {} pixels in flight",
                                           width, height, config.max_unfinished_pixels),
                               "/width"),
                   {}};
  }
  if (load.unfinished_pixels + pixels > config.max_unfinished_pixels) {
    return busy(fmt::format("unfinished jobs already hold {} of the limit of {} pixels; retry later",
                            load.unfinished_pixels, config.max_unfinished_pixels));
  }
  if (!load.accepting_writes) return busy("the collector is stopping");
  return {};
}

util::Result<CancelAction, Refusal> check_cancel(JobId id, const JobRecord* job, bool accepting_writes) {
  if (job == nullptr) return job_not_found(id);
  if (job->state == protocol::JobState::kCancelled) return CancelAction::kAlreadyCancelled;
  if (job->state == protocol::JobState::kDone || job->finishing) {
    return Refusal{http::Status::conflict, util::Error(fmt::format("job {} is finished; nothing to cancel", id)), {}};
  }
  if (!accepting_writes) return busy("the collector is stopping");
  return CancelAction::kCancel;
}

util::Result<protocol::TilePayload, Refusal> check_tile_payload(std::string_view body) {
  auto decoded = protocol::decode_tile_payload(body);
  if (!decoded) return bad_request("tile payload: " + decoded.error().message);
  protocol::TilePayload& payload = decoded.value();
  if (all_radiance(payload.rgb)) return std::move(payload);
  // Something is wrong: find the first bad value, to name it.
  constexpr std::string_view kChannels[] = {"red", "green", "blue"};
  for (std::size_t i = 0; i < payload.rgb.size(); ++i) {
    const float v = payload.rgb[i];
    // Radiance is a sum of non-negative terms; -0.0 compares equal to 0 and passes.
    if (std::isfinite(v) && v >= 0.0f) continue;
    const std::size_t pixel = i / 3;
    const std::uint32_t x = payload.rect.x0 + static_cast<std::uint32_t>(pixel % payload.rect.width);
    const std::uint32_t y = payload.rect.y0 + static_cast<std::uint32_t>(pixel / payload.rect.width);
    if (!std::isfinite(v)) return bad_request(fmt::format("pixel ({}, {}) holds a non-finite value", x, y), "/pixels");
    return bad_request(fmt::format("pixel ({}, {}) holds a negative value ({} in {}); radiance is never below 0", x, y,
                                   v, kChannels[i % 3]),
                       "/pixels");
  }
  return std::move(payload);
}

util::Result<TileAction, Refusal> check_tile(const Route& route, const JobRecord* job, const protocol::TilePayload& p) {
  if (p.job != route.job) {
    return bad_request(fmt::format("the payload is for job {} but the URL names job {}", p.job, route.job), "/job");
  }
  if (p.tile != route.tile) {
    return bad_request(fmt::format("the payload is tile {} but the URL names tile {}", p.tile, route.tile), "/tile");
  }
  if (job == nullptr || job->state == protocol::JobState::kCancelled) return TileAction::kJobGone;
  if (p.tile >= job->tile_indices) {
    return bad_request(fmt::format("job {} has {} tiles; there is no tile {}", job->id, job->tile_indices, p.tile),
                       "/tile");
  }
  if (!tile_of_job(*job, p.tile)) {
    return bad_request(
        fmt::format("tile {} of job {} lies outside the job's crop; it is not rendered", p.tile, job->id), "/tile");
  }
  const scene::TileRect expected = tile_place(*job, p.tile).rect;
  if (p.rect != expected) {
    return bad_request(
        fmt::format("the payload's rectangle {}x{} at ({}, {}) is not tile {} of job {}: {}x{} at ({}, {})",
                    p.rect.width, p.rect.height, p.rect.x0, p.rect.y0, p.tile, job->id, expected.width, expected.height,
                    expected.x0, expected.y0),
        "/rect");
  }
  if (util::Status counts = check_sample_counts(job->settings, expected, p.spp); !counts) {
    return Refusal{http::Status::bad_request, std::move(counts).error(), {}};
  }
  return TileAction::kStore;
}

}  // namespace dtraced::collector
