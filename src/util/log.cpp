#include "util/log.h"

#include <sys/stat.h>
#include <unistd.h>

#include <charconv>
#include <cstdint>
#include <cstdlib>
#include <system_error>

namespace dtraced::util {

namespace {

struct LevelNames {
  const char* tag;      // the plain format's word
  const char* journal;  // the syslog priority prefix journald reads (sd-daemon.h's SD_ERR etc.)
};

LevelNames names(LogLevel level) {
  switch (level) {
    case LogLevel::kDebug:
      return {"debug", "<7>"};
    case LogLevel::kInfo:
      return {"info", "<6>"};
    case LogLevel::kWarn:
      return {"warning", "<4>"};
    case LogLevel::kError:
      break;
  }
  return {"error", "<3>"};
}

// One unsigned decimal number taking the whole of `text`.
bool parse_number(std::string_view text, std::uint64_t& out) {
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), out);
  return !text.empty() && ec == std::errc() && end == text.data() + text.size();
}

}  // namespace

std::string format_log_line(LogLevel level, std::string_view message, bool journal) {
  const LevelNames n = names(level);
  if (journal) return fmt::format("{}{}\n", n.journal, message);
  return fmt::format("dtraced: {}: {}\n", n.tag, message);
}

bool is_journal_stream(std::string_view journal_stream, int fd) {
  const std::size_t colon = journal_stream.find(':');
  if (colon == std::string_view::npos) return false;
  std::uint64_t device = 0;
  std::uint64_t inode = 0;
  if (!parse_number(journal_stream.substr(0, colon), device) ||
      !parse_number(journal_stream.substr(colon + 1), inode)) {
    return false;
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0) return false;
  return static_cast<std::uint64_t>(st.st_dev) == device && static_cast<std::uint64_t>(st.st_ino) == inode;
}

void log_line(LogLevel level, std::string_view message) {
  // Checked per line rather than cached: no global state, and a getenv and an fstat cost little
  // next to the write.
  const char* stream = std::getenv("JOURNAL_STREAM");
  const bool journal = stream != nullptr && is_journal_stream(stream, STDERR_FILENO);
  const std::string line = format_log_line(level, message, journal);
  // One write(2) per line; a short write to stderr is not worth a retry loop here.
  [[maybe_unused]] const ssize_t n = ::write(STDERR_FILENO, line.data(), line.size());
}

}  // namespace dtraced::util
