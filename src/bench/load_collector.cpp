// dtraced-load: a load generator for a collector's worker endpoints, to measure how many durable
// tile submissions per second one collector sustains and how long a lease takes under that load.
//
// Each simulated worker is a coroutine on one io_context thread. It loops until the run's time is
// up: POST /v1/lease, then PUT /v1/jobs/{job}/tiles/{tile} with a valid payload for the leased
// rectangle (constant, finite pixels), expecting "stored" or "already_done". By default the
// requests go on kept-alive connections (one http::Client, as the real worker speaks to the
// collector: each simulated worker ends up with a connection of its own); with --no-keep-alive
// every request is its own connection (Connection: close), as workers spoke before keep-alive,
// so the cost of setting up a connection (and with https://, of a TLS handshake) is part of what
// is measured. An https:// collector needs --ca-file. Nothing renders: the simulated workers
// answer as fast as the collector lets them.
//
// It writes made-up pixels into the job it is given: point it only at a throwaway collector. As a
// guard it first checks that the job exists and is unfinished, and it stops at the first lease of
// any other job rather than upload into it.
//
// With --lease-only the simulated workers lease and never upload: the rate of bare requests, a
// floor that separates the cost of HTTP from the cost of storing tiles (the leased tiles are
// offered again once the collector's re-offer bound has passed).
//
// Figures: "stored" answers divided by the time from the first request to the last answer (no
// request starts after the deadline; those in flight finish); lease and upload latency
// percentiles over every completed exchange (nearest rank), as the client sees them: from just
// before the request is sent to the parsed answer, so they include this process's own queueing;
// this process's CPU use, so that a reader can tell whether the generator rather than the
// collector was the limit.
//
// Exit codes: 0 the run happened (problems are counted in the report); 1 it could not start or was
// stopped early (unknown or finished job, a foreign lease, the job gone); 2 usage error.
//
// Threading: one thread. All state lives in main's frame and is touched only by its io_context.
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <exception>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <CLI/CLI.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/json/object.hpp>
#include <fmt/format.h>

#include "http/client.h"
#include "http/types.h"
#include "jsonio/write.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "util/file.h"
#include "util/log.h"
#include "util/result.h"

namespace dtraced::bench {
namespace {

namespace net = boost::asio;
namespace bhttp = boost::beast::http;
using Clock = std::chrono::steady_clock;

constexpr std::uint32_t kMaxWorkers = 4096;
constexpr std::uint32_t kMaxSeconds = 3600;
constexpr std::size_t kMaxTokenBytes = 4096;
// Latency samples kept per kind (4 bytes each: 64 MiB at most); past this they are counted only.
constexpr std::size_t kMaxLatencySamples = std::size_t{1} << 24;
// After a failed exchange or a 503, a simulated worker waits this long before its next request,
// so that a collector in trouble is not hammered by a spinning loop.
constexpr std::chrono::milliseconds kErrorPause{50};
// Every answer of the collector's worker endpoints is a small JSON body.
constexpr std::uint64_t kMaxAnswerBytes = protocol::kMaxMessageBytes;
// Bytes of an unexpected answer kept for the report.
constexpr std::size_t kMaxQuotedBytes = 200;
// Any finite value is a valid pixel; one constant keeps duplicates of a tile identical, so the
// collector never counts them as faulty.
constexpr float kPixelValue = 0.5f;
const http::ClientTimeouts kTimeouts{std::chrono::milliseconds(5'000), std::chrono::milliseconds(10'000),
                                     std::chrono::milliseconds(10'000), std::chrono::milliseconds(10'000)};
constexpr std::uint64_t kMaxCaFileBytes = 1 << 20;

struct Options {
  std::string collector;
  std::string token_file;
  std::string ca_file;  // for an https:// collector
  bool keep_alive = true;
  std::uint32_t workers = 64;
  std::uint32_t seconds = 10;
  std::uint64_t job = 0;
  bool json = false;
  bool lease_only = false;
};

// Durations in whole microseconds, up to kMaxLatencySamples of them.
class Latencies {
 public:
  void add(Clock::duration d) {
    if (micros_.size() == kMaxLatencySamples) {
      ++dropped_;
      return;
    }
    const auto us = std::chrono::duration_cast<std::chrono::microseconds>(d).count();
    micros_.push_back(static_cast<std::uint32_t>(std::clamp<std::int64_t>(us, 0, UINT32_MAX)));
  }
  // Sorts the samples once; call after the run.
  void finish() { std::sort(micros_.begin(), micros_.end()); }
  std::size_t count() const { return micros_.size(); }
  std::uint64_t dropped() const { return dropped_; }
  // Nearest-rank percentile in milliseconds (0 < p <= 100); NaN without samples.
  double percentile_ms(double p) const {
    if (micros_.empty()) return std::nan("");
    const auto rank = static_cast<std::size_t>(std::ceil(p / 100.0 * static_cast<double>(micros_.size())));
    return micros_[std::clamp<std::size_t>(rank, 1, micros_.size()) - 1] / 1000.0;
  }

 private:
  std::vector<std::uint32_t> micros_;
  std::uint64_t dropped_ = 0;
};

struct Tally {
  std::uint64_t leases = 0;          // tiles leased
  std::uint64_t retry_after = 0;     // "nothing now" answers: the job had no tile to offer
  std::uint64_t stored = 0;          // 200 "stored": durably committed
  std::uint64_t already_done = 0;    // 200 "already_done"
  std::uint64_t job_gone = 0;        // 410
  std::uint64_t busy = 0;            // 503 from either endpoint
  std::uint64_t http_errors = 0;     // any other status, or a body that does not decode
  std::uint64_t network_errors = 0;  // no answer: refused, reset, timed out
  std::string first_problem;         // the first of the last three, quoted in the report
  Latencies lease;                   // POST /v1/lease, any complete answer
  Latencies upload;                  // PUT .../tiles/..., any complete answer
};

struct Run {
  http::Url url;
  http::Client* client = nullptr;  // every request
  std::string authorization;
  std::uint64_t job = 0;
  bool lease_only = false;
  Clock::time_point start;
  Clock::time_point deadline;
  Clock::time_point last_answer;  // when the last simulated worker ended
  bool stopped = false;           // a condition that makes the figures meaningless; see reason
  std::string reason;
  Tally tally;

  bool running() const { return !stopped && Clock::now() < deadline; }
  void stop(std::string why) {
    if (stopped) return;
    stopped = true;
    reason = std::move(why);
  }
  void note_problem(std::string what) {
    if (tally.first_problem.empty()) tally.first_problem = std::move(what);
  }
};

std::string quote(const http::Response& res) {
  std::string body = res.body().substr(0, kMaxQuotedBytes);
  for (char& c : body) {
    if (c < 0x20 || c > 0x7e) c = '?';
  }
  return fmt::format("HTTP {}: {}", res.result_int(), body);
}

// The first line of the file, without surrounding blanks (the rule the dtraced CLI applies).
util::Result<std::string> read_token(const std::string& path) {
  util::Result<std::string> text = util::read_file_limited(path, kMaxTokenBytes);
  if (!text) return text.error();
  std::string token = text->substr(0, text->find('\n'));
  const std::size_t begin = token.find_first_not_of(" \t\r");
  const std::size_t end = token.find_last_not_of(" \t\r");
  token = begin == std::string::npos ? std::string() : token.substr(begin, end - begin + 1);
  if (token.empty()) return util::Error{fmt::format("{}: the token file's first line is empty", path)};
  return token;
}

net::awaitable<http::ClientResult> exchange(const Run& run, http::Request req, std::string_view worker) {
  req.set(bhttp::field::authorization, run.authorization);
  req.set(protocol::kWorkerHeader, worker);
  co_return co_await run.client->request(run.url, std::move(req), kMaxAnswerBytes);
}

net::awaitable<void> pause_for(net::steady_timer& timer, Clock::duration d) {
  timer.expires_after(d);
  co_await timer.async_wait(net::use_awaitable);
}

// Before the run: the job must exist and still have tiles to lease.
net::awaitable<util::Status> check_job(const Run& run) {
  const std::string target = fmt::format("/v1/jobs/{}", run.job);
  http::ClientResult r = co_await exchange(run, http::make_request(http::Verb::get, target), "dtraced-load");
  if (!r.ok()) co_return util::Error{r.message, "GET " + target};
  if (r.response.result() != http::Status::ok) co_return util::Error{quote(r.response), "GET " + target};
  auto status = protocol::decode_job_status(r.response.body());
  if (!status) co_return util::Error{status.error().front().to_string(), "GET " + target};
  const protocol::JobStatus& s = status.value();
  if (s.state != protocol::JobState::kQueued && s.state != protocol::JobState::kRendering) {
    co_return util::Error{
        fmt::format("job {} is {}; the load needs an unfinished job", run.job, protocol::to_string(s.state))};
  }
  co_return util::Status();
}

net::awaitable<void> simulated_worker(Run& run, std::uint32_t index) {
  const std::string name = fmt::format("dtraced-load-{}-{}", ::getpid(), index);
  const std::string lease_body = protocol::encode(protocol::LeaseRequest{name, 1});
  net::steady_timer pause(co_await net::this_coro::executor);
  Tally& t = run.tally;

  while (run.running()) {
    // ---- lease ----
    Clock::time_point sent = Clock::now();
    http::ClientResult r = co_await exchange(
        run, http::make_request(http::Verb::post, "/v1/lease", lease_body, http::kJsonContentType), name);
    if (!r.ok()) {
      ++t.network_errors;
      run.note_problem("POST /v1/lease: " + r.message);
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    t.lease.add(Clock::now() - sent);
    if (r.response.result() == http::Status::service_unavailable) {
      ++t.busy;
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    auto reply = protocol::decode_lease_reply(r.response.body());
    if (r.response.result() != http::Status::ok || !reply) {
      ++t.http_errors;
      run.note_problem("POST /v1/lease: " + quote(r.response));
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    if (const auto* retry = std::get_if<protocol::RetryAfter>(&reply.value())) {
      ++t.retry_after;
      const auto left = run.deadline - Clock::now();
      co_await pause_for(pause, std::min<Clock::duration>(std::chrono::milliseconds(retry->ms), left));
      continue;
    }
    const protocol::Lease& lease = std::get<protocol::Lease>(reply.value());
    if (lease.job != run.job) {
      // Uploading made-up pixels into someone else's job would corrupt it.
      run.stop(fmt::format("the collector leased a tile of job {}, not of job {}: it is not idle", lease.job, run.job));
      co_return;
    }
    ++t.leases;
    if (run.lease_only) continue;

    // ---- upload ----
    protocol::TilePayload payload;
    payload.job = lease.job;
    payload.tile = lease.tile;
    payload.rect = lease.rect;
    payload.rgb.assign(std::size_t{lease.rect.width} * lease.rect.height * 3, kPixelValue);
    http::Request put = http::make_request(http::Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", lease.job, lease.tile),
                                           protocol::encode_tile_payload(payload), http::kBinaryContentType);
    sent = Clock::now();
    r = co_await exchange(run, std::move(put), name);
    if (!r.ok()) {
      ++t.network_errors;
      run.note_problem("PUT tile: " + r.message);
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    t.upload.add(Clock::now() - sent);
    const http::Status status = r.response.result();
    if (status == http::Status::service_unavailable) {
      ++t.busy;
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    auto answer = protocol::decode_submit_result(r.response.body());
    if ((status != http::Status::ok && status != http::Status::gone) || !answer) {
      ++t.http_errors;
      run.note_problem("PUT tile: " + quote(r.response));
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    switch (answer.value()) {
      case protocol::SubmitResult::kStored:
        ++t.stored;
        break;
      case protocol::SubmitResult::kAlreadyDone:
        ++t.already_done;
        break;
      case protocol::SubmitResult::kJobGone:
        ++t.job_gone;
        run.stop(fmt::format("job {} is gone (cancelled?)", run.job));
        co_return;
    }
  }
}

double cpu_seconds() {
  rusage usage{};
  ::getrusage(RUSAGE_SELF, &usage);
  const auto seconds = [](const timeval& tv) { return static_cast<double>(tv.tv_sec) + tv.tv_usec / 1e6; };
  return seconds(usage.ru_utime) + seconds(usage.ru_stime);
}

void report(const Options& o, const Run& run, const http::ClientStats& client, double elapsed_s, double cpu_s) {
  const Tally& t = run.tally;
  const double rate = elapsed_s > 0 ? static_cast<double>(t.stored) / elapsed_s : 0;
  const double lease_rate = elapsed_s > 0 ? static_cast<double>(t.leases) / elapsed_s : 0;
  if (o.json) {
    // A percentile without samples is NaN, which JSON cannot carry: null.
    const auto ms = [](double v) { return std::isnan(v) ? boost::json::value(nullptr) : boost::json::value(v); };
    boost::json::object j;
    j["workers"] = o.workers;
    j["job"] = o.job;
    j["elapsed_s"] = elapsed_s;
    j["stored"] = t.stored;
    j["stored_per_s"] = rate;
    j["already_done"] = t.already_done;
    j["job_gone"] = t.job_gone;
    j["lease_only"] = o.lease_only;
    j["keep_alive"] = o.keep_alive;
    j["tls"] = run.url.tls;
    j["connections_opened"] = client.connections_opened;
    j["tls_handshakes"] = client.tls_handshakes;
    j["leases"] = t.leases;
    j["leases_per_s"] = lease_rate;
    j["retry_after"] = t.retry_after;
    j["busy"] = t.busy;
    j["http_errors"] = t.http_errors;
    j["network_errors"] = t.network_errors;
    j["lease_samples"] = t.lease.count();
    j["lease_p50_ms"] = ms(t.lease.percentile_ms(50));
    j["lease_p90_ms"] = ms(t.lease.percentile_ms(90));
    j["lease_p99_ms"] = ms(t.lease.percentile_ms(99));
    j["upload_p50_ms"] = ms(t.upload.percentile_ms(50));
    j["upload_p90_ms"] = ms(t.upload.percentile_ms(90));
    j["upload_p99_ms"] = ms(t.upload.percentile_ms(99));
    j["generator_cpu"] = elapsed_s > 0 ? cpu_s / elapsed_s : 0;
    j["stopped"] = run.reason;
    j["first_problem"] = t.first_problem;
    fmt::print("{}\n", jsonio::to_text(j));
    return;
  }
  fmt::print("dtraced-load: {} simulated workers for {:.2f} s against {} (job {}){}, {}\n", o.workers, elapsed_s,
             run.url.to_string(), o.job, o.lease_only ? ", leases only" : "",
             o.keep_alive ? "kept-alive connections" : "a connection per request");
  fmt::print("  stored          {:>10}  {:>10.1f} /s\n", t.stored, rate);
  fmt::print("  already_done    {:>10}\n", t.already_done);
  fmt::print("  leases          {:>10}  {:>10.1f} /s  ({} retry_after answers)\n", t.leases, lease_rate, t.retry_after);
  fmt::print("  errors          {:>10}  network, {} busy (503), {} other, {} job_gone\n", t.network_errors, t.busy,
             t.http_errors, t.job_gone);
  const auto line = [](std::string_view what, const Latencies& l) {
    fmt::print("  {} ms  p50 {:.2f}  p90 {:.2f}  p99 {:.2f}  max {:.2f}  ({} samples{})\n", what, l.percentile_ms(50),
               l.percentile_ms(90), l.percentile_ms(99), l.percentile_ms(100), l.count(),
               l.dropped() ? fmt::format(", {} more not kept", l.dropped()) : "");
  };
  line("lease latency ", t.lease);
  line("upload latency", t.upload);
  fmt::print("  connections     {:>10}  opened ({} TLS handshakes, {} requests reused a connection)\n",
             client.connections_opened, client.tls_handshakes, client.reuses);
  fmt::print("  generator CPU   {:.2f} of one core\n", elapsed_s > 0 ? cpu_s / elapsed_s : 0);
  if (!t.first_problem.empty()) fmt::print("  first problem: {}\n", t.first_problem);
  if (t.retry_after > 0) {
    fmt::print(
        "  warning: the collector had no tile to lease {} times (job finished, or every tile out): the rate "
        "understates its capacity; use a larger job\n",
        t.retry_after);
  }
}

int run_load(const Options& o) {
  util::Result<http::Url> url = http::parse_base_url(o.collector);
  if (!url) {
    fmt::print(stderr, "--collector: {}\n", url.error().message);
    return 2;
  }
  const util::Result<std::string> token = read_token(o.token_file);
  if (!token) {
    fmt::print(stderr, "--token-file: {}\n", token.error().to_string());
    return 2;
  }
  http::ClientOptions client_options;
  client_options.timeouts = kTimeouts;
  if (url->tls) {
    if (o.ca_file.empty()) {
      fmt::print(stderr, "--ca-file: required for an https:// collector (its tls/ca.pem)\n");
      return 2;
    }
    util::Result<std::string> pem = util::read_file_limited(o.ca_file, kMaxCaFileBytes);
    if (!pem) {
      fmt::print(stderr, "--ca-file: {}\n", pem.error().to_string());
      return 2;
    }
    http::ClientTls tls{std::move(pem).value(), o.ca_file, std::nullopt};
    if (util::Status usable = http::check_client_tls(tls); !usable) {
      fmt::print(stderr, "--ca-file: {}\n", usable.error().to_string());
      return 2;
    }
    client_options.tls = std::move(tls);
  }
  // Kept alive: every simulated worker's connection may wait idle while it pauses.
  client_options.max_idle_connections = o.keep_alive ? o.workers : 0;
  client_options.max_requests_per_connection = o.keep_alive ? client_options.max_requests_per_connection : 1;
  Run run;
  run.url = *url;
  run.authorization = "Bearer " + *token;
  run.job = o.job;
  run.lease_only = o.lease_only;

  net::io_context io{1};
  http::Client client(io.get_executor(), client_options);  // after io: destroyed before it
  run.client = &client;
  util::Status checked = util::Error{"the job check did not finish"};
  net::co_spawn(io, check_job(run), [&checked](std::exception_ptr e, util::Status result) {
    if (!e) {
      checked = std::move(result);
      return;
    }
    try {
      std::rethrow_exception(e);
    } catch (const std::exception& ex) {
      checked = util::Error{fmt::format("job check: {}", ex.what())};
    }
  });
  io.run();
  if (!checked) {
    fmt::print(stderr, "dtraced-load: {}\n", checked.error().to_string());
    return 1;
  }

  io.restart();
  const double cpu_before = cpu_seconds();
  run.start = Clock::now();
  run.deadline = run.start + std::chrono::seconds(o.seconds);
  run.last_answer = run.start;
  for (std::uint32_t i = 0; i < o.workers; ++i) {
    net::co_spawn(io, simulated_worker(run, i), [&run, i](std::exception_ptr e) {
      run.last_answer = std::max(run.last_answer, Clock::now());
      if (!e) return;
      try {
        std::rethrow_exception(e);
      } catch (const std::exception& ex) {
        util::log_error("dtraced-load: simulated worker {} failed: {}", i, ex.what());
        run.stop(fmt::format("simulated worker {} failed: {}", i, ex.what()));
      }
    });
  }
  io.run();
  const double elapsed = std::chrono::duration<double>(run.last_answer - run.start).count();
  const double cpu = cpu_seconds() - cpu_before;
  run.tally.lease.finish();
  run.tally.upload.finish();
  report(o, run, client.stats(), elapsed, cpu);
  if (run.stopped) {
    fmt::print(stderr, "dtraced-load: stopped early: {}\n", run.reason);
    return 1;
  }
  return 0;
}

}  // namespace
}  // namespace dtraced::bench

int main(int argc, char** argv) {
  dtraced::bench::Options o;
  CLI::App app{
      "dtraced-load: simulated workers lease tiles from a collector and upload made-up pixels as fast as it answers; "
      "prints durable submissions per second and lease latency. Writes into the job it is given: use a throwaway "
      "collector.",
      "dtraced-load"};
  app.add_option("--collector", o.collector, "Collector base URL, http://HOST:PORT or https://HOST:PORT")->required();
  app.add_option("--ca-file", o.ca_file, "The collector's CA certificate (PEM), for an https:// collector");
  app.add_flag("--keep-alive,!--no-keep-alive", o.keep_alive,
               "Kept-alive connections (the default, as workers speak), or a connection per request");
  app.add_option("--token-file", o.token_file, "File holding the farm's bearer token")->required();
  app.add_option("--job", o.job, "The job to lease from and upload into (must be unfinished)")
      ->required()
      ->check(CLI::Range(std::uint64_t{1}, dtraced::protocol::kMaxId));
  app.add_option("--workers", o.workers, "Simulated workers (concurrent coroutines on one thread)")
      ->check(CLI::Range(std::uint32_t{1}, dtraced::bench::kMaxWorkers))
      ->capture_default_str();
  app.add_option("--seconds", o.seconds, "Length of the run")
      ->check(CLI::Range(std::uint32_t{1}, dtraced::bench::kMaxSeconds))
      ->capture_default_str();
  app.add_flag("--lease-only", o.lease_only, "Lease without uploading: the rate of bare requests");
  app.add_flag("--json", o.json, "Print the figures as one JSON object");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  return dtraced::bench::run_load(o);
}
