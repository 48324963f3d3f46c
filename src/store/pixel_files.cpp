#include "store/pixel_files.h"

#include <fcntl.h>
#include <limits.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>

#include <fmt/format.h>

#include "util/crc32c.h"

namespace dtraced::store {

using util::Error;
using util::Result;
using util::Status;

std::string pixel_file_path(const std::string& pixel_dir, std::int64_t job) {
  return fmt::format("{}/job-{}.pixels", pixel_dir, job);
}

Status write_all(int fd, const std::string& path, std::uint64_t offset, std::span<const iovec> pieces) {
  std::vector<iovec> rest(pieces.begin(), pieces.end());
  std::size_t first = 0;
  while (first < rest.size()) {
    const int count = static_cast<int>(std::min<std::size_t>(rest.size() - first, IOV_MAX));
    const ssize_t n = ::pwritev(fd, rest.data() + first, count, static_cast<off_t>(offset));
    if (n < 0) {
      if (errno == EINTR) continue;
      return Error{fmt::format("{}: appending tile pixels at offset {}: {}", path, offset, std::strerror(errno))};
    }
    offset += static_cast<std::uint64_t>(n);
    auto left = static_cast<std::size_t>(n);
    while (first < rest.size() && left >= rest[first].iov_len) left -= rest[first++].iov_len;
    if (first < rest.size()) {
      rest[first].iov_base = static_cast<char*>(rest[first].iov_base) + left;
      rest[first].iov_len -= left;
    }
  }
  return {};
}

Result<Blob> read_checked(int fd, const std::string& path, std::int64_t job, std::uint32_t tile, std::uint64_t offset,
                          std::uint64_t length, std::uint32_t crc) {
  Blob bytes(length);
  std::uint64_t done = 0;
  while (done < length) {
    const ssize_t n = ::pread(fd, bytes.data() + done, length - done, static_cast<off_t>(offset + done));
    if (n < 0) {
      if (errno == EINTR) continue;
      return Error{fmt::format("{}: reading tile {} of job {} ({} bytes at offset {}): {}", path, tile, job, length,
                               offset, std::strerror(errno))};
    }
    if (n == 0) {
      return Error{fmt::format("{}: tile {} of job {} lies at bytes {} to {}, but the file ends at {}: truncated", path,
                               tile, job, offset, offset + length, offset + done)};
    }
    done += static_cast<std::uint64_t>(n);
  }
  if (const std::uint32_t got = util::crc32c(bytes); got != crc) {
    return Error{
        fmt::format("{}: tile {} of job {} ({} bytes at offset {}): checksum mismatch (CRC-32C {:08x}, "
                    "stored {:08x}): the file is damaged",
                    path, tile, job, length, offset, got, crc)};
  }
  return bytes;
}

Result<util::FileHandle> open_for_reading(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return Error{fmt::format("{}: cannot open the tile pixels: {}", path, std::strerror(errno))};
  return util::FileHandle(fd);
}

}  // namespace dtraced::store
