// dtraced::collector writer bridge: the store writer's thread, awaited from the event loop.
//
// Owns: on_writer and commit_tile, which turn store::TileWriter's "run this on your thread, call
// me back" into something a coroutine on the loop co_awaits (through async::Bridge: the result is
// posted back to the awaiting coroutine's executor, and a work guard keeps the loop's run() from
// returning while the store works), and WriterReply, what the writer did with the work.
//
// Thread safety: call from the loop; the work runs on the writer's thread; the reply arrives on
// the loop.
#pragma once

#include <exception>
#include <memory>
#include <optional>
#include <type_traits>
#include <utility>

#include "async/async.h"
#include "store/tile_writer.h"
#include "util/log.h"

namespace dtraced::collector {

// What the store writer did with a task or a tile: refused it (status), or ran it (value; empty
// when the task threw, which is logged).
template <typename R>
struct WriterReply {
  store::SubmitStatus status = store::SubmitStatus::kStopped;
  std::optional<R> value;
  bool ok() const { return status == store::SubmitStatus::kAccepted && value.has_value(); }
};

// Runs f(Store&) on the writer thread, in order with the tiles and tasks around it. As with
// async::on_pool, name the function first and pass it with std::move (see async/async.h).
template <typename F>
auto on_writer(store::TileWriter& writer, F&& f) {
  using Fn = std::decay_t<F>;
  using R = std::invoke_result_t<Fn&, store::Store&>;
  namespace net = async::net;
  return net::async_initiate<decltype(net::use_awaitable), void(WriterReply<R>)>(
      [&writer](auto handler, Fn fn) {
        using Bridge = async::Bridge<decltype(handler)>;
        auto bridge = std::make_shared<Bridge>(std::move(handler));
        const store::SubmitStatus status = writer.post([bridge, fn = std::move(fn)](store::Store& s) mutable {
          WriterReply<R> reply;
          reply.status = store::SubmitStatus::kAccepted;
          try {
            reply.value.emplace(fn(s));
          } catch (const std::exception& e) {
            util::log_error("collector: a store task threw: {}", e.what());
          }
          Bridge::complete(bridge, std::move(reply));
        });
        if (status != store::SubmitStatus::kAccepted) Bridge::complete(bridge, WriterReply<R>{status, std::nullopt});
      },
      net::use_awaitable, Fn(std::forward<F>(f)));
}

// Queues a tile result with the writer; completes after its transaction committed (or failed).
inline auto commit_tile(store::TileWriter& writer, store::TileWrite&& write) {
  namespace net = async::net;
  using Reply = WriterReply<store::CommitResult>;
  return net::async_initiate<decltype(net::use_awaitable), void(Reply)>(
      [&writer](auto handler, store::TileWrite w) {
        using Bridge = async::Bridge<decltype(handler)>;
        auto bridge = std::make_shared<Bridge>(std::move(handler));
        const store::SubmitStatus status = writer.submit(std::move(w), [bridge](store::CommitResult result) {
          Bridge::complete(bridge, Reply{store::SubmitStatus::kAccepted, std::move(result)});
        });
        if (status != store::SubmitStatus::kAccepted) Bridge::complete(bridge, Reply{status, std::nullopt});
      },
      net::use_awaitable, store::TileWrite(std::move(write)));
}

}  // namespace dtraced::collector
