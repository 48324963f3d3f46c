#include "util/sha256.h"

#include <array>
#include <stdexcept>

#include <fmt/format.h>
#include <openssl/evp.h>

namespace dtraced::util {

std::string sha256_hex(std::string_view bytes) {
  const Sha256Digest md = sha256_bytes(bytes);
  std::string out;
  out.reserve(2 * md.size());
  for (const std::uint8_t b : md) out += fmt::format("{:02x}", b);
  return out;
}

Sha256Digest sha256_bytes(std::string_view bytes) {
  std::array<unsigned char, EVP_MAX_MD_SIZE> md{};
  unsigned int len = 0;
  if (EVP_Digest(bytes.data(), bytes.size(), md.data(), &len, EVP_sha256(), nullptr) != 1 || len != kSha256Bytes) {
    throw std::runtime_error("EVP_Digest(sha256) failed");
  }
  Sha256Digest out{};
  for (std::size_t i = 0; i < kSha256Bytes; ++i) out[i] = md[i];
  return out;
}

}  // namespace dtraced::util
