// dtraced::util CRC-32C (Castagnoli: polynomial 0x1EDC6F41, reflected, all ones in and out), the
// checksum of the store's pixel files and of `dtraced render`'s resume file. SSE4.2's crc32
// instruction where the CPU has it (about 8 bytes every 3 cycles), else Boost.CRC's table; both
// give the same value. Stateless apart from each Crc32c: thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include <boost/crc.hpp>

namespace dtraced::util {

// A CRC-32C over pieces fed one after another: the same value as over their concatenation.
class Crc32c {
 public:
  // `hardware`: use the crc32 instruction if the CPU has it (false: always the table, for tests).
  explicit Crc32c(bool hardware = true);
  void update(const void* data, std::size_t size);
  std::uint32_t value() const;

 private:
  bool hardware_;
  std::uint32_t state_ = 0xFFFFFFFFu;  // the instruction's register, while hardware_
  boost::crc_optimal<32, 0x1EDC6F41u, 0xFFFFFFFFu, 0xFFFFFFFFu, true, true> table_;  // otherwise
};

// The CRC-32C of `bytes` ("123456789" gives 0xE3069283).
std::uint32_t crc32c(std::span<const std::uint8_t> bytes, bool hardware = true);

}  // namespace dtraced::util
