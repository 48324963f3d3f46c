#include "collector/stop.h"

#include <chrono>
#include <exception>
#include <memory>
#include <utility>
#include <vector>

#include <boost/asio/co_spawn.hpp>

#include "util/log.h"
#include "util/sd_notify.h"

namespace dtraced::collector {
namespace {

namespace net = async::net;

// Drains the store writer and closes the database, off the loop: stop() blocks until every
// accepted tile is committed, and its callbacks post here.
async::Awaitable<> close_store(Context& c) {
  if (c.writer) {
    std::unique_ptr<store::TileWriter> writer = std::move(c.writer);
    c.last_writer_stats = writer->stats();
    auto drain = [&writer] {
      writer->stop();
      writer.reset();  // closes the database
      return true;
    };
    co_await async::on_pool(c.pool, std::move(drain));
  }
  auto close_reads = [&reader = c.reader] {
    reader.close();
    return true;
  };
  co_await async::on_pool(c.pool, std::move(close_reads));
}

async::Awaitable<> stop_sequence(Context& c) {
  util::sd_notify_state("STOPPING=1");
  util::log_info("collector: stopping (grace {} ms)", c.config.shutdown_grace.count());
  const util::TimePoint deadline = c.clock.now() + c.config.shutdown_grace;
  if (c.server) co_await c.server->stop(c.config.shutdown_grace);
  // Images being written: let them finish within the grace, so their jobs are marked done.
  while (c.finishes_in_flight > 0 && c.clock.now() < deadline) {
    async::Event ended(c.ioc->get_executor());
    c.finish_ended_event = &ended;
    co_await async::sleep_until(c.clock, deadline, &ended);
    c.finish_ended_event = nullptr;
  }
  if (c.finishes_in_flight > 0) {
    util::log_warn("collector: {} image(s) still being written at the end of the grace; a restart writes them",
                   c.finishes_in_flight);
  }
  co_await close_store(c);
  // Nothing of this collector uses the state directory any more: another may open it now, even
  // while this object lives on (a test, or a tool that stops one collector and opens the next).
  c.state_lock.reset();
  util::log_info("collector: stopped; the database is closed");
}

async::Awaitable<> linger(Context& c, int exit_code) {
  while (!c.stopping && !c.linger->over(c.clock.now())) {
    co_await async::sleep_until(c.clock, c.linger->deadline(), &*c.linger_wake);
  }
  if (c.stopping) co_return;  // a stop (a signal) came first; the exit code set at the start stays
  if (!c.linger->everyone_told()) {
    util::log_info("collector: {} worker(s) did not ask again before the linger ended; stopping", c.linger->untold());
  }
  begin_stop(c, exit_code);
}

}  // namespace

void begin_linger(Context& c, int exit_code) {
  if (c.stopping || c.linger) return;
  const std::vector<WorkerId> to_tell = workers_to_tell(c.workers, c.clock.now());
  if (to_tell.empty()) {
    begin_stop(c, exit_code);
    return;
  }
  // A signal during the linger stops at once, but with the job's exit code.
  if (!c.exit_code) c.exit_code = exit_code;
  const Duration bound = linger_bound(c.config.queue);
  c.linger.emplace(to_tell, c.clock.now() + bound);
  c.linger_wake.emplace(c.ioc->get_executor());
  util::log_info("collector: all work finished; telling {} worker(s) before stopping (at most {} ms)", to_tell.size(),
                 std::chrono::duration_cast<std::chrono::milliseconds>(bound).count());
  net::co_spawn(*c.ioc, linger(c, exit_code), [&c](const std::exception_ptr& error) {
    if (!error) return;
    async::log_exception("collector: lingering", error);
    begin_stop(c, 1);
  });
}

void linger_told(Context& c, const WorkerId& id) {
  if (!c.linger) return;
  c.linger->told(id);
  if (c.linger->everyone_told()) c.linger_wake->set();
}

void begin_stop(Context& c, int exit_code) {
  if (c.stopping) return;
  c.stopping = true;
  if (c.linger_wake) c.linger_wake->set();
  if (!c.exit_code) c.exit_code = exit_code;
  c.stop_begun->set();  // a finish retry waiting for its delay gives up
  net::co_spawn(*c.ioc, stop_sequence(c), [&c](const std::exception_ptr& error) {
    async::log_exception("collector: stopping", error);
    c.ioc->stop();  // whatever happened, run() returns
  });
}

}  // namespace dtraced::collector
