#include "collector/context.h"

#include <algorithm>
#include <utility>

namespace dtraced::collector {

Context::Context(CollectorConfig config_in, const util::Clock& clock_in)
    : config(std::move(config_in)),
      clock(clock_in),
      token(config.token),
      ioc(std::make_unique<async::net::io_context>(1)),
      pool(std::clamp<std::size_t>(config.cpu_threads, 1, kMaxCpuThreads)),
      stop_begun(std::in_place, ioc->get_executor()),
      reader(config.state_dir, config.image_memory_bytes),
      queue(config.queue),
      workers(config.workers),
      started(clock.now()) {}

Context::~Context() {
  // Order matters: everything that posts into the io_context (the writer's callbacks, the
  // pool's completions) ends first; then the io_context is destroyed, which destroys the
  // coroutines still suspended on it while every member they refer to still exists.
  if (writer) writer->stop();
  pool.join();
  server.reset();
  // Timers of the loop go before it: an Event destroyed after its io_context touches freed memory.
  stop_begun.reset();
  linger_wake.reset();
  ioc.reset();
}

JobRecord* Context::find_job(JobId id) {
  const auto it = jobs.find(id);
  return it == jobs.end() ? nullptr : &it->second;
}

const JobRecord* Context::find_job(JobId id) const {
  const auto it = jobs.find(id);
  return it == jobs.end() ? nullptr : &it->second;
}

std::shared_ptr<const std::string> Context::intern_scene(const std::string& digest, std::string json) {
  auto& slot = scenes[digest];
  if (auto existing = slot.lock()) return existing;
  auto text = std::make_shared<const std::string>(std::move(json));
  slot = text;
  // Forget entries of scenes no unfinished job uses any more.
  std::erase_if(scenes, [](const auto& entry) { return entry.second.expired(); });
  return text;
}

std::size_t Context::unfinished_jobs() const {
  return static_cast<std::size_t>(
      std::count_if(jobs.begin(), jobs.end(), [](const auto& entry) { return entry.second.unfinished(); }));
}

std::uint64_t Context::unfinished_pixels() const {
  std::uint64_t sum = 0;
  for (const auto& [id, job] : jobs) {
    if (job.unfinished()) sum += std::uint64_t{job.settings.width} * job.settings.height;
  }
  return sum;
}

MetricsSnapshot Context::metrics() const {
  MetricsSnapshot m;
  m.epoch = epoch;
  m.restored_tiles = restored_tiles;
  for (const auto& [id, job] : jobs) ++m.jobs_by_state[static_cast<std::size_t>(job.state)];
  m.counters = counters;
  for (const Role r : {Role::kViewer, Role::kClient, Role::kWorker}) {
    m.credentials_by_role[static_cast<std::size_t>(r)] = credentials.live(r);
  }
  m.queue = queue.stats();
  if (server) m.http = server->metrics();
  m.store = writer ? writer->stats() : last_writer_stats;
  m.process = read_process_stats();
  m.workers = workers.list(clock.now());
  m.retired_workers = workers.retired();
  m.workers_evicted = workers.evicted();
  return m;
}

}  // namespace dtraced::collector
