#include "async/systemd_notifier.h"

#include <unistd.h>

#include <algorithm>
#include <charconv>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <system_error>
#include <utility>

#include <boost/asio/co_spawn.hpp>

#include "util/sd_notify.h"

namespace dtraced::async {

namespace {

// A positive decimal number taking the whole of `text`.
std::optional<std::uint64_t> positive_number(const char* text) {
  if (text == nullptr) return std::nullopt;
  const char* end = text + std::strlen(text);
  std::uint64_t value = 0;
  const auto [stop, ec] = std::from_chars(text, end, value);
  if (ec != std::errc() || stop != end || stop == text || value == 0) return std::nullopt;
  return value;
}

// Below this the loop would do little but ping; systemd's own floor for WatchdogSec= is 1 ms,
// but no sane unit asks for less than this.
constexpr std::chrono::milliseconds kMinTick{10};

}  // namespace

std::optional<std::chrono::microseconds> watchdog_period(const char* usec, const char* pid, long self) {
  const std::optional<std::uint64_t> period = positive_number(usec);
  // Bounded so that the arithmetic below cannot overflow (a year is plenty).
  constexpr std::uint64_t kMaxUsec = std::uint64_t{365} * 24 * 3600 * 1000000;
  if (!period || *period > kMaxUsec) return std::nullopt;
  if (pid != nullptr) {
    const std::optional<std::uint64_t> for_pid = positive_number(pid);
    if (!for_pid || *for_pid != static_cast<std::uint64_t>(self)) return std::nullopt;
  }
  return std::chrono::microseconds(*period);
}

Awaitable<> run_systemd_notifier(const util::Clock& clock, NotifierOptions options, Event& stop,
                                 std::function<std::string()> status, std::function<void(std::string_view)> send) {
  auto tick = std::chrono::duration_cast<util::SteadyClock::duration>(options.status_every);
  if (options.watchdog)
    tick = std::min(tick, std::chrono::duration_cast<util::SteadyClock::duration>(*options.watchdog / 2));
  tick = std::max<util::SteadyClock::duration>(tick, kMinTick);
  std::string last_status;
  TimePoint status_due = clock.now();
  while (!stop.is_set()) {
    if (options.watchdog) send("WATCHDOG=1");
    if (clock.now() >= status_due) {
      std::string text = "STATUS=" + status();
      if (text != last_status) send(text);
      last_status = std::move(text);
      status_due = clock.now() + options.status_every;
    }
    co_await sleep_for(clock, tick, &stop);
  }
}

void start_systemd_notifier(const Executor& executor, const util::Clock& clock, Event& stop,
                            std::function<std::string()> status) {
  const char* socket = std::getenv("NOTIFY_SOCKET");
  if (socket == nullptr || socket[0] == '\0') return;
  NotifierOptions options;
  options.watchdog = watchdog_period(std::getenv("WATCHDOG_USEC"), std::getenv("WATCHDOG_PID"), ::getpid());
  net::co_spawn(executor,
                run_systemd_notifier(clock, options, stop, std::move(status),
                                     [](std::string_view state) { util::sd_notify_state(state); }),
                log_failure("the systemd notifier"));
}

}  // namespace dtraced::async
