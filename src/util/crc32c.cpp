#include "util/crc32c.h"

#include <cstring>

#if defined(__x86_64__)
#include <nmmintrin.h>
#endif

namespace dtraced::util {

namespace {

#if defined(__x86_64__)
// 8 bytes a step: ~1.5 us for a 32-px tile of 12 KB, against ~8 us for its SHA-256.
__attribute__((target("sse4.2"))) std::uint32_t crc32c_sse42(std::uint32_t crc, const unsigned char* p, std::size_t n) {
  std::uint64_t c = crc;
  for (; n >= 8; n -= 8, p += 8) {
    std::uint64_t word;
    std::memcpy(&word, p, 8);
    c = _mm_crc32_u64(c, word);
  }
  auto c32 = static_cast<std::uint32_t>(c);
  for (; n > 0; --n, ++p) c32 = _mm_crc32_u8(c32, *p);
  return c32;
}
#endif

bool has_crc32_instruction() {
#if defined(__x86_64__)
  static const bool has = __builtin_cpu_supports("sse4.2");
  return has;
#else
  return false;
#endif
}

}  // namespace

Crc32c::Crc32c(bool hardware) : hardware_(hardware && has_crc32_instruction()) {}

void Crc32c::update(const void* data, std::size_t size) {
#if defined(__x86_64__)
  if (hardware_) {
    state_ = crc32c_sse42(state_, static_cast<const unsigned char*>(data), size);
    return;
  }
#endif
  table_.process_bytes(data, size);
}

std::uint32_t Crc32c::value() const { return hardware_ ? ~state_ : table_.checksum(); }

std::uint32_t crc32c(std::span<const std::uint8_t> bytes, bool hardware) {
  Crc32c crc(hardware);
  crc.update(bytes.data(), bytes.size());
  return crc.value();
}

}  // namespace dtraced::util
