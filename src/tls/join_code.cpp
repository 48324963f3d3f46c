#include "tls/join_code.h"

#include <algorithm>
#include <stdexcept>
#include <vector>

#include <fmt/format.h>
#include <openssl/rand.h>

namespace dtraced::tls {
namespace {

constexpr std::string_view kAlphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_";
constexpr std::size_t kTokenBytes = 32;

int sextet(char c) {
  if (c >= 'A' && c <= 'Z') return c - 'A';
  if (c >= 'a' && c <= 'z') return c - 'a' + 26;
  if (c >= '0' && c <= '9') return c - '0' + 52;
  if (c == '-') return 62;
  if (c == '_') return 63;
  return -1;
}

void random_bytes(std::uint8_t* out, std::size_t n) {
  if (RAND_bytes(out, static_cast<int>(n)) != 1) throw std::runtime_error("RAND_bytes failed: no randomness");
}

bool is_space(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n'; }

// One base64url part of a join code that must decode to exactly `bytes` bytes.
util::Result<std::string> decode_part(std::string_view part, std::size_t bytes, std::string_view what) {
  const std::size_t want = (bytes * 4 + 2) / 3;
  if (part.size() != want) {
    return util::Error(fmt::format("the {} has {} characters; it should have {}", what, part.size(), want));
  }
  const auto bad = std::find_if(part.begin(), part.end(), [](char c) { return sextet(c) < 0; });
  if (bad != part.end()) {
    return util::Error(fmt::format("the {} holds '{}', which is not a base64url character", what,
                                   static_cast<unsigned char>(*bad) < 0x20 ? '?' : *bad));
  }
  std::optional<std::string> raw = base64url_decode(part);
  if (!raw || raw->size() != bytes) return util::Error(fmt::format("the {} is not valid base64url", what));
  return std::move(*raw);
}

}  // namespace

std::string base64url_encode(const std::uint8_t* data, std::size_t size) {
  std::string out;
  out.reserve((size * 4 + 2) / 3);
  std::size_t i = 0;
  for (; i + 3 <= size; i += 3) {
    const std::uint32_t v = (std::uint32_t{data[i]} << 16) | (std::uint32_t{data[i + 1]} << 8) | data[i + 2];
    for (int shift = 18; shift >= 0; shift -= 6) out += kAlphabet[(v >> shift) & 63];
  }
  const std::size_t rest = size - i;
  if (rest == 1) {
    const std::uint32_t v = std::uint32_t{data[i]} << 16;
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
  } else if (rest == 2) {
    const std::uint32_t v = (std::uint32_t{data[i]} << 16) | (std::uint32_t{data[i + 1]} << 8);
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
    out += kAlphabet[(v >> 6) & 63];
  }
  return out;
}

std::optional<std::string> base64url_decode(std::string_view text) {
  if (text.size() % 4 == 1) return std::nullopt;  // no byte count leaves one character over
  std::string out;
  out.reserve(text.size() * 3 / 4);
  std::uint32_t acc = 0;
  int bits = 0;
  for (const char c : text) {
    const int v = sextet(c);
    if (v < 0) return std::nullopt;
    acc = (acc << 6) | static_cast<std::uint32_t>(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out += static_cast<char>((acc >> bits) & 0xff);
    }
  }
  // The bits left over must be zero, so each byte string has exactly one encoding.
  if ((acc & ((1u << bits) - 1)) != 0) return std::nullopt;
  return out;
}

std::string format_join_code(const JoinCode& code) {
  std::string out(kJoinCodePrefix);
  out += base64url_encode(code.secret.data(), code.secret.size());
  out += '.';
  if (code.ca) out += base64url_encode(code.ca->data(), code.ca->size());
  return out;
}

util::Result<JoinCode> parse_join_code(std::string_view text) {
  while (!text.empty() && is_space(text.front())) text.remove_prefix(1);
  while (!text.empty() && is_space(text.back())) text.remove_suffix(1);
  if (text.empty()) return util::Error("the join code is empty");
  if (!text.starts_with(kJoinCodePrefix)) {
    return util::Error(fmt::format("a join code starts with \"{}\"; this one does not", kJoinCodePrefix));
  }
  text.remove_prefix(kJoinCodePrefix.size());
  const auto dot = text.find('.');
  if (dot == std::string_view::npos) {
    return util::Error("the join code has no fingerprint part (dtj1.<secret>.<fingerprint>); was it cut short?");
  }
  const std::string_view secret_part = text.substr(0, dot);
  const std::string_view ca_part = text.substr(dot + 1);
  if (ca_part.find('.') != std::string_view::npos) {
    return util::Error("the join code has too many parts (dtj1.<secret>.<fingerprint>)");
  }
  JoinCode code;
  auto secret = decode_part(secret_part, code.secret.size(), "secret");
  if (!secret) return std::move(secret).error();
  std::copy(secret->begin(), secret->end(), code.secret.begin());
  if (!ca_part.empty()) {
    Fingerprint fp{};
    auto raw = decode_part(ca_part, fp.size(), "CA fingerprint");
    if (!raw) return std::move(raw).error();
    std::copy(raw->begin(), raw->end(), fp.begin());
    code.ca = fp;
  }
  return code;
}

JoinCode make_join_code(std::optional<Fingerprint> ca) {
  JoinCode code;
  random_bytes(code.secret.data(), code.secret.size());
  code.ca = ca;
  return code;
}

std::string random_token() {
  std::array<std::uint8_t, kTokenBytes> bytes{};
  random_bytes(bytes.data(), bytes.size());
  return base64url_encode(bytes.data(), bytes.size());
}

}  // namespace dtraced::tls
