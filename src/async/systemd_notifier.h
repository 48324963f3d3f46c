// dtraced::async systemd notifier: keeps systemd's watchdog fed and the unit's STATUS= line
// current, from a daemon's event loop.
//
// WATCHDOG=1 is sent by a coroutine on the loop itself, so the pings stop when the loop stops
// turning (a handler that blocks, a deadlock) and systemd restarts the service; a thread of its
// own would keep pinging a wedged daemon. The period is $WATCHDOG_USEC (WatchdogSec=), for this
// process only ($WATCHDOG_PID, when set, must be ours); the pings go every half period, as
// sd_watchdog_enabled(3) advises.
//
// Thread safety: the coroutine belongs to the executor it is spawned on, and calls `status`
// there; the pure functions are stateless.
#pragma once

#include <chrono>
#include <functional>
#include <optional>
#include <string>
#include <string_view>

#include "async/async.h"

namespace dtraced::async {

struct NotifierOptions {
  std::optional<std::chrono::microseconds> watchdog;  // WatchdogSec=, if systemd asks for pings
  std::chrono::milliseconds status_every{5000};       // how often the STATUS= text is recomputed
};

// The watchdog period from $WATCHDOG_USEC's and $WATCHDOG_PID's values (null: unset) for the
// process `self`: nullopt when unset, malformed, zero, or meant for another process.
std::optional<std::chrono::microseconds> watchdog_period(const char* usec, const char* pid, long self);

// Until `stop` is set: "WATCHDOG=1" through `send` every half of options.watchdog (if set), and
// "STATUS=" + status() whenever that text changed, looked at least every options.status_every.
Awaitable<> run_systemd_notifier(const util::Clock& clock, NotifierOptions options, Event& stop,
                                 std::function<std::string()> status, std::function<void(std::string_view)> send);

// Under systemd ($NOTIFY_SOCKET set), spawns run_systemd_notifier on `executor` with the
// environment's watchdog period, sending through util::sd_notify_state; elsewhere does nothing
// (a test's loop gets no extra sleeper). `stop` and `status` must outlive the coroutine.
void start_systemd_notifier(const Executor& executor, const util::Clock& clock, Event& stop,
                            std::function<std::string()> status);

}  // namespace dtraced::async
