#include "util/sha256.h"

#include <array>
#include <memory>
#include <stdexcept>

#include <fmt/format.h>
#include <openssl/evp.h>

namespace dtraced::util {
namespace {

// SHA-256 fetched from the default provider once per process: EVP_Digest with EVP_sha256() looks
// the algorithm up again on every call (a property query under a lock), which on a 12 KB tile
// cost about a tenth of the hash itself. The EVP_MD is immutable and thread-safe once fetched.
const EVP_MD* sha256_md() {
  static const EVP_MD* const md = [] {
    EVP_MD* fetched = EVP_MD_fetch(nullptr, "SHA256", nullptr);
    if (fetched == nullptr) throw std::runtime_error("EVP_MD_fetch(SHA256) failed");
    return fetched;  // held for the process's life
  }();
  return md;
}

struct CtxFree {
  void operator()(EVP_MD_CTX* ctx) const { EVP_MD_CTX_free(ctx); }
};

// One digest context per thread, reset by each EVP_DigestInit_ex2: no allocation per hash.
EVP_MD_CTX* thread_ctx() {
  thread_local const std::unique_ptr<EVP_MD_CTX, CtxFree> ctx(EVP_MD_CTX_new());
  if (!ctx) throw std::runtime_error("EVP_MD_CTX_new failed");
  return ctx.get();
}

}  // namespace

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
  EVP_MD_CTX* ctx = thread_ctx();
  if (EVP_DigestInit_ex2(ctx, sha256_md(), nullptr) != 1 || EVP_DigestUpdate(ctx, bytes.data(), bytes.size()) != 1 ||
      EVP_DigestFinal_ex(ctx, md.data(), &len) != 1 || len != kSha256Bytes) {
    throw std::runtime_error("SHA-256 digest failed");
  }
  Sha256Digest out{};
  for (std::size_t i = 0; i < kSha256Bytes; ++i) out[i] = md[i];
  return out;
}

}  // namespace dtraced::util
