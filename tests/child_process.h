// A forked child for crash tests: the child runs a body that reports on a pipe (what it has made
// durable, say), the parent reads the reports, kills the child with SIGKILL and checks that what
// was reported survived. Shared by the store and collector tests.
//
// In the child there is no Catch2: the body ends every path with _exit, and an alarm ends a child
// whose parent died first.
#pragma once

#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <functional>
#include <string>

#include <catch2/catch.hpp>

namespace dtraced::testing {

class ForkedChild {
 public:
  // Forks; the child runs body(fd), fd the pipe's write end, and must not return.
  explicit ForkedChild(const std::function<void(int fd)>& body) {
    constexpr unsigned kChildLifetimeSeconds = 60;
    int fds[2];
    REQUIRE(::pipe(fds) == 0);
    pid_ = ::fork();
    REQUIRE(pid_ >= 0);
    if (pid_ == 0) {
      ::close(fds[0]);
      ::alarm(kChildLifetimeSeconds);
      body(fds[1]);
      ::_exit(100);
    }
    ::close(fds[1]);
    fd_ = fds[0];
  }
  ForkedChild(const ForkedChild&) = delete;
  ForkedChild& operator=(const ForkedChild&) = delete;
  ~ForkedChild() {
    if (pid_ > 0) reap();
    ::close(fd_);
  }

  // Appends what the child writes to `out` until `enough(out)` holds, the child's end is closed
  // (it died), or `bound` passes. Returns whether `enough` held.
  bool read(std::string& out, const std::function<bool(const std::string&)>& enough, std::chrono::milliseconds bound) {
    const auto deadline = std::chrono::steady_clock::now() + bound;
    char buf[4096];
    while (!enough(out)) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
      pollfd p{fd_, POLLIN, 0};
      if (left.count() <= 0 || ::poll(&p, 1, static_cast<int>(left.count())) <= 0) return false;
      const ssize_t n = ::read(fd_, buf, sizeof buf);
      if (n <= 0) return enough(out);
      out.append(buf, static_cast<std::size_t>(n));
    }
    return true;
  }

  // SIGKILL, then the wait status.
  int kill_and_wait() {
    REQUIRE(pid_ > 0);
    const int status = reap();
    REQUIRE(WIFSIGNALED(status));
    return status;
  }

 private:
  int reap() {
    ::kill(pid_, SIGKILL);
    int status = 0;
    ::waitpid(pid_, &status, 0);
    pid_ = -1;
    return status;
  }

  pid_t pid_ = -1;
  int fd_ = -1;
};

}  // namespace dtraced::testing
