// dtraced::util token files: the farm's bearer token, read from the file an operator names
// (--token-file, for both roles and every client verb).
//
// A token file that cannot be used is the most common first-run failure of a farm (a wrong
// path, a mode the service user cannot read), so every failure says that it is the token file,
// names the path and gives the system's reason. Stateless: thread-safe.
#pragma once

#include <cstddef>
#include <string>

#include "util/result.h"

namespace dtraced::util {

// A token file is one short line; anything larger is not a token file.
inline constexpr std::size_t kMaxTokenFileBytes = 4096;

// The token in the file `path`: its first line without surrounding blanks. Fails, with
// Error{problem, "", path} ("PATH: cannot open the token file: Permission denied"), when the
// file cannot be opened or read, is a directory, is larger than kMaxTokenFileBytes, or holds no
// token.
Result<std::string> read_token_file(const std::string& path);

}  // namespace dtraced::util
