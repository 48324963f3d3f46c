// dtraced::util SHA-256 through OpenSSL's libcrypto. Thread-safe (one digest context per thread).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

namespace dtraced::util {

inline constexpr std::size_t kSha256Bytes = 32;
using Sha256Digest = std::array<std::uint8_t, kSha256Bytes>;

// Lower-case hex digest (64 characters) of `bytes`.
std::string sha256_hex(std::string_view bytes);

// The raw 32-byte digest of `bytes`, for binary formats that carry a checksum.
Sha256Digest sha256_bytes(std::string_view bytes);

}  // namespace dtraced::util
