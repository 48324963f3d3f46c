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
