// dtraced::util logging: one line per event on stderr. No global logger object; each call
// formats and writes one line with a single write, so lines from different threads do not
// interleave. Stateless: thread-safe.
//
// Under systemd, when stderr is the journal stream ($JOURNAL_STREAM names stderr's device and
// inode, as sd-daemon(3) says to check), each line starts with the journald priority prefix
// (<3> error, <4> warning, <6> info, <7> debug) so `journalctl -p err` finds the errors, and the
// "dtraced: LEVEL:" prefix is left out (the journal records the unit and the priority).
// Anywhere else (a terminal, a file, a pipe) lines read "dtraced: LEVEL: message".
#pragma once

#include <string>
#include <string_view>

#include <fmt/format.h>

namespace dtraced::util {

enum class LogLevel { kDebug, kInfo, kWarn, kError };

void log_line(LogLevel level, std::string_view message);

// The line log_line writes, newline included; `journal`: stderr is the journal stream.
std::string format_log_line(LogLevel level, std::string_view message, bool journal);

// True when `journal_stream` ($JOURNAL_STREAM's "DEVICE:INODE", decimal) names the file open as
// `fd`; false for an empty or malformed value, or another file (a service's stderr redirected
// elsewhere keeps the variable it inherited).
bool is_journal_stream(std::string_view journal_stream, int fd);

template <typename... Args>
void log_debug(fmt::format_string<Args...> f, Args&&... args) {
  log_line(LogLevel::kDebug, fmt::format(f, std::forward<Args>(args)...));
}
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
