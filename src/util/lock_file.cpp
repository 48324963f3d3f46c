#include "util/lock_file.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <charconv>
#include <cstring>
#include <string_view>
#include <utility>

#include <fmt/format.h>

#include "util/log.h"

namespace dtraced::util {
namespace {

// A PID, then spaces up to this width, then a newline: every holder writes the same number of
// bytes at offset 0, so the file never grows past its first block and never keeps a longer PID's
// tail.
constexpr std::size_t kPidFieldBytes = 20;

std::optional<std::int64_t> read_pid(int fd) {
  char buf[kPidFieldBytes + 2] = {};
  const ssize_t n = ::pread(fd, buf, sizeof buf - 1, 0);
  if (n <= 0) return std::nullopt;
  std::string_view text(buf, static_cast<std::size_t>(n));
  while (!text.empty() && (text.back() == '\n' || text.back() == ' ')) text.remove_suffix(1);
  std::int64_t pid = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), pid);
  if (ec != std::errc() || end != text.data() + text.size() || pid <= 0) return std::nullopt;
  return pid;
}

Status write_pid(int fd, const std::string& path) {
  const std::string line = fmt::format("{:<{}}\n", ::getpid(), kPidFieldBytes);
  const ssize_t n = ::pwrite(fd, line.data(), line.size(), 0);
  if (n != static_cast<ssize_t>(line.size())) {
    return Error(
        fmt::format("cannot write the PID into the lock file: {}", n < 0 ? std::strerror(errno) : "short write"), "",
        path);
  }
  // An older, longer format would leave a tail; the fixed width makes this a no-op in practice.
  if (::ftruncate(fd, static_cast<off_t>(line.size())) != 0) {
    return Error(fmt::format("cannot trim the lock file: {}", std::strerror(errno)), "", path);
  }
  return {};
}

}  // namespace

Result<LockFile, LockRefusal> LockFile::acquire(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (fd < 0) {
    return LockRefusal{Error(fmt::format("cannot open the lock file: {}", std::strerror(errno)), "", path), false, {}};
  }
  int rc;
  do {
    rc = ::flock(fd, LOCK_EX | LOCK_NB);
  } while (rc != 0 && errno == EINTR);
  if (rc != 0) {
    const int err = errno;
    LockRefusal refusal{Error(fmt::format("cannot lock: {}", std::strerror(err)), "", path), err == EWOULDBLOCK, {}};
    if (refusal.held_by_another) {
      refusal.holder_pid = read_pid(fd);
      refusal.error.message = refusal.holder_pid ? fmt::format("locked by process {}", *refusal.holder_pid)
                                                 : std::string("locked by another process (its PID is not recorded)");
    }
    ::close(fd);
    return refusal;
  }
  if (Status written = write_pid(fd, path); !written) log_warn("{}", written.error().to_string());
  return LockFile(fd, path);
}

LockFile::LockFile(LockFile&& other) noexcept : fd_(std::exchange(other.fd_, -1)), path_(std::move(other.path_)) {}

LockFile& LockFile::operator=(LockFile&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = std::exchange(other.fd_, -1);
    path_ = std::move(other.path_);
  }
  return *this;
}

LockFile::~LockFile() {
  // Closing the last descriptor of the open file description releases the flock.
  if (fd_ >= 0) ::close(fd_);
}

}  // namespace dtraced::util
