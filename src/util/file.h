// dtraced::util file helpers: bounded reads, atomic writes and the clean-up of their leftovers.
// Stateless: thread-safe.
//
// Failures come back as util::Error{problem, "", path}: to_string() reads "PATH: problem".
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "util/result.h"

namespace dtraced::util {

// Reads a whole file. Fails when the file cannot be opened or read, or is larger than
// `max_bytes`; never allocates more than max_bytes + 1.
Result<std::string> read_file_limited(const std::string& path, std::uint64_t max_bytes);

// Writes `bytes` to `path` through a temporary file in the same directory, flushed and renamed
// over the target, so a reader sees the old file or the new one, never a torn one. The temporary
// file is named PATH.tmp.XXXXXX (mkstemp's six letters or digits) and holds an exclusive flock
// until it is renamed or removed, so remove_stale_temporaries can tell one whose writer died from
// one being written. A process killed mid-write leaves its temporary file behind.
Status write_file_atomic(const std::string& path, std::string_view bytes);

// The target name a temporary file of write_file_atomic stands for ("a.png" for
// "a.png.tmp.Ab3xY9"), or empty when `name` is not of that exact pattern.
std::string_view temporary_target(std::string_view name);

struct TemporaryCleanup {
  std::vector<std::string> removed;  // paths
  std::uint64_t removed_bytes = 0;
  std::vector<Error> failed;  // files that matched but could not be removed, each naming its path
};

// Removes, directly in `dir` (never below it, never through a symbolic link), the temporary files
// of write_file_atomic whose writer died: regular files whose name is TARGET.tmp.XXXXXX with
// `ours(TARGET)` true, and whose flock nobody holds (a live writer's file is left alone). A
// missing `dir` is no error. For start-up, before the files' targets are written again.
TemporaryCleanup remove_stale_temporaries(const std::string& dir,
                                          const std::function<bool(std::string_view target)>& ours);

}  // namespace dtraced::util

namespace dtraced::util {

// What write_file_new found.
enum class NewFile {
  kWritten,  // `path` did not exist and now holds the bytes
  kExists,   // a file of that name exists: nothing was changed
};

// Writes `bytes` to `path` only if nothing of that name exists, never replacing a file: the bytes
// go to a temporary file beside it (written as write_file_atomic writes) which is then link(2)ed
// into place, and link, unlike rename, fails when the name is taken. So two writers of one name,
// in one process or two, cannot overwrite each other: one gets kWritten, the other kExists.
Result<NewFile> write_file_new(const std::string& path, std::string_view bytes);

// Problems with `path` as a file about to be created or replaced: its directory ("." when it has
// none) must exist, be a directory and be writable, and `path` itself must not be a directory.
// The error names the directory or the path. For checks before long work, not a guarantee.
Status check_output_path(const std::string& path);

// An open file descriptor, closed when this goes out of scope (an fd of -1 holds nothing).
class FileHandle {
 public:
  FileHandle() = default;
  explicit FileHandle(int fd) : fd_(fd) {}
  FileHandle(FileHandle&& other) noexcept : fd_(other.release()) {}
  FileHandle& operator=(FileHandle&& other) noexcept;
  FileHandle(const FileHandle&) = delete;
  FileHandle& operator=(const FileHandle&) = delete;
  ~FileHandle();
  int get() const { return fd_; }
  int release() {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }

 private:
  int fd_ = -1;
};

}  // namespace dtraced::util
