#include "render/local_render.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <utility>
#include <vector>

#include "util/cpus.h"

namespace dtraced::render {

namespace {

// The calling thread takes the finished tiles (for tile_done and progress) in batches: it is woken
// when kWakeTiles tiles have finished since it last took them, or when a render thread returns,
// and otherwise takes what there is after kWakeAfter. So a tile reaches tile_done within about
// kWakeAfter or kWakeTiles tiles' time. Woken for every tile instead, it preempted a render
// thread at each wake-up: whitted10 at 1280x720 (920 tiles) on 2 threads of 2 cores took about
// 2000 context switches against 420, and 2.5 % more CPU time.
constexpr std::size_t kWakeTiles = 8;
constexpr std::chrono::milliseconds kWakeAfter{20};

}  // namespace

void paste_tile(const Tile& t, std::uint32_t image_width, LocalResult& result) {
  for (std::uint32_t row = 0; row < t.rect.height; ++row) {
    const float* src = &t.rgb[std::size_t(row) * t.rect.width * 3];
    std::copy(src, src + std::size_t(t.rect.width) * 3, result.image.pixel(t.rect.x0, t.rect.y0 + row));
    if (!t.spp.empty() && !result.spp.empty()) {
      const std::uint32_t* counts = &t.spp[std::size_t(row) * t.rect.width];
      std::copy(counts, counts + t.rect.width, &result.spp[std::size_t(t.rect.y0 + row) * image_width + t.rect.x0]);
    }
    if (!t.variance.empty() && !result.variance.rgb.empty()) {
      const float* var = &t.variance[std::size_t(row) * t.rect.width * 3];
      std::copy(var, var + std::size_t(t.rect.width) * 3, result.variance.pixel(t.rect.x0, t.rect.y0 + row));
    }
  }
}

LocalResult render_local(const RenderScene& scene, const scene::RenderSettings& settings, const LocalOptions& options) {
  LocalResult result;
  result.image = image::ImageRGBf(settings.width, settings.height);
  const std::vector<TileRect> all = scene::TileGrid(settings, std::max(1u, options.tile_size)).all();
  std::vector<std::size_t> tiles;  // indices of those to render
  tiles.reserve(all.size());
  for (std::size_t i = 0; i < all.size(); ++i) {
    if (i >= options.skip.size() || !options.skip[i]) tiles.push_back(i);
  }
  const std::size_t skipped = all.size() - tiles.size();
  std::uint32_t threads = options.threads ? options.threads : util::usable_cpus();
  threads = std::min<std::uint32_t>(threads, std::max<std::size_t>(1, tiles.size()));
  result.threads = threads;

  const bool adaptive = settings.error_target > 0;
  if (adaptive) result.spp.assign(std::size_t(settings.width) * settings.height, 0);
  if (options.want_variance) result.variance = image::ImageRGBf(settings.width, settings.height);
  const TileOptions tile_options{
      .packets = options.packets, .specialise = options.specialise, .want_variance = options.want_variance};
  std::atomic<std::size_t> next{0};
  std::mutex mu;
  std::condition_variable cv;
  std::size_t done = 0;     // guarded by mu
  std::size_t taken = 0;    // `done` when this thread last took the finished tiles; guarded by mu
  std::uint32_t ended = 0;  // render threads that have returned; guarded by mu
  TraceStats stats;         // guarded by mu
  // Tiles rendered and not yet handed to tile_done, which this thread calls (guarded by mu).
  std::vector<std::pair<std::size_t, Tile>> finished;

  const auto start = std::chrono::steady_clock::now();
  auto worker = [&] {
    TraceStats local;
    for (std::size_t i = next.fetch_add(1); i < tiles.size(); i = next.fetch_add(1)) {
      if (options.stop_requested && options.stop_requested()) break;
      Tile t = render_tile(scene, settings, all[tiles[i]], tile_options);
      paste_tile(t, settings.width, result);
      local.add(t.stats);
      std::lock_guard lock(mu);
      if (options.tile_done) finished.emplace_back(tiles[i], std::move(t));
      if (++done - taken >= kWakeTiles) cv.notify_one();
    }
    std::lock_guard lock(mu);
    stats.add(local);
    ++ended;
    cv.notify_one();
  };
  {
    std::vector<std::jthread> pool;
    pool.reserve(threads);
    for (std::uint32_t i = 0; i < threads; ++i) pool.emplace_back(worker);
    std::vector<std::pair<std::size_t, Tile>> batch;
    std::unique_lock lock(mu);
    // Until every thread has returned (all tiles done, or a stop) and every tile it rendered has
    // been through tile_done.
    for (bool last = false; !last;) {
      cv.wait_for(lock, kWakeAfter, [&] { return done - taken >= kWakeTiles || ended == threads; });
      last = ended == threads;  // then every tile rendered is in `finished`
      batch.swap(finished);
      taken = done;
      const std::size_t d = done;
      lock.unlock();
      for (const auto& [index, t] : batch) options.tile_done(index, t);
      batch.clear();
      if (options.progress) options.progress(skipped + d, all.size());
      lock.lock();
    }
  }  // joins the pool
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  result.stats = stats;
  result.tiles_rendered = done;
  result.complete = done == tiles.size();
  if (options.progress) options.progress(skipped + done, all.size());
  return result;
}

}  // namespace dtraced::render
