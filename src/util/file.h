// dtraced::util file helpers: bounded reads and atomic writes. Stateless: thread-safe.
//
// Failures come back as util::Error{problem, "", path}: to_string() reads "PATH: problem".
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "util/result.h"

namespace dtraced::util {

// Reads a whole file. Fails when the file cannot be opened or read, or is larger than
// `max_bytes`; never allocates more than max_bytes + 1.
Result<std::string> read_file_limited(const std::string& path, std::uint64_t max_bytes);

// Writes `bytes` to `path` through a temporary file in the same directory, flushed and renamed
// over the target, so a reader sees the old file or the new one, never a torn one.
Status write_file_atomic(const std::string& path, std::string_view bytes);

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

}  // namespace dtraced::util
