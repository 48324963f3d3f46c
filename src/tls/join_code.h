// dtraced::tls join codes and tokens: the one-time codes an operator hands to a new worker, and
// the random bearer tokens credentials are made of.
//
// A join code reads "dtj1.<secret>.<fingerprint>": version tag, 16 random bytes, and the SHA-256
// fingerprint of the CA certificate the worker must trust (empty when the collector speaks plain
// HTTP), each base64url without padding. Holding the code is what authorises one enrollment; the
// fingerprint lets the worker check the collector's CA before it sends the secret.
//
// Randomness comes from OpenSSL's RAND_bytes; a failure there is not an expected failure (the
// process cannot make secrets at all) and throws std::runtime_error.
//
// Thread safety: stateless free functions.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "tls/material.h"
#include "util/result.h"

namespace dtraced::tls {

inline constexpr std::string_view kJoinCodePrefix = "dtj1.";

struct JoinCode {
  std::array<std::uint8_t, 16> secret{};
  std::optional<Fingerprint> ca;
  bool operator==(const JoinCode&) const = default;
};

// "dtj1.<22 characters>.<43 characters or nothing>".
std::string format_join_code(const JoinCode& code);

// Parses a join code (surrounding white space ignored, as pasted). The error says what is wrong:
// the prefix, the number of parts, a character outside base64url, a part of the wrong length.
util::Result<JoinCode> parse_join_code(std::string_view text);

// A new code with a random secret.
JoinCode make_join_code(std::optional<Fingerprint> ca);

// 32 random bytes, base64url without padding (43 characters): per-worker and role tokens.
std::string random_token();

// base64url (RFC 4648 section 5) without padding, and back; decoding refuses padding, characters
// outside the alphabet and encodings whose unused trailing bits are not zero.
std::string base64url_encode(const std::uint8_t* data, std::size_t size);
std::optional<std::string> base64url_decode(std::string_view text);

}  // namespace dtraced::tls
