#include "async/async.h"

#include <boost/asio/experimental/awaitable_operators.hpp>
#include <boost/asio/this_coro.hpp>

#include "util/log.h"

namespace dtraced::async {

using namespace net::experimental::awaitable_operators;

void log_exception(std::string_view what, const std::exception_ptr& error) {
  if (!error) return;
  try {
    std::rethrow_exception(error);
  } catch (const std::exception& e) {
    util::log_error("{} failed: {}", what, e.what());
  } catch (...) {
    util::log_error("{} failed with an unknown exception", what);
  }
}

namespace {

// The timer a sleeper waits on. Shared with the clock's wake, which may run on another thread
// after the sleep has ended: it then cancels a timer nobody waits on any more.
struct Sleeper {
  explicit Sleeper(const Executor& executor) : timer(executor, TimePoint::max()) {}
  net::steady_timer timer;
};

// Forgets the clock's wake when the sleep ends, however it ends.
class WakeGuard {
 public:
  WakeGuard(const util::Clock& clock, std::uint64_t id) : clock_(clock), id_(id) {}
  ~WakeGuard() { clock_.cancel_wake(id_); }
  WakeGuard(const WakeGuard&) = delete;
  WakeGuard& operator=(const WakeGuard&) = delete;

 private:
  const util::Clock& clock_;
  std::uint64_t id_;
};

}  // namespace

Awaitable<> sleep_until(const util::Clock& clock, TimePoint deadline, Event* wake) {
  const Executor executor = co_await net::this_coro::executor;
  auto sleeper = std::make_shared<Sleeper>(executor);
  // A manual clock calls this from the thread that moves it (or at once, when the deadline has
  // passed). The cancel is posted, so it runs on this executor after the wait below has begun.
  const std::uint64_t id =
      clock.wake_at(deadline, [sleeper, executor] { net::post(executor, [sleeper] { sleeper->timer.cancel(); }); });
  const WakeGuard guard(clock, id);
  if (id == 0) sleeper->timer.expires_at(deadline);  // the real clock: a real timer
  if (wake != nullptr) {
    co_await (sleeper->timer.async_wait(kAwaitTuple) || wake->wait());
  } else {
    co_await sleeper->timer.async_wait(kAwaitTuple);
  }
}

Awaitable<> sleep_for(const util::Clock& clock, util::SteadyClock::duration d, Event* wake) {
  co_await sleep_until(clock, clock.now() + d, wake);
}

}  // namespace dtraced::async
