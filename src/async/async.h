// dtraced::async: the coroutine toolkit both daemons and the HTTP layer share, in one header.
//
// Owns: the Asio names every coroutine module uses; log_exception and the completion handler
// that logs what a co_spawn'ed coroutine threw (nothing is detached silently); Bridge/on_pool,
// which run work on another thread and resume the awaiting coroutine on its own executor;
// Signal and Event, a condition variable and a one-shot flag for coroutines on one executor; and
// sleep_until, the only way a daemon sleeps, on the injected util::Clock (a real timer for the
// real clock, ManualClock's wake list for a test's).
//
// Thread safety: Signal, Event and the sleeps belong to one executor (one thread: the daemon's
// event loop). on_pool and Bridge are made to be completed from any thread.
#pragma once

#include <exception>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

#include <boost/asio/any_io_executor.hpp>
#include <boost/asio/as_tuple.hpp>
#include <boost/asio/associated_executor.hpp>
#include <boost/asio/async_result.hpp>
#include <boost/asio/awaitable.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/asio/use_awaitable.hpp>

#include "util/clock.h"

namespace dtraced::async {

namespace net = boost::asio;
using Executor = net::any_io_executor;
template <typename T = void>
using Awaitable = net::awaitable<T>;
using util::TimePoint;

// co_await op(kAwaitTuple): errors come back as values instead of exceptions.
inline constexpr auto kAwaitTuple = net::as_tuple(net::use_awaitable);

// Logs "WHAT failed: MESSAGE" at error level when `error` holds an exception; nothing otherwise.
void log_exception(std::string_view what, const std::exception_ptr& error);

// A co_spawn completion handler that logs what the coroutine threw:
//   net::co_spawn(ex, run(), async::log_failure("the signal watcher"));
inline auto log_failure(std::string what) {
  return [what = std::move(what)](const std::exception_ptr& error) { log_exception(what, error); };
}

// ---- bridges from other threads back to the loop --------------------------------------------
//
// Each turns "run this elsewhere, call me back" into something a coroutine can co_await. The
// completion is posted to the awaiting coroutine's executor, and a work guard keeps that
// executor's run() from returning while the operation is out (so a test that runs the loop until
// it is idle waits for it).

template <typename Handler>
class Bridge {
 public:
  explicit Bridge(Handler h)
      : handler_(std::move(h)), work_(net::make_work_guard(net::get_associated_executor(*handler_))) {}

  // Resumes the handler with `args` on its executor. Call once, from any thread.
  template <typename... Args>
  static void complete(const std::shared_ptr<Bridge>& self, Args... args) {
    auto executor = self->work_.get_executor();
    net::post(executor, [self, ... args = std::move(args)]() mutable {
      Handler handler = std::move(*self->handler_);
      self->handler_.reset();
      self->work_.reset();
      std::move(handler)(std::move(args)...);
    });
  }

 private:
  std::optional<Handler> handler_;
  net::executor_work_guard<net::associated_executor_t<Handler>> work_;
};

// GCC 12 destroys a prvalue argument of a call inside a co_await expression twice when the
// coroutine resumes (a lambda's captured string was freed by both copies; seen with g++ 12.2).
// So the bridges take their function by reference and callers name it first:
//   auto task = [...] { ... };
//   auto result = co_await async::on_pool(pool, std::move(task));

// Runs f() on `pool`; the awaiting coroutine gets its result or its exception, on its own
// executor. The result type must be default-constructible. Lambdas given here capture by value,
// or by reference only what the awaiting coroutine's frame keeps alive while it waits.
template <typename F>
auto on_pool(net::thread_pool& pool, F&& f) {
  using Fn = std::decay_t<F>;
  using R = std::invoke_result_t<Fn&>;
  return net::async_initiate<decltype(net::use_awaitable), void(std::exception_ptr, R)>(
      [&pool](auto handler, Fn fn) {
        auto bridge = std::make_shared<Bridge<decltype(handler)>>(std::move(handler));
        net::post(pool, [bridge, fn = std::move(fn)]() mutable {
          std::exception_ptr error;
          R result{};
          try {
            result = fn();
          } catch (...) {
            error = std::current_exception();
          }
          Bridge<decltype(handler)>::complete(bridge, error, std::move(result));
        });
      },
      net::use_awaitable, Fn(std::forward<F>(f)));
}

// ---- waiting on one executor ------------------------------------------------------------------

// Wakes every coroutine waiting on it: a condition variable for one thread (the idiom of Asio's
// chat_server example: a timer that never expires, cancelled to notify). Waiters re-check their
// condition after waking.
class Signal {
 public:
  explicit Signal(const Executor& executor) : timer_(executor, TimePoint::max()) {}

  void notify_all() { timer_.cancel(); }

  // Returns after the next notify_all(), or when the awaiting coroutine is cancelled.
  Awaitable<> wait() { co_await timer_.async_wait(kAwaitTuple); }

 private:
  net::steady_timer timer_;
};

// A flag that, once set, stays set; setting it wakes its waiters.
class Event {
 public:
  explicit Event(const Executor& executor) : signal_(executor) {}

  void set() {
    if (set_) return;
    set_ = true;
    signal_.notify_all();
  }
  bool is_set() const { return set_; }

  // Returns once set, or when the awaiting coroutine is cancelled.
  Awaitable<> wait() {
    if (!set_) co_await signal_.wait();
  }

 private:
  Signal signal_;
  bool set_ = false;
};

// Sleeps until `clock` reaches `deadline`; returns early when `wake` (if given) is set, or when
// the awaiting coroutine is cancelled.
Awaitable<> sleep_until(const util::Clock& clock, TimePoint deadline, Event* wake = nullptr);

// sleep_until(clock, clock.now() + d, wake).
Awaitable<> sleep_for(const util::Clock& clock, util::SteadyClock::duration d, Event* wake = nullptr);

}  // namespace dtraced::async
