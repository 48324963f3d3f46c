#include "util/log.h"

#include <unistd.h>

#include <string>

namespace dtraced::util {

void log_line(LogLevel level, std::string_view message) {
  const char* tag = level == LogLevel::kInfo ? "info" : (level == LogLevel::kWarn ? "warning" : "error");
  std::string line = fmt::format("dtraced: {}: {}\n", tag, message);
  // One write(2) per line; a short write to stderr is not worth a retry loop here.
  [[maybe_unused]] const ssize_t n = ::write(STDERR_FILENO, line.data(), line.size());
}

}  // namespace dtraced::util
