#include "protocol/tile_payload.h"

#include <bit>
#include <cassert>
#include <cstring>
#include <limits>
#include <utility>

#include <fmt/format.h>

#include "protocol/messages.h"
#include "util/sha256.h"

namespace dtraced::protocol {
namespace {

static_assert(kTileMagic.size() == 8);
static_assert(kTileHeaderBytes == 8 + 8 + 6 * 4);
static_assert(kTileChecksumBytes == util::kSha256Bytes);
static_assert(sizeof(float) == 4 && std::numeric_limits<float>::is_iec559);

// Byte-by-byte little-endian access: independent of the host's byte order and alignment.
template <typename U>
void put_le(std::string& out, U value) {
  for (std::size_t i = 0; i < sizeof(U); ++i) out += static_cast<char>((value >> (8 * i)) & 0xff);
}

template <typename U>
U get_le(std::string_view bytes, std::size_t offset) {
  U value = 0;
  for (std::size_t i = 0; i < sizeof(U); ++i) {
    value |= static_cast<U>(static_cast<unsigned char>(bytes[offset + i])) << (8 * i);
  }
  return value;
}

TilePayloadFailure failure(TilePayloadError code, std::string message) { return {code, std::move(message)}; }

}  // namespace

std::size_t tile_payload_size(std::uint32_t width, std::uint32_t height, bool sample_counts) {
  return kTileHeaderBytes + std::size_t{width} * height * (sample_counts ? 16 : 12) + kTileChecksumBytes;
}

std::string encode_tile_payload(const TilePayload& p) {
  assert(p.rect.width >= 1 && p.rect.width <= scene::kMaxTileSize);
  assert(p.rect.height >= 1 && p.rect.height <= scene::kMaxTileSize);
  assert(p.rgb.size() == std::size_t{p.rect.width} * p.rect.height * 3);
  assert(p.spp.empty() || p.spp.size() == std::size_t{p.rect.width} * p.rect.height);
  const bool counts = !p.spp.empty();

  std::string out;
  out.reserve(tile_payload_size(p.rect.width, p.rect.height, counts));
  out += kTileMagic;
  put_le<std::uint64_t>(out, p.job);
  put_le<std::uint32_t>(out, p.tile);
  put_le<std::uint32_t>(out, p.rect.x0);
  put_le<std::uint32_t>(out, p.rect.y0);
  put_le<std::uint32_t>(out, p.rect.width);
  put_le<std::uint32_t>(out, p.rect.height);
  put_le<std::uint32_t>(out, counts ? kTileFlagSampleCounts : 0);
  if constexpr (std::endian::native == std::endian::little) {
    out.append(reinterpret_cast<const char*>(p.rgb.data()), p.rgb.size() * sizeof(float));
    out.append(reinterpret_cast<const char*>(p.spp.data()), p.spp.size() * sizeof(std::uint32_t));
  } else {
    for (const float f : p.rgb) put_le<std::uint32_t>(out, std::bit_cast<std::uint32_t>(f));
    for (const std::uint32_t n : p.spp) put_le<std::uint32_t>(out, n);
  }
  const util::Sha256Digest sum = util::sha256_bytes(out);
  out.append(reinterpret_cast<const char*>(sum.data()), sum.size());
  assert(out.size() == tile_payload_size(p.rect.width, p.rect.height, counts));
  return out;
}

util::Result<TilePayload, TilePayloadFailure> decode_tile_payload(std::string_view bytes) {
  constexpr std::size_t kMinBytes = kTileHeaderBytes + kTileChecksumBytes;
  if (bytes.size() < kMinBytes) {
    return failure(TilePayloadError::kTruncated,
                   fmt::format("payload is {} bytes, shorter than a {}-byte header and a {}-byte checksum",
                               bytes.size(), kTileHeaderBytes, kTileChecksumBytes));
  }
  if (bytes.substr(0, kTileMagic.size()) != kTileMagic) {
    return failure(TilePayloadError::kBadMagic, fmt::format("payload does not start with \"{}\"", kTileMagic));
  }
  TilePayload p;
  p.job = get_le<std::uint64_t>(bytes, 8);
  p.tile = get_le<std::uint32_t>(bytes, 16);
  p.rect.x0 = get_le<std::uint32_t>(bytes, 20);
  p.rect.y0 = get_le<std::uint32_t>(bytes, 24);
  p.rect.width = get_le<std::uint32_t>(bytes, 28);
  p.rect.height = get_le<std::uint32_t>(bytes, 32);
  const auto flags = get_le<std::uint32_t>(bytes, 36);
  if ((flags & ~kTileKnownFlags) != 0) {
    return failure(TilePayloadError::kUnknownFlags,
                   fmt::format("flags word is {:#x}; only bit 0 (sample counts) may be set", flags));
  }
  const bool counts = (flags & kTileFlagSampleCounts) != 0;
  if (p.rect.width < 1 || p.rect.width > scene::kMaxTileSize || p.rect.height < 1 ||
      p.rect.height > scene::kMaxTileSize) {
    return failure(TilePayloadError::kBadDimensions, fmt::format("tile is {}x{}; each side must be in [1, {}]",
                                                                 p.rect.width, p.rect.height, scene::kMaxTileSize));
  }
  const std::size_t expected = tile_payload_size(p.rect.width, p.rect.height, counts);
  if (bytes.size() != expected) {
    return failure(TilePayloadError::kWrongSize,
                   fmt::format("payload is {} bytes; a {}x{} tile {} needs exactly {}", bytes.size(), p.rect.width,
                               p.rect.height, counts ? "with sample counts" : "without sample counts", expected));
  }
  const std::string_view body = bytes.substr(0, expected - kTileChecksumBytes);
  const util::Sha256Digest sum = util::sha256_bytes(body);
  if (std::memcmp(sum.data(), bytes.data() + body.size(), sum.size()) != 0) {
    return failure(TilePayloadError::kBadChecksum, "payload checksum does not match its contents (SHA-256)");
  }
  p.rgb.resize(std::size_t{p.rect.width} * p.rect.height * 3);
  if (counts) p.spp.resize(std::size_t{p.rect.width} * p.rect.height);
  const std::string_view pixels = body.substr(kTileHeaderBytes, p.rgb.size() * sizeof(float));
  const std::string_view spp = body.substr(kTileHeaderBytes + pixels.size());
  if constexpr (std::endian::native == std::endian::little) {
    std::memcpy(p.rgb.data(), pixels.data(), pixels.size());
    if (counts) std::memcpy(p.spp.data(), spp.data(), spp.size());
  } else {
    for (std::size_t i = 0; i < p.rgb.size(); ++i)
      p.rgb[i] = std::bit_cast<float>(get_le<std::uint32_t>(pixels, 4 * i));
    for (std::size_t i = 0; i < p.spp.size(); ++i) p.spp[i] = get_le<std::uint32_t>(spp, 4 * i);
  }
  return p;
}

}  // namespace dtraced::protocol
