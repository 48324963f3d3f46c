// dtraced::util file helpers: bounded reads and atomic writes. Stateless: thread-safe.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

namespace dtraced::util {

// Reads a whole file. Fails (returns nullopt and sets `error`) when the file cannot be opened or
// read, or is larger than `max_bytes`; never allocates more than max_bytes + 1.
std::optional<std::string> read_file_limited(const std::string& path, std::uint64_t max_bytes, std::string& error);

// Writes `bytes` to `path` through a temporary file in the same directory, flushed and renamed
// over the target, so a reader sees the old file or the new one, never a torn one.
bool write_file_atomic(const std::string& path, std::string_view bytes, std::string& error);

}  // namespace dtraced::util
