#include "collector/service.h"

#include <signal.h>

#include <algorithm>
#include <cassert>
#include <charconv>
#include <cmath>
#include <exception>
#include <filesystem>
#include <functional>
#include <map>
#include <mutex>
#include <stdexcept>
#include <type_traits>
#include <utility>
#include <variant>
#include <vector>

#include <boost/asio/as_tuple.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/ip/address.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/signal_set.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/thread_pool.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/beast/http/field.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "collector/admission.h"
#include "collector/jobs.h"
#include "collector/queue.h"
#include "collector/routes.h"
#include "http/server.h"
#include "image/image_io.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "store/store.h"
#include "store/tile_writer.h"
#include "util/file.h"
#include "util/log.h"
#include "util/sd_notify.h"
#include "util/sha256.h"

namespace dtraced::collector {
namespace {

namespace net = boost::asio;
namespace fs = std::filesystem;
namespace bhttp = boost::beast::http;
using protocol::JobState;

// Tile payloads larger than this are checksummed and checked on the thread pool rather than on
// the loop (SHA-256 of 256 KiB is a fraction of a millisecond; of the largest payload, tens).
constexpr std::size_t kInlinePayloadBytes = 256 << 10;
// A failed image write (disk full, output directory gone) is tried again after this long.
constexpr std::chrono::seconds kFinishRetryDelay{5};
// The epoch file holds one decimal number.
constexpr std::uint64_t kMaxEpochFileBytes = 64;

std::int64_t now_unix() {
  return std::chrono::duration_cast<std::chrono::seconds>(std::chrono::system_clock::now().time_since_epoch()).count();
}

void log_exception(std::string_view what, const std::exception_ptr& error) {
  try {
    std::rethrow_exception(error);
  } catch (const std::exception& e) {
    util::log_error("collector: {} failed: {}", what, e.what());
  } catch (...) {
    util::log_error("collector: {} failed with an unknown exception", what);
  }
}

// ---- bridges from other threads back to the loop --------------------------------------------
//
// Each turns "run this elsewhere, call me back" into something a coroutine on the loop can
// co_await. The completion is posted to the awaiting coroutine's executor, and a work guard keeps
// that executor's run() from returning while the operation is out (so a test running the loop
// until idle waits for it).

template <typename Handler>
struct SharedCompletion {
  explicit SharedCompletion(Handler h)
      : handler(std::move(h)), work(net::make_work_guard(net::get_associated_executor(*handler))) {}

  std::optional<Handler> handler;
  net::executor_work_guard<net::associated_executor_t<Handler>> work;
};

// Resumes the handler with `args` on its executor. Called once, from any thread.
template <typename Handler, typename... Args>
void complete(const std::shared_ptr<SharedCompletion<Handler>>& done, Args... args) {
  auto executor = done->work.get_executor();
  net::post(executor, [done, ... args = std::move(args)]() mutable {
    Handler handler = std::move(*done->handler);
    done->handler.reset();
    done->work.reset();
    std::move(handler)(std::move(args)...);
  });
}

// GCC 12 destroys a prvalue argument of a call inside a co_await expression twice when the
// coroutine resumes (a lambda's captured string was freed by both copies). So the bridges take
// their function by reference and callers name it first:
//   auto task = [...] { ... };
//   auto result = co_await on_pool(pool_, std::move(task));

// Runs f() on the pool; the awaiting coroutine gets its result or its exception. The result type
// must be default-constructible. Lambdas given here capture by value, or by reference only what
// the awaiting coroutine's frame keeps alive while it waits.
template <typename F>
auto on_pool(net::thread_pool& pool, F&& f) {
  using Fn = std::decay_t<F>;
  using R = std::invoke_result_t<Fn&>;
  return net::async_initiate<decltype(net::use_awaitable), void(std::exception_ptr, R)>(
      [&pool](auto handler, Fn f) {
        using Handler = decltype(handler);
        auto done = std::make_shared<SharedCompletion<Handler>>(std::move(handler));
        net::post(pool, [done, f = std::move(f)]() mutable {
          std::exception_ptr error;
          R result{};
          try {
            result = f();
          } catch (...) {
            error = std::current_exception();
          }
          complete(done, error, std::move(result));
        });
      },
      net::use_awaitable, Fn(std::forward<F>(f)));
}

// What the store writer did with a task or a tile: refused it (status), or ran it (value; empty
// when the task threw, which is logged).
template <typename R>
struct WriterReply {
  store::SubmitStatus status = store::SubmitStatus::kStopped;
  std::optional<R> value;
  bool ok() const { return status == store::SubmitStatus::kAccepted && value.has_value(); }
};

// Runs f(Store&) on the writer thread, in order with the tiles and tasks around it.
template <typename F>
auto on_writer(store::TileWriter& writer, F&& f) {
  using Fn = std::decay_t<F>;
  using R = std::invoke_result_t<Fn&, store::Store&>;
  return net::async_initiate<decltype(net::use_awaitable), void(WriterReply<R>)>(
      [&writer](auto handler, Fn f) {
        using Handler = decltype(handler);
        auto done = std::make_shared<SharedCompletion<Handler>>(std::move(handler));
        const store::SubmitStatus status = writer.post([done, f = std::move(f)](store::Store& s) mutable {
          WriterReply<R> reply;
          reply.status = store::SubmitStatus::kAccepted;
          try {
            reply.value.emplace(f(s));
          } catch (const std::exception& e) {
            util::log_error("collector: a store task threw: {}", e.what());
          }
          complete(done, std::move(reply));
        });
        if (status != store::SubmitStatus::kAccepted) complete(done, WriterReply<R>{status, std::nullopt});
      },
      net::use_awaitable, Fn(std::forward<F>(f)));
}

// Queues a tile result with the writer; completes after its transaction committed (or failed).
auto commit_tile(store::TileWriter& writer, store::TileWrite&& write) {
  return net::async_initiate<decltype(net::use_awaitable), void(WriterReply<store::CommitResult>)>(
      [&writer](auto handler, store::TileWrite write) {
        using Handler = decltype(handler);
        auto done = std::make_shared<SharedCompletion<Handler>>(std::move(handler));
        const store::SubmitStatus status = writer.submit(std::move(write), [done](store::CommitResult result) {
          complete(done, WriterReply<store::CommitResult>{store::SubmitStatus::kAccepted, std::move(result)});
        });
        if (status != store::SubmitStatus::kAccepted) {
          complete(done, WriterReply<store::CommitResult>{status, std::nullopt});
        }
      },
      net::use_awaitable, store::TileWrite(std::move(write)));
}

// ---- pure helpers -----------------------------------------------------------------------------

http::Response json_text(http::Status status, std::string body) {
  return http::make_text_response(status, std::move(body), http::kJsonContentType);
}

http::Response busy_answer(std::string_view message) { return respond(busy(std::string(message))); }

http::Response decode_failure_answer(const util::Errors& errors) {
  const protocol::ErrorBody body = protocol::error_body(errors);
  return http::make_error(http::Status::bad_request, body.error, body.field);
}

http::Response job_not_found_answer(JobId id) {
  return http::make_error(http::Status::not_found, fmt::format("no such job: {}", id));
}

http::Response submit_answer(protocol::SubmitResult result) {
  const http::Status status = result == protocol::SubmitResult::kJobGone ? http::Status::gone : http::Status::ok;
  return json_text(status, protocol::encode(result));
}

// The worker's name as it gave it in kWorkerHeader: printable ASCII, bounded; "unknown" if none.
std::string worker_name(const http::Request& req) {
  const auto it = req.find(boost::beast::string_view(kWorkerHeader.data(), kWorkerHeader.size()));
  std::string name;
  if (it != req.end()) {
    for (const char c : it->value()) {
      if (name.size() == protocol::kMaxWorkerNameBytes) break;
      name += (c >= 0x20 && c <= 0x7e) ? c : '?';
    }
  }
  return name.empty() ? std::string("unknown") : name;
}

// A tile payload, decoded and checked for what does not depend on the job.
struct CheckedTile {
  std::optional<protocol::TilePayload> payload;
  std::string error;  // when !payload
  std::string field;
};

CheckedTile check_tile_payload(std::string_view body) {
  auto decoded = protocol::decode_tile_payload(body);
  if (auto* failure = std::get_if<protocol::TilePayloadFailure>(&decoded)) {
    return {std::nullopt, "tile payload: " + failure->message, ""};
  }
  auto& payload = std::get<protocol::TilePayload>(decoded);
  // The renderer never produces NaN or infinity: such a tile comes from a broken worker, and
  // accepting it would make it the stored truth.
  for (std::size_t i = 0; i < payload.rgb.size(); ++i) {
    if (!std::isfinite(payload.rgb[i])) {
      const std::size_t pixel = i / 3;
      return {std::nullopt,
              fmt::format("pixel ({}, {}) holds a non-finite value", payload.rect.x0 + pixel % payload.rect.width,
                          payload.rect.y0 + pixel / payload.rect.width),
              "/pixels"};
    }
  }
  return {std::move(payload), {}, {}};
}

// A submission decoded, with what the loop needs: done on the pool (a scene may be 64 MiB).
struct PreparedJob {
  util::Errors errors;         // non-empty: the body was refused
  protocol::JobSubmit submit;  // its scene is emptied once turned into text
  scene::RenderSettings settings;
  std::uint32_t tile_size = 0;
  std::uint32_t png_bit_depth = 0;
  std::string scene_json;  // canonical
  std::string digest;
};

PreparedJob prepare_job(std::string_view body) {
  PreparedJob p;
  auto decoded = protocol::decode_job_submit(body);
  if (!decoded) {
    p.errors = std::move(decoded).error();
    return p;
  }
  p.submit = std::move(decoded).value();
  p.settings = protocol::effective_settings(p.submit);
  p.tile_size = scene::tile_size_or_default(p.submit.overrides);
  p.png_bit_depth = scene::png_bit_depth_or_default(p.submit.overrides);
  p.scene_json = scene::canonical_json(p.submit.scene);
  p.digest = util::sha256_hex(p.scene_json);  // = scene::scene_digest, without a second serialisation
  p.submit.scene = {};
  return p;
}

// Stores a scene and a job in one transaction; returns the job's id.
util::Result<std::int64_t> insert_scene_and_job(store::Store& s, const store::StoredJob& row,
                                                std::string_view scene_json) {
  std::int64_t id = 0;
  const util::Status status = s.transaction([&]() -> util::Status {
    if (util::Status put = s.put_scene(row.digest, scene_json); !put) return put;
    util::Result<std::int64_t> inserted = s.insert_job(row);
    if (!inserted) return inserted.error();
    id = inserted.value();
    return {};
  });
  if (!status) return status.error();
  return id;
}

// A job record from its stored row; the error names the job and the problem.
std::variant<JobRecord, std::string> record_from_row(const store::StoredJob& row) {
  auto settings = protocol::decode_settings(row.settings_json);
  if (!settings)
    return fmt::format("job {}: stored settings are unreadable: {}", row.id, util::to_string(settings.error()));
  const auto state = protocol::job_state_from_string(row.state);
  if (!state) return fmt::format("job {}: unknown state '{}'", row.id, row.state);
  if (row.tile_size < scene::kMinTileSize || row.tile_size > scene::kMaxTileSize) {
    return fmt::format("job {}: tile size {} is out of range", row.id, row.tile_size);
  }
  const std::uint64_t tiles = scene::TileGrid(settings.value().render, row.tile_size).count();
  if (tiles == 0 || tiles > protocol::kMaxTilesPerJob) {
    return fmt::format("job {}: {} tiles, outside [1, {}]", row.id, tiles, protocol::kMaxTilesPerJob);
  }
  if (row.id <= 0 || static_cast<std::uint64_t>(row.id) > protocol::kMaxId) {
    return fmt::format("job id {} is out of range", row.id);
  }
  JobRecord rec;
  rec.id = static_cast<JobId>(row.id);
  rec.digest = row.digest;
  rec.settings = settings.value().render;
  rec.png_bit_depth = settings.value().png_bit_depth;
  rec.output = row.output.empty() ? default_output_name(rec.id) : row.output;
  rec.priority = row.priority;
  rec.tile_size = row.tile_size;
  rec.state = *state;
  rec.created_unix = row.created_unix;
  rec.finished_unix = row.finished_unix;
  rec.tiles_total = static_cast<TileIndex>(tiles);
  rec.tiles_done = rec.state == JobState::kDone ? rec.tiles_total : 0;
  return rec;
}

}  // namespace

// ---- Impl -------------------------------------------------------------------------------------

struct Collector::Impl {
  explicit Impl(CollectorConfig config)
      : config_(std::move(config)),
        token_(config_.token),
        ioc_(std::make_unique<net::io_context>(1)),
        pool_(std::clamp<std::size_t>(config_.cpu_threads, 1, kMaxCpuThreads)),
        idle_timer_(std::in_place, *ioc_),
        retry_timer_(std::in_place, *ioc_) {}

  ~Impl() {
    // Order matters: everything that posts into the io_context (the writer's callbacks, the
    // pool's completions) ends first; then the io_context is destroyed, which destroys the
    // coroutines still suspended on it while every member they refer to still exists.
    if (writer_) writer_->stop();
    pool_.join();
    server_.reset();
    idle_timer_.reset();
    retry_timer_.reset();
    ioc_.reset();
  }

  // Start-up.
  std::optional<std::string> open();
  std::optional<std::string> bump_epoch();
  std::optional<std::string> restore(store::Store& s);
  std::optional<std::string> restore_active(store::Store& s, const store::StoredJob& row, JobRecord& rec);
  struct SampleCounts {
    SampleTally tally;
    std::string error;  // a store failure
  };
  SampleCounts read_sample_counts(JobId id, scene::RenderSettings settings, std::uint32_t tile_size,
                                  TileIndex tiles_total);
  net::awaitable<void> restore_sample_counts(JobId id);
  std::optional<std::string> enqueue_one_shot(store::Store& s);
  std::optional<std::string> listen();

  // Requests.
  net::awaitable<http::Response> handle(http::Request req);
  // The server's header check: the token and the route, before any body is read.
  std::optional<http::Response> check_header(const http::Request& header, std::uint64_t& body_limit);
  net::awaitable<http::Response> submit_job(http::Request req);
  http::Response list_jobs() const;
  http::Response job_status_response(JobId id) const;
  net::awaitable<http::Response> job_image(JobId id, image::ImageFormat format);
  net::awaitable<http::Response> cancel_job(JobId id);
  http::Response lease(std::string_view body);
  net::awaitable<http::Response> scene(std::string digest);
  net::awaitable<http::Response> put_tile(Route route, http::Request req);
  http::Response on_tile_stored(JobId id, const protocol::TilePayload& payload);

  // Job lifecycle.
  JobRecord* find_job(JobId id) {
    const auto it = jobs_.find(id);
    return it == jobs_.end() ? nullptr : &it->second;
  }
  const JobRecord* find_job(JobId id) const {
    const auto it = jobs_.find(id);
    return it == jobs_.end() ? nullptr : &it->second;
  }
  std::shared_ptr<const std::string> intern_scene(const std::string& digest, std::string json);
  void persist_rendering(JobRecord& job);
  void start_finish(JobId id);
  net::awaitable<void> finish_job(JobId id);
  void finish_ended();
  void arm_finish_retry();
  static void release(JobRecord& job);
  std::size_t unfinished_jobs() const;
  std::uint64_t unfinished_pixels() const;

  // Reads on the pool's threads, through the read-only connection.
  struct Encoded {
    std::optional<std::string> bytes;
    std::string error;
  };
  Encoded encode_from_store(JobId id, scene::RenderSettings settings, std::uint32_t tile_size,
                            image::WriteOptions options, image::ImageFormat format);
  struct FetchedScene {
    std::optional<std::string> json;
    std::string error;  // a store failure (not "missing")
  };
  FetchedScene scene_from_store(const std::string& digest);
  store::Store* read_store_locked(std::string& error);

  // Stop.
  void begin_stop(int exit_code);
  net::awaitable<void> stop_sequence();

  MetricsSnapshot metrics() const;

  // Immutable after construction.
  const CollectorConfig config_;
  const TokenCheck token_;
  std::string output_dir_;  // set by open()

  // The loop and what lives on it. The io_context is destroyed first (see ~Impl).
  std::unique_ptr<net::io_context> ioc_;
  net::thread_pool pool_;
  std::optional<net::steady_timer> idle_timer_;   // wakes stop_sequence when image writes end
  std::optional<net::steady_timer> retry_timer_;  // failed image writes
  bool retry_armed_ = false;
  std::unique_ptr<http::Server> server_;
  std::unique_ptr<store::TileWriter> writer_;
  store::WriterStats last_writer_stats_;  // once the writer is gone

  WorkQueue queue_;
  std::map<JobId, JobRecord> jobs_;
  // Canonical scene text by digest, shared by the unfinished jobs that use it.
  std::map<std::string, std::weak_ptr<const std::string>, std::less<>> scenes_;
  std::vector<JobId> to_finish_;  // found complete at start-up
  std::vector<JobId> to_count_;   // finished adaptive jobs whose mean spp is read after start-up
  CollectorCounters counters_;
  std::int64_t epoch_ = 0;
  std::uint64_t restored_tiles_ = 0;
  std::optional<JobId> one_shot_id_;
  std::size_t finishes_in_flight_ = 0;
  bool opened_ = false;
  bool stopping_ = false;
  std::optional<int> exit_code_;

  // The read-only connection, used by pool threads one at a time.
  std::mutex read_mu_;
  std::optional<store::Store> read_store_;  // guarded by read_mu_; opened on first use
  bool reads_closed_ = false;               // guarded by read_mu_: stopping, never reopen
};

// ---- start-up ---------------------------------------------------------------------------------

std::optional<std::string> Collector::Impl::open() {
  if (opened_) return "the collector is already open";
  if (auto error = check_collector_config(config_)) return "configuration: " + *error;
  queue_ = WorkQueue(config_.queue);

  auto opened = store::Store::open(config_.state_dir);
  if (!opened) return opened.error().message;
  store::Store s = std::move(opened).value();

  output_dir_ = config_.effective_output_dir();
  std::error_code ec;
  fs::create_directories(output_dir_, ec);
  if (ec) return fmt::format("output directory {}: cannot create it: {}", output_dir_, ec.message());

  if (auto error = bump_epoch()) return error;
  if (auto error = restore(s)) return error;
  if (config_.one_shot) {
    if (auto error = enqueue_one_shot(s)) return error;
  }

  writer_ = std::make_unique<store::TileWriter>(std::move(s), config_.writer);
  opened_ = true;
  for (const JobId id : to_finish_) start_finish(id);
  to_finish_.clear();
  for (const JobId id : to_count_) {
    net::co_spawn(*ioc_, restore_sample_counts(id), [id](std::exception_ptr error) {
      if (error) log_exception(fmt::format("reading the sample counts of job {}", id), error);
    });
  }
  to_count_.clear();
  util::log_info("collector: start {} on {}; {} unfinished job(s), {} tile(s) already stored", epoch_,
                 config_.state_dir, unfinished_jobs(), restored_tiles_);
  return std::nullopt;
}

std::optional<std::string> Collector::Impl::bump_epoch() {
  const std::string path = (fs::path(config_.state_dir) / kEpochFileName).string();
  std::int64_t previous = 0;
  std::error_code ec;
  if (fs::exists(path, ec)) {
    std::string error;
    auto text = util::read_file_limited(path, kMaxEpochFileBytes, error);
    if (!text) return error;
    std::string_view digits = *text;
    while (!digits.empty() && (digits.back() == '\n' || digits.back() == ' ')) digits.remove_suffix(1);
    const auto [end, parse_error] = std::from_chars(digits.data(), digits.data() + digits.size(), previous);
    if (parse_error != std::errc() || end != digits.data() + digits.size() || previous < 0 ||
        previous == std::numeric_limits<std::int64_t>::max()) {
      return fmt::format("{}: not a start counter; refusing to start (fix the file or remove it)", path);
    }
  }
  epoch_ = previous + 1;
  std::string error;
  if (!util::write_file_atomic(path, fmt::format("{}\n", epoch_), error)) return error;
  return std::nullopt;
}

std::optional<std::string> Collector::Impl::restore(store::Store& s) {
  auto rows = s.list_jobs();
  if (!rows) return rows.error().message;
  for (const store::StoredJob& row : rows.value()) {
    auto made = record_from_row(row);
    if (auto* error = std::get_if<std::string>(&made)) return fmt::format("{}: {}", s.path(), *error);
    JobRecord rec = std::move(std::get<JobRecord>(made));
    if (rec.unfinished()) {
      if (auto error = restore_active(s, row, rec)) return error;
    } else if (rec.state == JobState::kCancelled) {
      // Its status still says how far it got.
      auto count = s.count_tiles(row.id);
      if (!count) return count.error().message;
      rec.tiles_done = static_cast<TileIndex>(std::min<std::uint64_t>(count.value(), rec.tiles_total));
    }
    if (!rec.unfinished() && rec.settings.error_target > 0) {
      // Its mean spp needs every stored tile read: done after start-up, off the loop, so that
      // start-up time does not grow with the job history (see restore_sample_counts).
      rec.spp_pending = true;
      to_count_.push_back(rec.id);
    }
    jobs_.emplace(rec.id, std::move(rec));
  }
  return std::nullopt;
}

// A finished adaptive job's sample counts, read back from its stored tiles one at a time on the
// read connection (a done job's tiles are not otherwise read at start). Runs on the pool; takes
// the read connection one tile at a time, so image and scene reads go on in between.
Collector::Impl::SampleCounts Collector::Impl::read_sample_counts(JobId id, scene::RenderSettings settings,
                                                                  std::uint32_t tile_size, TileIndex tiles_total) {
  SampleCounts c;
  std::vector<std::uint32_t> indices;
  {
    std::lock_guard lock(read_mu_);
    store::Store* s = read_store_locked(c.error);
    if (s == nullptr) return c;
    auto tiles = s->stored_tiles(static_cast<std::int64_t>(id));
    if (!tiles) {
      c.error = tiles.error().message;
      return c;
    }
    indices = std::move(tiles.value());
  }
  for (const std::uint32_t index : indices) {
    if (index >= tiles_total) continue;
    std::optional<store::StoredTile> stored;
    {
      std::lock_guard lock(read_mu_);
      store::Store* s = read_store_locked(c.error);
      if (s == nullptr) return c;
      auto tile = s->get_tile(static_cast<std::int64_t>(id), index);
      if (!tile) {
        c.error = tile.error().message;
        return c;
      }
      stored = std::move(tile.value());
    }
    if (!stored) continue;
    const scene::TileRect rect = scene::TileGrid(settings, tile_size).rect(index);
    auto parsed = blob_to_tile(stored->pixels, std::size_t{rect.width} * rect.height);
    if (!parsed) {
      c.tally.known = false;  // the image itself is checked when it is served
      continue;
    }
    c.tally.add(parsed->spp);
  }
  return c;
}

// Fills in a finished adaptive job's mean spp after start-up; until then its status reports the
// mean as unknown. A tile that cannot be read leaves it unknown for good (logged).
net::awaitable<void> Collector::Impl::restore_sample_counts(JobId id) {
  const JobRecord* job = find_job(id);
  if (job == nullptr || stopping_) co_return;
  auto read = [this, id, settings = job->settings, tile_size = job->tile_size, total = job->tiles_total] {
    return read_sample_counts(id, settings, tile_size, total);
  };
  const SampleCounts c = co_await on_pool(pool_, std::move(read));
  JobRecord* rec = find_job(id);
  if (rec == nullptr) co_return;
  rec->spp_pending = false;
  rec->spp.add(c.tally);
  if (!c.error.empty()) rec->spp.known = false;
  if (!rec->spp.known) {
    util::log_warn("collector: job {}: mean spp unknown: {}", id,
                   c.error.empty() ? "a stored tile's sample counts do not parse" : c.error);
  }
}

std::optional<std::string> Collector::Impl::restore_active(store::Store& s, const store::StoredJob& row,
                                                           JobRecord& rec) {
  auto scene_json = s.get_scene(row.digest);
  if (!scene_json) return scene_json.error().message;
  if (!scene_json.value()) return fmt::format("{}: job {}: its scene {} is missing", s.path(), rec.id, row.digest);
  auto tiles = s.get_all_tiles(row.id);
  if (!tiles) return tiles.error().message;

  std::vector<TileIndex> stored;
  rec.restored.assign(rec.tiles_total, false);
  for (store::StoredTile& t : tiles.value()) {
    if (t.tile >= rec.tiles_total) {
      return fmt::format("{}: job {}: stored tile {} is out of range ({} tiles)", s.path(), rec.id, t.tile,
                         rec.tiles_total);
    }
    const scene::TileRect rect = scene::TileGrid(rec.settings, rec.tile_size).rect(t.tile);
    const std::size_t pixels = std::size_t{rect.width} * rect.height;
    auto stored_tile = blob_to_tile(t.pixels, pixels);
    if (!stored_tile) {
      return fmt::format(
          "{}: job {}: stored tile {} holds {} bytes; its {}x{} rectangle needs {} (or {} with sample "
          "counts)",
          s.path(), rec.id, t.tile, t.pixels.size(), rect.width, rect.height, pixels * 12, pixels * 16);
    }
    copy_tile(writable_framebuffer(rec), rect, stored_tile->rgb);
    count_samples(rec, stored_tile->spp);
    t.pixels = {};  // free as we go: the framebuffer holds them now
    stored.push_back(t.tile);
    rec.restored[t.tile] = true;
  }
  if (!queue_.add_job(rec.id, rec.priority, rec.tiles_total, stored)) {
    return fmt::format("{}: job {}: cannot be queued (duplicate tiles?)", s.path(), rec.id);
  }
  rec.tiles_done = static_cast<TileIndex>(stored.size());
  restored_tiles_ += stored.size();
  rec.state = rec.tiles_done > 0 ? JobState::kRendering : JobState::kQueued;
  rec.rendering_persisted = row.state == store::kJobRendering;
  rec.scene_json = intern_scene(row.digest, std::move(*scene_json.value()));
  if (rec.tiles_done == rec.tiles_total) to_finish_.push_back(rec.id);
  util::log_info("collector: job {} restored: {}/{} tiles stored", rec.id, rec.tiles_done, rec.tiles_total);
  return std::nullopt;
}

std::optional<std::string> Collector::Impl::enqueue_one_shot(store::Store& s) {
  const OneShotJob& one = *config_.one_shot;
  scene::LoadResult loaded = scene::load_scene_file(one.scene_path);
  if (!loaded.ok()) return "scene: " + scene::format_errors(loaded.errors);

  protocol::JobSubmit submit;
  submit.scene = std::move(*loaded.scene);
  submit.output = one.output;
  submit.priority = one.priority;
  submit.overrides = one.overrides;
  // Through the wire format, so a one-shot job meets exactly the checks of a submitted one.
  PreparedJob p = prepare_job(protocol::encode(submit));
  if (!p.errors.empty()) {
    const protocol::ErrorBody e = protocol::error_body(p.errors);
    return e.field.empty() ? "one-shot job: " + e.error : "one-shot job: " + e.field + ": " + e.error;
  }

  const std::string key = one_shot_client_key(p.digest, {p.settings, p.png_bit_depth}, p.tile_size, p.submit.output);
  auto found = s.find_job_by_key(key);
  if (!found) return found.error().message;
  if (found.value()) {
    const store::StoredJob& row = *found.value();
    const JobId id = static_cast<JobId>(row.id);
    one_shot_id_ = id;
    JobRecord* rec = find_job(id);
    assert(rec != nullptr);
    if (rec->unfinished()) {
      util::log_info("collector: one-shot job {} resumed: {}/{} tiles stored", id, rec->tiles_done, rec->tiles_total);
    } else if (rec->state == JobState::kCancelled) {
      util::log_error("collector: one-shot job {} was cancelled; nothing to do", id);
      if (config_.exit_when_done) begin_stop(1);
    } else {
      const fs::path path = fs::path(output_dir_) / rec->output;
      std::error_code ec;
      if (fs::exists(path, ec)) {
        util::log_info("collector: one-shot job {} is done; {} is written", id, path.string());
        if (config_.exit_when_done) begin_stop(0);
      } else {
        // Done, but the image is gone: assemble it again from the stored tiles.
        util::log_info("collector: one-shot job {} is done but {} is missing; writing it again", id, path.string());
        JobRecord again = *rec;
        again.state = JobState::kRendering;
        if (auto error = restore_active(s, row, again)) return error;
        *rec = std::move(again);
      }
    }
    return std::nullopt;
  }

  store::StoredJob row;
  row.digest = p.digest;
  row.settings_json = protocol::encode_settings({p.settings, p.png_bit_depth});
  row.output = p.submit.output;
  row.priority = p.submit.priority;
  row.tile_size = p.tile_size;
  row.state = std::string(store::kJobQueued);
  row.created_unix = now_unix();
  row.client_key = key;
  auto inserted = insert_scene_and_job(s, row, p.scene_json);
  if (!inserted) return inserted.error().message;
  row.id = inserted.value();
  auto made = record_from_row(row);
  if (auto* error = std::get_if<std::string>(&made)) return *error;
  JobRecord rec = std::move(std::get<JobRecord>(made));
  rec.scene_json = intern_scene(p.digest, std::move(p.scene_json));
  if (!queue_.add_job(rec.id, rec.priority, rec.tiles_total)) return fmt::format("job {}: cannot be queued", rec.id);
  one_shot_id_ = rec.id;
  util::log_info("collector: one-shot job {} enqueued: {} -> {} ({}x{}, {} samples, {} tiles)", rec.id, one.scene_path,
                 rec.output, rec.settings.width, rec.settings.height, rec.settings.samples, rec.tiles_total);
  jobs_.emplace(rec.id, std::move(rec));
  return std::nullopt;
}

std::optional<std::string> Collector::Impl::listen() {
  if (!opened_) return "listen() before open()";
  if (stopping_ || server_) return std::nullopt;
  http::ServerLimits limits = config_.limits;
  // One body limit for the server: the largest of the routes' (each route checks its own).
  limits.max_body_bytes =
      std::min<std::uint64_t>(config_.limits.max_body_bytes,
                              std::max<std::uint64_t>(protocol::kMaxJobSubmitBytes, protocol::kMaxTilePayloadBytes));
  boost::system::error_code ec;
  const auto address = net::ip::make_address(config_.listen_address, ec);
  if (ec) return fmt::format("listen_address '{}': {}", config_.listen_address, ec.message());
  server_ = std::make_unique<http::Server>(
      ioc_->get_executor(), address, config_.port, limits, [this](http::Request req) { return handle(std::move(req)); },
      [this](const http::Request& header, std::uint64_t& body_limit) { return check_header(header, body_limit); });
  ec = server_->start();
  if (ec) {
    server_.reset();
    return fmt::format("cannot listen on {} port {}: {}", config_.listen_address, config_.port, ec.message());
  }
  util::log_info("collector: listening on {} port {}; images go to {}", config_.listen_address, server_->port(),
                 output_dir_);
  util::sd_notify_state("READY=1");
  return std::nullopt;
}

// ---- requests -----------------------------------------------------------------------------------

// Refuses a wrong token or an unknown route on the header alone, and gives the body the route's
// own limit, so that no request buffers more than its endpoint accepts (a wrong token, none at
// all). handle() checks the same again, for requests that reach it by other paths (tests).
std::optional<http::Response> Collector::Impl::check_header(const http::Request& header, std::uint64_t& body_limit) {
  auto admitted = admit(header, token_, config_.limits.max_body_bytes);
  if (!admitted) {
    if (admitted.error().status == http::Status::unauthorized) ++counters_.auth_failures;
    return respond(admitted.error());
  }
  body_limit = std::min(body_limit, admitted->body_limit);
  return std::nullopt;
}

net::awaitable<http::Response> Collector::Impl::handle(http::Request req) {
  auto admitted = admit(req, token_, config_.limits.max_body_bytes);
  if (!admitted) {
    if (admitted.error().status == http::Status::unauthorized) ++counters_.auth_failures;
    co_return respond(admitted.error());
  }
  Route route = std::move(admitted->route);
  if (route.kind == RouteKind::kHealthz) {
    co_return http::make_json_response(http::Status::ok, boost::json::value{{"ok", true}});
  }
  if (auto sized = check_body_size(req.body().size(), admitted->body_limit); !sized) co_return respond(sized.error());
  if (!opened_) co_return busy_answer("the collector is starting");

  switch (route.kind) {
    case RouteKind::kHealthz:
      co_return http::make_json_response(http::Status::ok, boost::json::value{{"ok", true}});
    case RouteKind::kMetrics:
      co_return http::make_text_response(http::Status::ok, format_metrics(metrics()), kMetricsContentType);
    case RouteKind::kSubmitJob:
      co_return co_await submit_job(std::move(req));
    case RouteKind::kListJobs:
      co_return list_jobs();
    case RouteKind::kJobStatus:
      co_return job_status_response(route.job);
    case RouteKind::kJobImage:
      co_return co_await job_image(route.job, route.image_format);
    case RouteKind::kCancelJob:
      co_return co_await cancel_job(route.job);
    case RouteKind::kLease:
      co_return lease(req.body());
    case RouteKind::kScene:
      co_return co_await scene(std::move(route.digest));
    case RouteKind::kPutTile:
      co_return co_await put_tile(std::move(route), std::move(req));
  }
  co_return http::make_error(http::Status::internal_server_error, "unhandled route");
}

net::awaitable<http::Response> Collector::Impl::submit_job(http::Request req) {
  if (unfinished_jobs() >= config_.max_unfinished_jobs) {
    co_return busy_answer(fmt::format("too many unfinished jobs (limit {}); retry later", config_.max_unfinished_jobs));
  }
  auto prepare = [body = std::move(req.body())] { return prepare_job(body); };
  PreparedJob p = co_await on_pool(pool_, std::move(prepare));
  if (!p.errors.empty()) co_return decode_failure_answer(p.errors);

  const std::uint64_t pixels = std::uint64_t{p.settings.width} * p.settings.height;
  if (pixels > config_.max_unfinished_pixels) {
    co_return http::make_error(http::Status::payload_too_large,
                               fmt::format("a {}x{} image is more than the collector's limit of {} pixels in flight",
                                           p.settings.width, p.settings.height, config_.max_unfinished_pixels),
                               "/width");
  }
  if (unfinished_pixels() + pixels > config_.max_unfinished_pixels) {
    co_return busy_answer(fmt::format("unfinished jobs already hold {} of the limit of {} pixels; retry later",
                                      unfinished_pixels(), config_.max_unfinished_pixels));
  }
  if (!writer_ || stopping_) co_return busy_answer("the collector is stopping");

  store::StoredJob row;
  row.digest = p.digest;
  row.settings_json = protocol::encode_settings({p.settings, p.png_bit_depth});
  row.output = p.submit.output;  // "" stands for job-<id>.png
  row.priority = p.submit.priority;
  row.tile_size = p.tile_size;
  row.state = std::string(store::kJobQueued);
  row.created_unix = now_unix();
  std::shared_ptr<const std::string> scene_json = intern_scene(p.digest, std::move(p.scene_json));

  auto insert = [row, scene_json](store::Store& s) { return insert_scene_and_job(s, row, *scene_json); };
  auto reply = co_await on_writer(*writer_, std::move(insert));
  if (reply.status != store::SubmitStatus::kAccepted) {
    ++counters_.store_busy;
    co_return busy_answer("the store is busy; retry later");
  }
  if (!reply.value || !reply.value->ok()) {
    ++counters_.store_busy;
    const std::string why = reply.value ? reply.value->error().message : std::string("the store task failed");
    util::log_error("collector: a job could not be stored: {}", why);
    co_return busy_answer("the job could not be stored; retry later");
  }
  row.id = reply.value->value();
  auto made = record_from_row(row);
  if (auto* error = std::get_if<std::string>(&made)) {
    util::log_error("collector: {}", *error);
    co_return http::make_error(http::Status::internal_server_error, "the stored job is unusable");
  }
  JobRecord rec = std::move(std::get<JobRecord>(made));
  rec.scene_json = std::move(scene_json);
  if (!queue_.add_job(rec.id, rec.priority, rec.tiles_total)) {
    util::log_error("collector: job {} could not be queued", rec.id);
    co_return http::make_error(http::Status::internal_server_error, "the job could not be queued");
  }
  ++counters_.jobs_submitted;
  util::log_info("collector: job {} submitted: {}x{}, {} samples, {} tiles of {}, priority {}, -> {}", rec.id,
                 rec.settings.width, rec.settings.height, rec.settings.samples, rec.tiles_total, rec.tile_size,
                 rec.priority, rec.output);
  const protocol::JobCreated created{rec.id, rec.digest};
  jobs_.emplace(rec.id, std::move(rec));
  co_return json_text(http::Status::created, protocol::encode(created));
}

http::Response Collector::Impl::list_jobs() const {
  protocol::JobList list;
  const std::int64_t unix_now = now_unix();
  const TimePoint now = Clock::now();
  // The newest ones when there are more than a list may hold.
  auto it = jobs_.rbegin();
  for (; it != jobs_.rend() && list.jobs.size() < protocol::kMaxListedJobs; ++it) {
    list.jobs.push_back(job_status(it->second, unix_now, now));
  }
  std::reverse(list.jobs.begin(), list.jobs.end());
  return json_text(http::Status::ok, protocol::encode(list));
}

http::Response Collector::Impl::job_status_response(JobId id) const {
  const JobRecord* job = find_job(id);
  if (job == nullptr) return job_not_found_answer(id);
  return json_text(http::Status::ok, protocol::encode(job_status(*job, now_unix(), Clock::now())));
}

net::awaitable<http::Response> Collector::Impl::job_image(JobId id, image::ImageFormat format) {
  const JobRecord* job = find_job(id);
  if (job == nullptr) co_return job_not_found_answer(id);
  // PNG at the job's bit depth, as its output file is written.
  const image::WriteOptions options{.png_bit_depth = static_cast<int>(job->png_bit_depth)};
  Encoded encoded;
  if (job->unfinished()) {
    // The framebuffer as it is now. The snapshot is held (and released) here, on the loop; the
    // pool only reads through a plain pointer, so copy-on-write stays exact.
    std::shared_ptr<const image::ImageRGBf> snapshot = job->framebuffer;
    const std::uint32_t w = job->settings.width, h = job->settings.height;
    auto encode = [image = snapshot.get(), w, h, format, options] {
      Encoded e;
      if (image != nullptr) {
        e.bytes = image::encode_image(format, *image, options, e.error);
      } else {
        e.bytes = image::encode_image(format, image::ImageRGBf(w, h), options, e.error);  // nothing stored yet
      }
      return e;
    };
    encoded = co_await on_pool(pool_, std::move(encode));
  } else {
    // Done or cancelled: the pixels live in the store only.
    auto assemble = [this, id, settings = job->settings, tile_size = job->tile_size, options, format] {
      return encode_from_store(id, settings, tile_size, options, format);
    };
    encoded = co_await on_pool(pool_, std::move(assemble));
  }
  if (!encoded.bytes) {
    util::log_error("collector: job {}: cannot produce its image: {}", id, encoded.error);
    co_return http::make_error(http::Status::internal_server_error, "cannot produce the image: " + encoded.error);
  }
  co_return http::make_binary_response(http::Status::ok, std::move(*encoded.bytes),
                                       image::format_info(format).content_type);
}

net::awaitable<http::Response> Collector::Impl::cancel_job(JobId id) {
  JobRecord* job = find_job(id);
  if (job == nullptr) co_return job_not_found_answer(id);
  if (job->state == JobState::kCancelled) co_return job_status_response(id);
  if (job->state == JobState::kDone || job->finishing) {
    co_return http::make_error(http::Status::conflict, fmt::format("job {} is finished; nothing to cancel", id));
  }
  if (!writer_ || stopping_) co_return busy_answer("the collector is stopping");
  const std::int64_t when = now_unix();
  // Durable first: a cancellation that is answered must survive a crash.
  auto record = [id, when](store::Store& s) {
    return s.set_job_state(static_cast<std::int64_t>(id), store::kJobCancelled, when);
  };
  auto reply = co_await on_writer(*writer_, std::move(record));
  if (!reply.ok() || !reply.value->ok()) {
    ++counters_.store_busy;
    if (reply.value && !reply.value->ok())
      util::log_error("collector: job {}: cannot record the cancellation: {}", id, reply.value->error().message);
    co_return busy_answer("the cancellation could not be stored; retry later");
  }
  job = find_job(id);
  // While the store wrote, the last tile may have arrived: then the job finishes after all, and
  // its "done" reaches the store after this "cancelled".
  if (job->unfinished() && !job->finishing) {
    queue_.cancel(id);
    job->state = JobState::kCancelled;
    job->finished_unix = when;
    release(*job);
    ++counters_.jobs_cancelled;
    util::log_info("collector: job {} cancelled", id);
    if (one_shot_id_ == id && config_.exit_when_done) begin_stop(1);
  }
  co_return job_status_response(id);
}

http::Response Collector::Impl::lease(std::string_view body) {
  auto request = protocol::decode_lease_request(body);
  if (!request) return decode_failure_answer(request.error());
  const TimePoint now = Clock::now();
  const LeaseResult result = queue_.lease(now);
  JobRecord* job = result.grant ? find_job(result.grant->job) : nullptr;
  if (!result.grant || job == nullptr || !job->unfinished()) {
    if (result.grant)
      util::log_error("collector: the queue leased tile {} of job {}, which is not unfinished", result.grant->tile,
                      result.grant->job);
    ++counters_.lease_retries;
    const auto ms =
        std::min<std::int64_t>(std::max<std::int64_t>(result.retry_after.count(), 1), protocol::kMaxRetryAfterMs);
    return json_text(http::Status::ok,
                     protocol::encode(protocol::LeaseReply{protocol::RetryAfter{static_cast<std::uint32_t>(ms)}}));
  }
  const TileIndex tile = result.grant->tile;
  if (!job->restored.empty() && job->restored[tile]) {
    // Impossible by construction (the queue was told these are stored); counted to prove it.
    ++counters_.restored_tile_leases;
    util::log_error("collector: tile {} of job {} was stored before this start and is being leased again", tile,
                    job->id);
  }
  if (!job->first_lease) job->first_lease = now;
  if (job->state == JobState::kQueued) job->state = JobState::kRendering;
  protocol::Lease lease;
  lease.job = job->id;
  lease.digest = job->digest;
  lease.tile = tile;
  lease.rect = scene::TileGrid(job->settings, job->tile_size).rect(tile);
  lease.settings = job->settings;
  return json_text(http::Status::ok, protocol::encode(protocol::LeaseReply{std::move(lease)}));
}

net::awaitable<http::Response> Collector::Impl::scene(std::string digest) {
  if (const auto it = scenes_.find(digest); it != scenes_.end()) {
    if (std::shared_ptr<const std::string> json = it->second.lock()) {
      co_return json_text(http::Status::ok, *json);
    }
  }
  auto fetch = [this, digest] { return scene_from_store(digest); };
  FetchedScene fetched = co_await on_pool(pool_, std::move(fetch));
  if (!fetched.error.empty()) {
    util::log_error("collector: cannot read scene {}: {}", digest, fetched.error);
    co_return busy_answer("the store could not be read; retry later");
  }
  if (!fetched.json) co_return http::make_error(http::Status::not_found, fmt::format("no such scene: {}", digest));
  co_return json_text(http::Status::ok, std::move(*fetched.json));
}

net::awaitable<http::Response> Collector::Impl::put_tile(Route route, http::Request req) {
  const std::string worker = worker_name(req);
  CheckedTile checked;
  if (req.body().size() > kInlinePayloadBytes) {
    auto check = [body = std::move(req.body())] { return check_tile_payload(body); };
    checked = co_await on_pool(pool_, std::move(check));
  } else {
    checked = check_tile_payload(req.body());
  }
  if (!checked.payload) {
    ++counters_.tiles_refused;
    co_return http::make_error(http::Status::bad_request, checked.error, checked.field);
  }
  const protocol::TilePayload& p = *checked.payload;
  if (p.job != route.job) {
    ++counters_.tiles_refused;
    co_return http::make_error(http::Status::bad_request,
                               fmt::format("the payload is for job {} but the URL names job {}", p.job, route.job),
                               "/job");
  }
  if (p.tile != route.tile) {
    ++counters_.tiles_refused;
    co_return http::make_error(http::Status::bad_request,
                               fmt::format("the payload is tile {} but the URL names tile {}", p.tile, route.tile),
                               "/tile");
  }
  JobRecord* job = find_job(route.job);
  if (job == nullptr || job->state == JobState::kCancelled) {
    ++counters_.tiles_job_gone;
    co_return submit_answer(protocol::SubmitResult::kJobGone);
  }
  if (p.tile >= job->tiles_total) {
    ++counters_.tiles_refused;
    co_return http::make_error(
        http::Status::bad_request,
        fmt::format("job {} has {} tiles; there is no tile {}", job->id, job->tiles_total, p.tile), "/tile");
  }
  const scene::TileRect expected = scene::TileGrid(job->settings, job->tile_size).rect(p.tile);
  if (p.rect != expected) {
    ++counters_.tiles_refused;
    co_return http::make_error(
        http::Status::bad_request,
        fmt::format("the payload's rectangle {}x{} at ({}, {}) is not tile {} of job {}: {}x{} at ({}, {})",
                    p.rect.width, p.rect.height, p.rect.x0, p.rect.y0, p.tile, job->id, expected.width, expected.height,
                    expected.x0, expected.y0),
        "/rect");
  }
  if (auto counts = check_sample_counts(job->settings, expected, p.spp); !counts) {
    ++counters_.tiles_refused;
    co_return http::make_error(http::Status::bad_request, counts.error().message, counts.error().path);
  }
  if (!job->restored.empty() && job->restored[p.tile]) ++counters_.restored_tile_submissions;

  if (job->unfinished() && queue_.tile_status(job->id, p.tile) == TileStatus::kStored) {
    // The framebuffer holds the stored pixels: compare here, no store round trip.
    ++counters_.tile_duplicates;
    if (!job->framebuffer || !tile_matches(*job->framebuffer, expected, p.rgb)) {
      ++counters_.faulty_results;
      util::log_warn("collector: tile {} of job {} from worker '{}' differs from the stored result: faulty worker?",
                     p.tile, job->id, worker);
    }
    co_return submit_answer(protocol::SubmitResult::kAlreadyDone);
  }
  // Not stored yet, or the job is done and its pixels are only in the store: the store decides
  // (INSERT OR IGNORE: the first result wins, and a duplicate is compared with it).
  if (!writer_ || stopping_) co_return busy_answer("the collector is stopping; retry later");
  store::TileWrite write;
  write.job = static_cast<std::int64_t>(job->id);
  write.tile = p.tile;
  write.pixels = pixels_to_blob(p.rgb, p.spp);
  write.worker = fmt::format("epoch={} worker={}", epoch_, worker);
  write.stored_unix = now_unix();
  auto reply = co_await commit_tile(*writer_, std::move(write));
  if (reply.status != store::SubmitStatus::kAccepted) {
    ++counters_.store_busy;
    co_return busy_answer("the store's queue is full; retry later");
  }
  const store::CommitResult& result = *reply.value;
  switch (result.outcome) {
    case store::TileOutcome::kStored:
      co_return on_tile_stored(route.job, p);
    case store::TileOutcome::kAlreadyPresent:
      ++counters_.tile_duplicates;
      if (!result.identical) {
        ++counters_.faulty_results;
        util::log_warn("collector: tile {} of job {} from worker '{}' differs from the stored result: faulty worker?",
                       p.tile, route.job, worker);
      }
      co_return submit_answer(protocol::SubmitResult::kAlreadyDone);
    case store::TileOutcome::kRejected:
      util::log_error("collector: the store refused tile {} of job {}: {}", p.tile, route.job, result.error);
      co_return http::make_error(http::Status::internal_server_error, "the store refused the tile");
    case store::TileOutcome::kFailed:
      break;
  }
  ++counters_.store_busy;
  util::log_warn("collector: tile {} of job {} was not stored: {}", p.tile, route.job, result.error);
  co_return busy_answer("the tile could not be stored; retry later");
}

http::Response Collector::Impl::on_tile_stored(JobId id, const protocol::TilePayload& payload) {
  const CompleteResult completed = queue_.complete(id, payload.tile, Clock::now());
  JobRecord* job = find_job(id);
  if (completed == CompleteResult::kJobGone || job == nullptr || !job->unfinished()) {
    // Cancelled while the store wrote: the pixels are stored, and nobody wants them.
    ++counters_.tiles_job_gone;
    return submit_answer(protocol::SubmitResult::kJobGone);
  }
  if (completed == CompleteResult::kAlreadyDone) {
    util::log_error("collector: the store stored tile {} of job {}, which the queue had as done", payload.tile, id);
    ++counters_.tile_duplicates;
    return submit_answer(protocol::SubmitResult::kAlreadyDone);
  }
  copy_tile(writable_framebuffer(*job), payload.rect, payload.rgb);
  count_samples(*job, payload.spp);
  ++job->tiles_done;
  ++job->stored_this_run;
  ++counters_.tiles_stored;
  if (job->state == JobState::kQueued) job->state = JobState::kRendering;
  persist_rendering(*job);
  if (queue_.is_done(id)) start_finish(id);
  return submit_answer(protocol::SubmitResult::kStored);
}

// ---- job lifecycle ------------------------------------------------------------------------------

std::shared_ptr<const std::string> Collector::Impl::intern_scene(const std::string& digest, std::string json) {
  auto& slot = scenes_[digest];
  if (auto existing = slot.lock()) return existing;
  auto text = std::make_shared<const std::string>(std::move(json));
  slot = text;
  // Forget entries of scenes no unfinished job uses any more.
  std::erase_if(scenes_, [](const auto& entry) { return entry.second.expired(); });
  return text;
}

void Collector::Impl::persist_rendering(JobRecord& job) {
  if (job.rendering_persisted || !writer_) return;
  // Informational (a restart derives the state from the stored tiles), so not awaited; but the
  // loop counts it as outstanding work until the store thread has run it, so a test that runs
  // the loop until idle sees the state written.
  const auto id = static_cast<std::int64_t>(job.id);
  auto pending = std::make_shared<net::executor_work_guard<net::io_context::executor_type>>(ioc_->get_executor());
  const store::SubmitStatus status = writer_->post([id, pending](store::Store& s) {
    if (util::Status st = s.set_job_state(id, store::kJobRendering, 0); !st) {
      util::log_warn("collector: job {}: cannot record the rendering state: {}", id, st.error().message);
    }
  });
  job.rendering_persisted = status == store::SubmitStatus::kAccepted;
}

void Collector::Impl::start_finish(JobId id) {
  JobRecord* job = find_job(id);
  assert(job != nullptr && job->unfinished());
  job->finishing = true;
  job->finish_failed = false;
  ++finishes_in_flight_;
  net::co_spawn(*ioc_, finish_job(id), [id](std::exception_ptr error) {
    if (error) log_exception(fmt::format("writing the image of job {}", id), error);
  });
}

net::awaitable<void> Collector::Impl::finish_job(JobId id) {
  JobRecord* job = find_job(id);
  std::shared_ptr<const image::ImageRGBf> image = job->framebuffer;
  if (!image) image = std::make_shared<const image::ImageRGBf>(job->settings.width, job->settings.height);
  const std::string path = (fs::path(output_dir_) / job->output).string();
  struct Written {
    bool ok = false;
    std::string error;
  };
  auto write = [img = image.get(), path, bits = job->png_bit_depth] {
    Written w;
    w.ok = image::write_image(path, *img, {.png_bit_depth = static_cast<int>(bits)}, w.error);
    return w;
  };
  const Written written = co_await on_pool(pool_, std::move(write));
  image.reset();
  job = find_job(id);
  if (!written.ok) {
    ++counters_.image_write_failures;
    util::log_error("collector: job {}: cannot write its image: {}; trying again in {} s", id, written.error,
                    kFinishRetryDelay.count());
    job->finishing = false;
    job->finish_failed = true;
    finish_ended();
    arm_finish_retry();
    co_return;
  }
  ++counters_.images_written;
  const std::int64_t when = now_unix();
  if (writer_) {
    auto mark_done = [id, when](store::Store& s) {
      return s.set_job_state(static_cast<std::int64_t>(id), store::kJobDone, when);
    };
    auto reply = co_await on_writer(*writer_, std::move(mark_done));
    if (!reply.ok() || !reply.value->ok()) {
      util::log_warn(
          "collector: job {}: the image is written but the store did not record it as done ({}); a "
          "restart writes it again",
          id, reply.value ? reply.value->error().message : std::string("store unavailable"));
    }
  }
  job = find_job(id);
  job->state = JobState::kDone;
  job->finished_unix = when;
  job->finishing = false;
  job->tiles_done = job->tiles_total;
  release(*job);
  queue_.remove_job(id);
  util::log_info("collector: job {} done: {} written", id, path);
  finish_ended();
  if (one_shot_id_ == id && config_.exit_when_done) begin_stop(0);
}

void Collector::Impl::finish_ended() {
  assert(finishes_in_flight_ > 0);
  --finishes_in_flight_;
  if (stopping_ && idle_timer_) idle_timer_->cancel();
}

void Collector::Impl::arm_finish_retry() {
  if (retry_armed_ || stopping_ || !retry_timer_) return;
  retry_armed_ = true;
  retry_timer_->expires_after(kFinishRetryDelay);
  retry_timer_->async_wait([this](const boost::system::error_code& ec) {
    retry_armed_ = false;
    if (ec || stopping_) return;
    for (auto& [id, job] : jobs_) {
      if (job.unfinished() && job.finish_failed && !job.finishing) start_finish(id);
    }
  });
}

void Collector::Impl::release(JobRecord& job) {
  job.framebuffer.reset();
  job.scene_json.reset();
  job.restored = {};
}

std::size_t Collector::Impl::unfinished_jobs() const {
  return static_cast<std::size_t>(
      std::count_if(jobs_.begin(), jobs_.end(), [](const auto& entry) { return entry.second.unfinished(); }));
}

std::uint64_t Collector::Impl::unfinished_pixels() const {
  std::uint64_t sum = 0;
  for (const auto& [id, job] : jobs_) {
    if (job.unfinished()) sum += std::uint64_t{job.settings.width} * job.settings.height;
  }
  return sum;
}

// ---- reads on the pool --------------------------------------------------------------------------

store::Store* Collector::Impl::read_store_locked(std::string& error) {
  if (reads_closed_) {
    error = "the collector is stopping";
    return nullptr;
  }
  if (!read_store_) {
    store::OpenOptions options;
    options.verify_integrity = false;  // verified at start-up by the first connection
    auto opened = store::Store::open(config_.state_dir, options);
    if (!opened) {
      error = opened.error().message;
      return nullptr;
    }
    read_store_.emplace(std::move(opened).value());
  }
  return &*read_store_;
}

Collector::Impl::Encoded Collector::Impl::encode_from_store(JobId id, scene::RenderSettings settings,
                                                            std::uint32_t tile_size, image::WriteOptions options,
                                                            image::ImageFormat format) {
  Encoded e;
  image::ImageRGBf image(settings.width, settings.height);
  {
    std::lock_guard lock(read_mu_);
    store::Store* s = read_store_locked(e.error);
    if (s == nullptr) return e;
    auto tiles = s->get_all_tiles(static_cast<std::int64_t>(id));
    if (!tiles) {
      e.error = tiles.error().message;
      return e;
    }
    const std::uint64_t count = scene::TileGrid(settings, tile_size).count();
    for (const store::StoredTile& t : tiles.value()) {
      if (t.tile >= count) continue;
      const scene::TileRect rect = scene::TileGrid(settings, tile_size).rect(t.tile);
      auto stored_tile = blob_to_tile(t.pixels, std::size_t{rect.width} * rect.height);
      if (!stored_tile) {
        e.error = fmt::format("stored tile {} has the wrong size", t.tile);
        return e;
      }
      copy_tile(image, rect, stored_tile->rgb);
    }
  }
  e.bytes = image::encode_image(format, image, options, e.error);
  return e;
}

Collector::Impl::FetchedScene Collector::Impl::scene_from_store(const std::string& digest) {
  FetchedScene f;
  std::lock_guard lock(read_mu_);
  store::Store* s = read_store_locked(f.error);
  if (s == nullptr) return f;
  auto json = s->get_scene(digest);
  if (!json) {
    f.error = json.error().message;
    return f;
  }
  f.json = std::move(json.value());
  return f;
}

// ---- stop -----------------------------------------------------------------------------------------

void Collector::Impl::begin_stop(int exit_code) {
  if (stopping_) return;
  stopping_ = true;
  if (!exit_code_) exit_code_ = exit_code;
  net::co_spawn(*ioc_, stop_sequence(), [this](std::exception_ptr error) {
    if (error) log_exception("stopping", error);
    ioc_->stop();  // whatever happened, run() returns
  });
}

net::awaitable<void> Collector::Impl::stop_sequence() {
  util::sd_notify_state("STOPPING=1");
  util::log_info("collector: stopping (grace {} ms)", config_.shutdown_grace.count());
  const auto deadline = std::chrono::steady_clock::now() + config_.shutdown_grace;
  if (server_) co_await server_->stop(config_.shutdown_grace);
  // Images being written: let them finish within the grace, so their jobs are marked done.
  while (finishes_in_flight_ > 0 && std::chrono::steady_clock::now() < deadline) {
    idle_timer_->expires_at(deadline);
    co_await idle_timer_->async_wait(net::as_tuple(net::use_awaitable));
  }
  if (finishes_in_flight_ > 0) {
    util::log_warn("collector: {} image(s) still being written at the end of the grace; a restart writes them",
                   finishes_in_flight_);
  }
  retry_timer_->cancel();
  if (writer_) {
    // Drain and close off the loop: stop() blocks until every accepted tile is committed, and
    // its callbacks post here.
    std::unique_ptr<store::TileWriter> writer = std::move(writer_);
    last_writer_stats_ = writer->stats();
    auto drain = [&writer] {
      writer->stop();
      writer.reset();  // closes the database
      return true;
    };
    co_await on_pool(pool_, std::move(drain));
  }
  auto close_reads = [this] {
    std::lock_guard lock(read_mu_);
    read_store_.reset();
    reads_closed_ = true;
    return true;
  };
  co_await on_pool(pool_, std::move(close_reads));
  util::log_info("collector: stopped; the database is closed");
}

MetricsSnapshot Collector::Impl::metrics() const {
  MetricsSnapshot m;
  m.epoch = epoch_;
  m.restored_tiles = restored_tiles_;
  for (const auto& [id, job] : jobs_) ++m.jobs_by_state[static_cast<std::size_t>(job.state)];
  m.counters = counters_;
  m.queue = queue_.stats();
  if (server_) m.http = server_->metrics();
  m.store = writer_ ? writer_->stats() : last_writer_stats_;
  return m;
}

// ---- Collector ------------------------------------------------------------------------------------

Collector::Collector(CollectorConfig config) : impl_(std::make_unique<Impl>(std::move(config))) {}
Collector::~Collector() = default;

std::optional<std::string> Collector::open() { return impl_->open(); }
std::optional<std::string> Collector::listen() { return impl_->listen(); }

int Collector::run() {
  impl_->ioc_->restart();
  impl_->ioc_->run();
  return impl_->exit_code_.value_or(0);
}

void Collector::stop() {
  net::post(*impl_->ioc_, [impl = impl_.get()] { impl->begin_stop(0); });
}

std::uint16_t Collector::port() const { return impl_->server_ ? impl_->server_->port() : 0; }

net::awaitable<http::Response> Collector::handle(http::Request req) { return impl_->handle(std::move(req)); }

http::Response Collector::handle_sync(http::Request req) {
  std::optional<http::Response> answer;
  std::exception_ptr failure;
  net::co_spawn(*impl_->ioc_, impl_->handle(std::move(req)), [&](std::exception_ptr error, http::Response res) {
    failure = error;
    answer = std::move(res);
  });
  run_until_idle();
  if (failure) std::rethrow_exception(failure);
  if (!answer) throw std::runtime_error("handle_sync: the request did not complete");
  answer->prepare_payload();
  return std::move(*answer);
}

void Collector::run_until_idle() {
  impl_->ioc_->restart();
  impl_->ioc_->run();
}

MetricsSnapshot Collector::metrics() const { return impl_->metrics(); }

net::io_context& Collector::io_context() { return *impl_->ioc_; }

int run_collector(const CollectorConfig& config) {
  Collector collector(config);
  if (auto error = collector.open()) {
    util::log_error("collector: cannot start: {}", *error);
    return 1;
  }
  if (auto error = collector.listen()) {
    util::log_error("collector: cannot start: {}", *error);
    return 1;
  }
  // Signals are caught on the loop; the first one starts the graceful stop.
  net::signal_set signals(collector.io_context(), SIGINT, SIGTERM);
  signals.async_wait([&collector](const boost::system::error_code& ec, int signal_number) {
    if (ec) return;
    util::log_info("collector: signal {} received", signal_number);
    collector.stop();
  });
  return collector.run();
}

}  // namespace dtraced::collector
