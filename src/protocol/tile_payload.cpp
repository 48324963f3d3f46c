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
static_assert(kMaxTileSide == kMaxTileSize);
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

std::size_t tile_payload_size(std::uint32_t width, std::uint32_t height) {
  return kTileHeaderBytes + std::size_t{width} * height * 12 + kTileChecksumBytes;
}

std::string encode_tile_payload(const TilePayload& p) {
  assert(p.rect.width >= 1 && p.rect.width <= kMaxTileSide);
  assert(p.rect.height >= 1 && p.rect.height <= kMaxTileSide);
  assert(p.rgb.size() == std::size_t{p.rect.width} * p.rect.height * 3);

  std::string out;
  out.reserve(tile_payload_size(p.rect.width, p.rect.height));
  out += kTileMagic;
  put_le<std::uint64_t>(out, p.job);
  put_le<std::uint32_t>(out, p.tile);
  put_le<std::uint32_t>(out, p.rect.x0);
  put_le<std::uint32_t>(out, p.rect.y0);
  put_le<std::uint32_t>(out, p.rect.width);
  put_le<std::uint32_t>(out, p.rect.height);
  put_le<std::uint32_t>(out, 0);  // reserved
  if constexpr (std::endian::native == std::endian::little) {
    out.append(reinterpret_cast<const char*>(p.rgb.data()), p.rgb.size() * sizeof(float));
  } else {
    for (const float f : p.rgb) put_le<std::uint32_t>(out, std::bit_cast<std::uint32_t>(f));
  }
  const util::Sha256Digest sum = util::sha256_bytes(out);
  out.append(reinterpret_cast<const char*>(sum.data()), sum.size());
  assert(out.size() == tile_payload_size(p.rect.width, p.rect.height));
  return out;
}

std::variant<TilePayload, TilePayloadFailure> decode_tile_payload(std::string_view bytes) {
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
  if (const auto reserved = get_le<std::uint32_t>(bytes, 36); reserved != 0) {
    return failure(TilePayloadError::kReservedNotZero, fmt::format("reserved header word is {}, not 0", reserved));
  }
  if (p.rect.width < 1 || p.rect.width > kMaxTileSide || p.rect.height < 1 || p.rect.height > kMaxTileSide) {
    return failure(TilePayloadError::kBadDimensions, fmt::format("tile is {}x{}; each side must be in [1, {}]",
                                                                 p.rect.width, p.rect.height, kMaxTileSide));
  }
  const std::size_t expected = tile_payload_size(p.rect.width, p.rect.height);
  if (bytes.size() != expected) {
    return failure(TilePayloadError::kWrongSize, fmt::format("payload is {} bytes; a {}x{} tile needs exactly {}",
                                                             bytes.size(), p.rect.width, p.rect.height, expected));
  }
  const std::string_view body = bytes.substr(0, expected - kTileChecksumBytes);
  const util::Sha256Digest sum = util::sha256_bytes(body);
  if (std::memcmp(sum.data(), bytes.data() + body.size(), sum.size()) != 0) {
    return failure(TilePayloadError::kBadChecksum, "payload checksum does not match its contents (SHA-256)");
  }
  p.rgb.resize(std::size_t{p.rect.width} * p.rect.height * 3);
  const std::string_view pixels = body.substr(kTileHeaderBytes);
  if constexpr (std::endian::native == std::endian::little) {
    std::memcpy(p.rgb.data(), pixels.data(), pixels.size());
  } else {
    for (std::size_t i = 0; i < p.rgb.size(); ++i)
      p.rgb[i] = std::bit_cast<float>(get_le<std::uint32_t>(pixels, 4 * i));
  }
  return p;
}

}  // namespace dtraced::protocol
