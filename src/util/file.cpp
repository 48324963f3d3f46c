#include "util/file.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>

#include <fmt/format.h>

namespace dtraced::util {

std::optional<std::string> read_file_limited(const std::string& path, std::uint64_t max_bytes, std::string& error) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    error = fmt::format("{}: cannot open: {}", path, std::strerror(errno));
    return std::nullopt;
  }
  std::string data;
  char buf[1 << 16];
  while (in) {
    in.read(buf, sizeof buf);
    const auto got = static_cast<std::uint64_t>(in.gcount());
    if (data.size() + got > max_bytes) {
      error = fmt::format("{}: file is larger than the limit of {} bytes", path, max_bytes);
      return std::nullopt;
    }
    data.append(buf, static_cast<std::size_t>(got));
  }
  if (in.bad()) {
    error = fmt::format("{}: read error", path);
    return std::nullopt;
  }
  return data;
}

bool write_file_atomic(const std::string& path, std::string_view bytes, std::string& error) {
  const std::string tmp = fmt::format("{}.tmp.{}", path, ::getpid());
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) {
    error = fmt::format("{}: cannot create: {}", tmp, std::strerror(errno));
    return false;
  }
  std::size_t off = 0;
  while (off < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + off, bytes.size() - off);
    if (n < 0) {
      if (errno == EINTR) continue;
      error = fmt::format("{}: write failed: {}", tmp, std::strerror(errno));
      ::close(fd);
      ::unlink(tmp.c_str());
      return false;
    }
    off += static_cast<std::size_t>(n);
  }
  if (::fsync(fd) != 0 || ::close(fd) != 0) {
    error = fmt::format("{}: flush failed: {}", tmp, std::strerror(errno));
    ::unlink(tmp.c_str());
    return false;
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    error = fmt::format("{}: cannot rename into place: {}", path, std::strerror(errno));
    ::unlink(tmp.c_str());
    return false;
  }
  return true;
}

}  // namespace dtraced::util
