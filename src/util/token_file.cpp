#include "util/token_file.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>
#include <utility>

#include <fmt/format.h>

#include "util/file.h"

namespace dtraced::util {

namespace {

Error token_error(const std::string& path, std::string problem) { return Error(std::move(problem), "", path); }

// The first line of `text` without the blanks around it.
std::string first_line_trimmed(const std::string& text) {
  std::string line = text.substr(0, text.find('\n'));
  const std::size_t start = line.find_first_not_of(" \t\r");
  if (start == std::string::npos) return {};
  const std::size_t end = line.find_last_not_of(" \t\r");
  return line.substr(start, end - start + 1);
}

}  // namespace

Result<std::string> read_token_file(const std::string& path) {
  const FileHandle fd(::open(path.c_str(), O_RDONLY | O_CLOEXEC));
  if (fd.get() < 0) return token_error(path, fmt::format("cannot open the token file: {}", std::strerror(errno)));
  struct stat st {};
  if (::fstat(fd.get(), &st) == 0 && S_ISDIR(st.st_mode)) {
    return token_error(path, "the token file is a directory; give the file that holds the token");
  }
  std::string text;
  char buf[1024];
  for (;;) {
    const ssize_t got = ::read(fd.get(), buf, sizeof buf);
    if (got < 0 && errno == EINTR) continue;
    if (got < 0) return token_error(path, fmt::format("cannot read the token file: {}", std::strerror(errno)));
    if (got == 0) break;
    text.append(buf, static_cast<std::size_t>(got));
    if (text.size() > kMaxTokenFileBytes) {
      return token_error(path, fmt::format("the token file is larger than {} bytes", kMaxTokenFileBytes));
    }
  }
  std::string token = first_line_trimmed(text);
  if (token.empty()) return token_error(path, "the token file is empty (the token is its first line)");
  return token;
}

}  // namespace dtraced::util
