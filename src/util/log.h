// dtraced::util logging: one line per event on stderr (journald keeps them). No global logger
// object; each call formats and writes one line with a single write, so lines from different
// threads do not interleave.
#pragma once

#include <string_view>

#include <fmt/format.h>

namespace dtraced::util {

enum class LogLevel { kInfo, kWarn, kError };

void log_line(LogLevel level, std::string_view message);

template <typename... Args>
void log_info(fmt::format_string<Args...> f, Args&&... args) {
  log_line(LogLevel::kInfo, fmt::format(f, std::forward<Args>(args)...));
}
template <typename... Args>
void log_warn(fmt::format_string<Args...> f, Args&&... args) {
  log_line(LogLevel::kWarn, fmt::format(f, std::forward<Args>(args)...));
}
template <typename... Args>
void log_error(fmt::format_string<Args...> f, Args&&... args) {
  log_line(LogLevel::kError, fmt::format(f, std::forward<Args>(args)...));
}

}  // namespace dtraced::util
