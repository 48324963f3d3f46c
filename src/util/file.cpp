#include "util/file.h"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <system_error>

#include <fmt/format.h>

namespace dtraced::util {

Result<std::string> read_file_limited(const std::string& path, std::uint64_t max_bytes) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return Error(fmt::format("cannot open: {}", std::strerror(errno)), "", path);
  }
  std::string data;
  char buf[1 << 16];
  while (in) {
    in.read(buf, sizeof buf);
    const auto got = static_cast<std::uint64_t>(in.gcount());
    if (data.size() + got > max_bytes) {
      return Error(fmt::format("file is larger than the limit of {} bytes", max_bytes), "", path);
    }
    data.append(buf, static_cast<std::size_t>(got));
  }
  if (in.bad()) {
    return Error("read error", "", path);
  }
  return data;
}

Status write_file_atomic(const std::string& path, std::string_view bytes) {
  // mkstemp gives a name no other thread or process is using, in the target's directory so the
  // rename stays on one file system.
  std::string tmp = path + ".tmp.XXXXXX";
  const int fd = ::mkstemp(tmp.data());
  if (fd < 0) {
    return Error(fmt::format("cannot create a temporary file: {}", std::strerror(errno)), "", path);
  }
  // Held until the file is renamed or removed (closing releases it): a clean-up at start-up
  // leaves a temporary file alone while its writer lives. A clean-up that takes the file between
  // mkstemp and this flock removes it; the rename then fails and the caller retries.
  ::flock(fd, LOCK_EX | LOCK_NB);
  auto fail = [&](const char* what) -> Status {
    Error error(fmt::format("{}: {}", what, std::strerror(errno)), "", path);
    ::close(fd);
    ::unlink(tmp.c_str());
    return error;
  };
  if (::fchmod(fd, 0644) != 0) return fail("cannot set permissions");
  std::size_t off = 0;
  while (off < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + off, bytes.size() - off);
    if (n < 0) {
      if (errno == EINTR) continue;
      return fail("write failed");
    }
    off += static_cast<std::size_t>(n);
  }
  if (::fsync(fd) != 0) return fail("flush failed");
  if (::close(fd) != 0) {
    Error error(fmt::format("close failed: {}", std::strerror(errno)), "", path);
    ::unlink(tmp.c_str());
    return error;
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    Error error(fmt::format("cannot rename into place: {}", std::strerror(errno)), "", path);
    ::unlink(tmp.c_str());
    return error;
  }
  // The rename itself is durable only once the directory is synced.
  const std::string dir = std::filesystem::path(path).parent_path().string();
  const int dfd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    ::fsync(dfd);
    ::close(dfd);
  }
  return {};
}

std::string_view temporary_target(std::string_view name) {
  constexpr std::string_view kInfix = ".tmp.";
  constexpr std::size_t kRandomChars = 6;  // mkstemp's XXXXXX
  if (name.size() <= kInfix.size() + kRandomChars) return {};
  const std::string_view random = name.substr(name.size() - kRandomChars);
  const bool alnum = std::all_of(random.begin(), random.end(), [](char ch) {
    return (ch >= 'a' && ch <= 'z') || (ch >= 'A' && ch <= 'Z') || (ch >= '0' && ch <= '9');
  });
  const std::string_view head = name.substr(0, name.size() - kRandomChars);
  if (!alnum || !head.ends_with(kInfix)) return {};
  return head.substr(0, head.size() - kInfix.size());
}

TemporaryCleanup remove_stale_temporaries(const std::string& dir,
                                          const std::function<bool(std::string_view target)>& ours) {
  TemporaryCleanup cleanup;
  std::error_code ec;
  std::filesystem::directory_iterator it(dir, ec);
  if (ec) {
    if (ec != std::errc::no_such_file_or_directory) {
      cleanup.failed.push_back(Error(fmt::format("cannot list the directory: {}", ec.message()), "", dir));
    }
    return cleanup;
  }
  for (; it != std::filesystem::directory_iterator(); it.increment(ec)) {
    const std::string name = it->path().filename().string();
    const std::string_view target = temporary_target(name);
    if (target.empty() || !ours(target)) continue;
    const std::string path = it->path().string();
    // O_NOFOLLOW and the fstat: only a regular file of this directory, never what a link points to.
    const int fd = ::open(path.c_str(), O_RDONLY | O_NOFOLLOW | O_CLOEXEC | O_NONBLOCK);
    if (fd < 0) continue;  // gone already, or a symbolic link
    struct stat st {};
    if (::fstat(fd, &st) == 0 && S_ISREG(st.st_mode) && ::flock(fd, LOCK_EX | LOCK_NB) == 0) {
      if (::unlink(path.c_str()) == 0) {
        cleanup.removed.push_back(path);
        cleanup.removed_bytes += static_cast<std::uint64_t>(st.st_size);
      } else {
        cleanup.failed.push_back(Error(fmt::format("cannot remove: {}", std::strerror(errno)), "", path));
      }
    }
    ::close(fd);
  }
  if (ec) cleanup.failed.push_back(Error(fmt::format("cannot list the directory: {}", ec.message()), "", dir));
  return cleanup;
}

}  // namespace dtraced::util

namespace dtraced::util {

Result<NewFile> write_file_new(const std::string& path, std::string_view bytes) {
  // A staging name of the same pattern as write_file_atomic's temporary files, reserved with
  // mkstemp, filled (atomically, flushed) by write_file_atomic, then linked to `path`.
  std::string staging = path + ".tmp.XXXXXX";
  const int fd = ::mkstemp(staging.data());
  if (fd < 0) {
    return Error(fmt::format("cannot create a temporary file: {}", std::strerror(errno)), "", path);
  }
  ::close(fd);
  if (Status written = write_file_atomic(staging, bytes); !written) {
    ::unlink(staging.c_str());
    return written.error();
  }
  const int linked = ::link(staging.c_str(), path.c_str());
  const int link_errno = errno;
  ::unlink(staging.c_str());
  if (linked != 0) {
    if (link_errno == EEXIST) return NewFile::kExists;
    return Error(fmt::format("cannot link into place: {}", std::strerror(link_errno)), "", path);
  }
  const std::string dir = std::filesystem::path(path).parent_path().string();
  const int dfd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    ::fsync(dfd);
    ::close(dfd);
  }
  return NewFile::kWritten;
}

Status check_output_path(const std::string& path) {
  const std::filesystem::path p(path);
  const std::string dir = p.has_parent_path() ? p.parent_path().string() : std::string(".");
  struct stat st {};
  if (::stat(dir.c_str(), &st) != 0) {
    return Error(fmt::format("the output directory does not exist ({})", std::strerror(errno)), "", dir);
  }
  if (!S_ISDIR(st.st_mode)) return Error("the output's directory is not a directory", "", dir);
  if (::access(dir.c_str(), W_OK | X_OK) != 0) {
    return Error(fmt::format("the output directory is not writable ({})", std::strerror(errno)), "", dir);
  }
  if (::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode)) return Error("the output is a directory", "", path);
  return {};
}

FileHandle& FileHandle::operator=(FileHandle&& other) noexcept {
  if (this != &other) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = other.release();
  }
  return *this;
}

FileHandle::~FileHandle() {
  if (fd_ >= 0) ::close(fd_);
}

}  // namespace dtraced::util
