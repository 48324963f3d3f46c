// dtraced::util lock file: one process at a time on a directory, by an exclusive flock(2).
//
// Owns: an open descriptor on a lock file holding an exclusive flock, released when the LockFile
// is destroyed (or when the process dies, however it dies: the kernel drops the lock with the
// descriptor, so a killed holder never leaves a stale lock behind). The file itself stays: its
// presence means nothing, only the lock does. After locking, the holder's PID is written into the
// file (overwritten in place, padded to a fixed width, so that on a full disk the write needs no
// new block), so a refused process can say who holds it.
//
// flock locks belong to the open file description: two acquire() calls in one process on the same
// path conflict just as two processes do. Not for network file systems whose flock is local only.
//
// Thread safety: a LockFile is a handle; use it from one thread at a time. acquire() is
// stateless and thread-safe.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "util/result.h"

namespace dtraced::util {

// Why acquire() failed. `holder_pid` is set when another holder was found and its PID could be
// read from the file.
struct LockRefusal {
  Error error;  // "PATH: problem"
  bool held_by_another = false;
  std::optional<std::int64_t> holder_pid;
};

class LockFile {
 public:
  // Opens (creating it with mode 0644 if missing) and locks `path` without waiting, then writes
  // the caller's PID into it. Fails at once when another open file description holds the lock.
  // A failure to write the PID is not a failure to lock: the lock holds, and the PID write is
  // logged as a warning.
  static Result<LockFile, LockRefusal> acquire(const std::string& path);

  LockFile(LockFile&& other) noexcept;
  LockFile& operator=(LockFile&& other) noexcept;
  LockFile(const LockFile&) = delete;
  LockFile& operator=(const LockFile&) = delete;
  ~LockFile();

  const std::string& path() const { return path_; }

 private:
  LockFile(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  int fd_ = -1;
  std::string path_;
};

}  // namespace dtraced::util
