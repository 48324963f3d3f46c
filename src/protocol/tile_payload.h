// dtraced::protocol tile payload: the binary body of PUT /v1/jobs/{id}/tiles/{tile}.
//
// Owns: the one binary format on the wire (README.md, "Tile payload"). All integers and floats
// are little-endian, whatever the host:
//
//   offset  size         field
//   0       8            magic "DTTILE01" (ASCII, no terminator)
//   8       8            u64 job
//   16      4            u32 tile
//   20      4            u32 x        (the tile rectangle in image pixels)
//   24      4            u32 y
//   28      4            u32 width    [1, scene::kMaxTileSize]
//   32      4            u32 height   [1, scene::kMaxTileSize]
//   36      4            u32 flags: bit 0 set = per-pixel sample counts follow; other bits 0
//   40      w * h * 12   float32 linear RGB, row-major, top row first (the renderer's output)
//   (flag)  w * h * 4    u32 samples each pixel took, row-major (adaptive renders); present
//                        exactly when flags bit 0 is set (adaptive sampling)
//   end-32  32           SHA-256 of every byte before it
//
// The flags word was a reserved word that had to be 0, so every payload written before sample
// counts existed is still a valid payload, without counts.
//
// The checksum catches corruption in transit or in a worker's memory, not forgery (the bearer
// token guards who may submit). Floats are carried bit for bit, NaN payloads included; whether
// the rectangle is the job's tile is the collector's check, not this format's.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include "scene/tiling.h"
#include "util/result.h"

namespace dtraced::protocol {

inline constexpr std::string_view kTileMagic = "DTTILE01";
inline constexpr std::size_t kTileHeaderBytes = 40;
inline constexpr std::size_t kTileChecksumBytes = 32;
inline constexpr std::uint32_t kTileFlagSampleCounts = 1u << 0;
inline constexpr std::uint32_t kTileKnownFlags = kTileFlagSampleCounts;
// The largest valid payload (the largest tile, with counts): the HTTP body limit for tile uploads.
inline constexpr std::size_t kMaxTilePayloadBytes =
    kTileHeaderBytes + std::size_t{scene::kMaxTileSize} * scene::kMaxTileSize * 16 + kTileChecksumBytes;

struct TilePayload {
  std::uint64_t job = 0;
  std::uint32_t tile = 0;
  scene::TileRect rect;
  std::vector<float> rgb;  // rect.width * rect.height * 3 floats
  // Empty (flags 0), or rect.width * rect.height counts (flags bit 0). The format carries any u32;
  // whether the counts fit the job is the collector's check.
  std::vector<std::uint32_t> spp;
  bool operator==(const TilePayload&) const = default;
};

// The exact size of a payload carrying a width x height tile, with or without sample counts.
std::size_t tile_payload_size(std::uint32_t width, std::uint32_t height, bool sample_counts = false);

// Requires 1 <= rect.width, rect.height <= scene::kMaxTileSize, rgb.size() == width * height * 3 and
// spp.size() either 0 or width * height (asserted: a caller holding the render output meets it by construction).
std::string encode_tile_payload(const TilePayload& payload);

// Why a payload was refused; each check has its own code.
enum class TilePayloadError {
  kTruncated,      // shorter than a header plus a checksum
  kBadMagic,       // the first 8 bytes are not "DTTILE01"
  kUnknownFlags,   // the flags word has a bit other than kTileKnownFlags set
  kBadDimensions,  // width or height is 0 or above scene::kMaxTileSize
  kWrongSize,      // the size is not header + width * height * (12, or 16 with counts) + checksum
  kBadChecksum,    // the trailing SHA-256 does not match
};

struct TilePayloadFailure {
  TilePayloadError code;
  std::string message;  // names the values found, e.g. "payload is 100 bytes; a 2x2 tile needs 120"
};

// Checks, in this order: minimum size, magic, flags, dimensions, exact size, checksum. The error
// carries a code (for tests and counters) beside its message.
util::Result<TilePayload, TilePayloadFailure> decode_tile_payload(std::string_view bytes);

}  // namespace dtraced::protocol
