// dtraced::util logging under systemd: journald priority prefixes when stderr is the journal
// stream ($JOURNAL_STREAM names its device and inode), the plain format anywhere else.
#include <fcntl.h>
#include <stdlib.h>
#include <sys/stat.h>
#include <unistd.h>

#include <fstream>
#include <iterator>
#include <string>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "temp_dir.h"
#include "util/log.h"

namespace {

using dtraced::util::format_log_line;
using dtraced::util::is_journal_stream;
using dtraced::util::LogLevel;

std::string device_inode(int fd) {
  struct stat st {};
  REQUIRE(::fstat(fd, &st) == 0);
  return fmt::format("{}:{}", st.st_dev, st.st_ino);
}

std::string read_all(const std::string& path) {
  std::ifstream in(path);
  return {std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>()};
}

// Runs `log` with stderr sent to a file and $JOURNAL_STREAM set to `journal_stream` (or to the
// file's own device:inode when `journal_stream` is "self"); returns what was written.
template <typename F>
std::string captured_stderr(const std::string& journal_stream, F log) {
  dtraced::testing::TempDir dir("dtraced-log");
  const std::string path = (dir.path() / "stderr").string();
  const int file = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  REQUIRE(file >= 0);
  const int saved = ::dup(STDERR_FILENO);
  REQUIRE(saved >= 0);
  REQUIRE(::dup2(file, STDERR_FILENO) == STDERR_FILENO);
  const std::string value = journal_stream == "self" ? device_inode(file) : journal_stream;
  ::setenv("JOURNAL_STREAM", value.c_str(), 1);
  log();
  ::unsetenv("JOURNAL_STREAM");
  ::dup2(saved, STDERR_FILENO);
  ::close(saved);
  ::close(file);
  return read_all(path);
}

}  // namespace

TEST_CASE("a log line carries the journald priority of its level only for the journal", "[util][log]") {
  CHECK(format_log_line(LogLevel::kError, "disk full", true) == "<3>disk full\n");
  CHECK(format_log_line(LogLevel::kWarn, "slow", true) == "<4>slow\n");
  CHECK(format_log_line(LogLevel::kInfo, "listening", true) == "<6>listening\n");
  CHECK(format_log_line(LogLevel::kDebug, "lease", true) == "<7>lease\n");
  CHECK(format_log_line(LogLevel::kError, "disk full", false) == "dtraced: error: disk full\n");
  CHECK(format_log_line(LogLevel::kWarn, "slow", false) == "dtraced: warning: slow\n");
  CHECK(format_log_line(LogLevel::kInfo, "listening", false) == "dtraced: info: listening\n");
  CHECK(format_log_line(LogLevel::kDebug, "lease", false) == "dtraced: debug: lease\n");
}

TEST_CASE("JOURNAL_STREAM counts only when it names the very file descriptor", "[util][log]") {
  dtraced::testing::TempDir dir("dtraced-log");
  const int fd = ::open((dir.path() / "f").c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0600);
  REQUIRE(fd >= 0);
  const std::string self = device_inode(fd);
  CHECK(is_journal_stream(self, fd));
  struct stat st {};
  REQUIRE(::fstat(fd, &st) == 0);
  CHECK_FALSE(is_journal_stream(fmt::format("{}:{}", st.st_dev, st.st_ino + 1), fd));
  CHECK_FALSE(is_journal_stream(fmt::format("{}:{}", st.st_dev + 1, st.st_ino), fd));
  for (const char* bad : {"", ":", "12", "12:", ":34", "a:b", "12:34x", "-1:5", "1:2:3", "99999999999999999999999:1"}) {
    INFO(bad);
    CHECK_FALSE(is_journal_stream(bad, fd));
  }
  CHECK_FALSE(is_journal_stream(self, -1));
  ::close(fd);
}

TEST_CASE("log lines go to stderr with priorities under the journal and plain elsewhere", "[util][log]") {
  const std::string journal = captured_stderr("self", [] {
    dtraced::util::log_error("cannot open {}", "x.db");
    dtraced::util::log_info("listening on port {}", 7878);
  });
  CHECK(journal == "<3>cannot open x.db\n<6>listening on port 7878\n");
  // A stream inherited from a parent whose stderr was the journal: ours is a file now.
  const std::string inherited = captured_stderr("1:1", [] { dtraced::util::log_warn("slow"); });
  CHECK(inherited == "dtraced: warning: slow\n");
}
