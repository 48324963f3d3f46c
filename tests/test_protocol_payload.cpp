// Tests for dtraced::protocol's binary tile payload: it round trips bit for bit (special floats
// and per-pixel sample counts included) and detects each kind of corruption.
#include <bit>
#include <cfloat>
#include <cstdint>
#include <cstring>
#include <initializer_list>
#include <limits>
#include <string>
#include <string_view>
#include <utility>
#include <variant>

#include <catch2/catch.hpp>

#include "protocol/tile_payload.h"
#include "scene/tiling.h"
#include "util/sha256.h"

namespace {

namespace protocol = dtraced::protocol;

}  // namespace

namespace {

protocol::TilePayload test_tile(std::uint32_t w, std::uint32_t h) {
  protocol::TilePayload p;
  p.job = 0x0102030405060708ull;
  p.tile = 77;
  p.rect = {96, 64, w, h};
  p.rgb.resize(std::size_t{w} * h * 3);
  for (std::size_t i = 0; i < p.rgb.size(); ++i) p.rgb[i] = static_cast<float>(i) * 0.37f + 1e-3f;
  return p;
}

protocol::TilePayloadError error_of(std::string_view bytes) {
  auto d = protocol::decode_tile_payload(bytes);
  REQUIRE_FALSE(d);
  INFO(d.error().message);
  return d.error().code;
}

// Recomputes nothing: header edits keep the old checksum unless re-encoded, so corruptions that
// must be caught before the checksum are built through the encoder with the checksum refreshed.
std::string with_checksum(std::string bytes) {
  bytes.resize(bytes.size() - protocol::kTileChecksumBytes);
  const auto sum = dtraced::util::sha256_bytes(bytes);
  bytes.append(reinterpret_cast<const char*>(sum.data()), sum.size());
  return bytes;
}

// `bytes` with the header bytes at the given offsets set, the checksum refreshed.
std::string patched(std::string bytes, std::initializer_list<std::pair<std::size_t, char>> edits) {
  for (const auto& [offset, value] : edits) bytes[offset] = value;
  return with_checksum(std::move(bytes));
}

}  // namespace

TEST_CASE("a tile payload round trips bit for bit, special floats included", "[protocol][tile]") {
  protocol::TilePayload p = test_tile(32, 17);
  p.rgb[0] = -0.0f;
  p.rgb[1] = std::numeric_limits<float>::denorm_min();
  p.rgb[2] = std::numeric_limits<float>::infinity();
  p.rgb[3] = std::bit_cast<float>(0x7fc12345u);  // a NaN with a payload
  p.rgb[4] = FLT_MAX;
  const std::string bytes = protocol::encode_tile_payload(p);
  REQUIRE(bytes.size() == protocol::tile_payload_size(32, 17));
  REQUIRE(bytes.size() == 40 + 32 * 17 * 12 + 32);

  // The header layout, little-endian.
  CHECK(bytes.substr(0, 8) == "DTTILE01");
  CHECK(bytes.substr(8, 8) == std::string("\x08\x07\x06\x05\x04\x03\x02\x01", 8));
  CHECK(bytes.substr(16, 4) == std::string("\x4d\0\0\0", 4));  // tile 77
  CHECK(bytes.substr(20, 4) == std::string("\x60\0\0\0", 4));  // x 96
  CHECK(bytes.substr(36, 4) == std::string(4, '\0'));          // reserved

  auto d = protocol::decode_tile_payload(bytes);
  REQUIRE(d);
  const protocol::TilePayload& back = d.value();
  CHECK(back.job == p.job);
  CHECK(back.tile == p.tile);
  CHECK(back.rect == p.rect);
  REQUIRE(back.rgb.size() == p.rgb.size());
  CHECK(std::memcmp(back.rgb.data(), p.rgb.data(), p.rgb.size() * sizeof(float)) == 0);

  // The largest tile is within the upload limit (which leaves room for sample counts).
  CHECK(protocol::tile_payload_size(dtraced::scene::kMaxTileSize, dtraced::scene::kMaxTileSize) <
        protocol::kMaxTilePayloadBytes);
}

TEST_CASE("each kind of payload corruption is detected and named", "[protocol][tile]") {
  const std::string good = protocol::encode_tile_payload(test_tile(8, 8));
  REQUIRE(protocol::decode_tile_payload(good).ok());
  using E = protocol::TilePayloadError;

  SECTION("a flipped pixel bit fails the checksum") {
    std::string bad = good;
    bad[40 + 100] ^= 0x10;
    CHECK(error_of(bad) == E::kBadChecksum);
  }
  SECTION("a flipped header bit (the job) fails the checksum") {
    std::string bad = good;
    bad[9] ^= 0x01;
    CHECK(error_of(bad) == E::kBadChecksum);
  }
  SECTION("a flipped checksum bit fails the checksum") {
    std::string bad = good;
    bad[bad.size() - 1] ^= 0x80;
    CHECK(error_of(bad) == E::kBadChecksum);
  }
  SECTION("one byte short is the wrong size") { CHECK(error_of(good.substr(0, good.size() - 1)) == E::kWrongSize); }
  SECTION("one byte long is the wrong size") { CHECK(error_of(good + "x") == E::kWrongSize); }
  SECTION("a header claiming a bigger tile is the wrong size") {
    CHECK(error_of(patched(good, {{28, 9}})) == E::kWrongSize);  // width 9 with the pixels of width 8
  }
  SECTION("shorter than a header and checksum is truncated") {
    CHECK(error_of(good.substr(0, 71)) == E::kTruncated);
    CHECK(error_of("") == E::kTruncated);
  }
  SECTION("wrong magic") { CHECK(error_of(patched(good, {{7, '2'}})) == E::kBadMagic); }
  SECTION("reserved word not zero") {
    CHECK(error_of(patched(good, {{39, 1}})) == E::kUnknownFlags);
    CHECK(error_of(patched(good, {{36, 2}})) == E::kUnknownFlags);  // bit 1: not defined
  }
  SECTION("the counts flag without the counts, or counts without the flag, is the wrong size") {
    CHECK(error_of(patched(good, {{36, 1}})) == E::kWrongSize);
    protocol::TilePayload p = test_tile(8, 8);
    p.spp.assign(64, 5);
    CHECK(error_of(patched(protocol::encode_tile_payload(p), {{36, 0}})) == E::kWrongSize);
  }
  SECTION("zero or oversized dimensions") {
    CHECK(error_of(patched(good, {{28, 0}})) == E::kBadDimensions);
    CHECK(error_of(patched(good, {{32, 0x01}, {33, 0x04}})) == E::kBadDimensions);  // height 0x401 = 1025
  }
}

TEST_CASE("a tile payload carries per-pixel sample counts behind flag bit 0", "[protocol][tile][adaptive]") {
  protocol::TilePayload p = test_tile(5, 3);
  p.spp = {1, 2, 4, 8, 16, 32, 64, 65536, 0xffffffffu, 7, 7, 7, 9, 10, 11};
  const std::string bytes = protocol::encode_tile_payload(p);
  REQUIRE(bytes.size() == protocol::tile_payload_size(5, 3, /* sample_counts = */ true));
  REQUIRE(bytes.size() == 40 + 5 * 3 * 16 + 32);
  CHECK(bytes.substr(36, 4) == std::string("\x01\0\0\0", 4));  // flags
  // The counts follow the floats, little-endian.
  CHECK(bytes.substr(40 + 5 * 3 * 12, 8) == std::string("\x01\0\0\0\x02\0\0\0", 8));
  auto d = protocol::decode_tile_payload(bytes);
  REQUIRE(d);
  CHECK(d.value() == p);

  // A payload without counts keeps the old layout (flags 0) and decodes with none.
  p.spp.clear();
  const std::string plain = protocol::encode_tile_payload(p);
  CHECK(plain.size() == protocol::tile_payload_size(5, 3));
  CHECK(plain.substr(36, 4) == std::string(4, '\0'));
  auto back = protocol::decode_tile_payload(plain);
  REQUIRE(back);
  CHECK(back->spp.empty());

  // The largest payload with counts is the upload limit.
  CHECK(protocol::tile_payload_size(dtraced::scene::kMaxTileSize, dtraced::scene::kMaxTileSize, true) ==
        protocol::kMaxTilePayloadBytes);
}
