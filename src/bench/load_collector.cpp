// dtraced-load: a load generator for a collector's worker endpoints, to measure how many durable
// tile submissions per second one collector sustains and how long a lease takes under that load.
//
// Each simulated worker is a coroutine on one io_context thread. It loops until the run's time is
// up: POST /v1/lease, then PUT /v1/jobs/{job}/tiles/{tile} with a valid payload for the leased
// rectangle (constant, finite pixels), expecting "stored" or "already_done". By default the
// requests go on kept-alive connections, one per slot (below), as each real worker's slot has one
// request in flight, under http::Client's rules (at most 500 requests a connection, none reused
// after 15 s idle); with --no-keep-alive every request is its own connection (Connection: close),
// as workers spoke before keep-alive, so the cost of setting up a connection (and with https://,
// of a TLS handshake) is part of what is measured. An https:// collector needs --ca-file. Nothing
// renders: by default the simulated workers answer as fast as the collector lets them.
//
// The generator has to be cheap per tile: it runs on one core against a collector on one other,
// and is only a measure of the collector while it has CPU to spare. So a slot builds its requests
// once and patches them (the lease request is constant; an upload's pixels stay in place and only
// the tile's header, its SHA-256 and the request line change), sends each request as one buffer
// (one TLS record, one write), and reads answers with a parser for exactly what the collector
// sends, on a connection of its own (Wire) rather than through http::Client and Beast. The
// payload is checked against protocol::encode_tile_payload's bytes before every run.
//
// With --slots N each simulated worker runs N lease/upload loops at once under one name, as the
// real worker runs one slot per render thread (worker/worker.h): a worker of N threads has up to N
// tiles in flight, and its lease requests say threads = N. Each slot chains its own next lease
// (--next-lease). The default, 1, is one tile in flight per worker, the figures of earlier runs.
//
// A farm rather than a flood: --render-ms N makes each simulated worker hold every leased tile for
// N ms (uniform within +/- --render-jitter percent) before it uploads, as a worker rendering it
// would; --ramp-ms spreads the workers' first requests over that long, as a farm's workers start
// at different times; --warmup-seconds runs before the measured window and is not counted (its
// connections and TLS handshakes stay for the window; a line on stderr says when the window opens,
// so that a script can sample the collector's counters then). A
// "nothing now" answer (retry_after_ms) is obeyed as the real worker obeys it: a wait drawn
// uniformly from [asked, 1.5 x asked], never less than 50 ms. Without --job the workers are idle
// workers of a farm with no work: every lease must come back "nothing now", and the figures are
// the polling load they put on the collector (a granted lease stops the run: the collector is not
// idle, and nothing is uploaded). Each simulated worker keeps a connection open, so the run raises
// this process's open-file limit (RLIMIT_NOFILE) to the workers plus a margin, within the hard
// limit, and refuses to start when the hard limit is too low.
//
// It writes made-up pixels into the job it is given: point it only at a throwaway collector. As a
// guard it first checks that the job exists and is unfinished, and it stops at the first lease of
// any other job rather than upload into it.
//
// With --next-lease each upload asks for the worker's next lease in the same exchange
// (protocol::kNextLeaseHeader), as the real worker does: a tile then costs one request, not two,
// and POST /v1/lease goes out only when an answer carried no lease (the first tile, a retry-after,
// an error). Without it every tile is a lease and an upload (older workers).
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
#include <array>
#include <bit>
#include <cassert>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <exception>
#include <limits>
#include <memory>
#include <optional>
#include <random>
#include <stdexcept>
#include <string>
#include <string_view>
#include <tuple>
#include <utility>
#include <vector>

#include <CLI/CLI.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/ssl/context.hpp>
#include <boost/asio/ssl/stream.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/http/empty_body.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/json/object.hpp>
#include <fmt/format.h>
#include <openssl/ssl.h>
#include <openssl/x509v3.h>

#include "async/async.h"
#include "http/client.h"
#include "http/serialise.h"
#include "http/types.h"
#include "jsonio/write.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "protocol/worker_messages.h"
#include "util/file.h"
#include "util/log.h"
#include "util/result.h"
#include "util/sha256.h"

namespace dtraced::bench {
namespace {

namespace net = boost::asio;
namespace ssl = net::ssl;
namespace beast = boost::beast;
namespace bhttp = boost::beast::http;
using tcp = net::ip::tcp;
using async::kAwaitTuple;
using boost::system::error_code;
using Clock = std::chrono::steady_clock;

// Each simulated worker holds a connection (a file descriptor) and a coroutine frame (a few KiB):
// 20,000 fit the open-file limits of most systems once the soft limit is raised.
constexpr std::uint32_t kMaxWorkers = 20'000;
// Slots of one simulated worker (its render threads); workers x slots is bounded by kMaxWorkers too,
// as each slot may hold a connection.
constexpr std::uint32_t kMaxSlots = 256;
// Descriptors beyond one per simulated worker: stdio, the io_context's own, the files read.
constexpr rlim_t kSpareFds = 64;
// A simulated tile takes at most ten minutes; ramp-up and warm-up are bounded alike.
constexpr std::uint32_t kMaxRenderMs = 600'000;
constexpr std::uint32_t kMaxRampMs = 600'000;
constexpr std::uint32_t kMaxWarmupSeconds = 600;
constexpr std::uint32_t kMaxJitterPercent = 100;
// The real worker's bounds on a "nothing now" wait (worker/backoff.h): never sooner than this.
constexpr std::chrono::milliseconds kMinRetryAfter{50};
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
// The simulated workers' own connections (Wire below) keep the rules of http::Client, the real
// worker's: at most this many requests on a connection (the last says Connection: close), an
// idle connection older than this is not reused, and a connect, handshake or exchange that takes
// longer than this fails (a watchdog, checking every kWatchdogPeriod, closes its socket).
const std::uint32_t kMaxRequestsPerConnection = http::ClientOptions{}.max_requests_per_connection;
const Clock::duration kMaxIdle = http::ClientOptions{}.max_idle;
constexpr Clock::duration kExchangeTimeout = std::chrono::seconds(10);
constexpr Clock::duration kWatchdogPeriod = std::chrono::milliseconds(250);
constexpr std::size_t kMaxAnswerHeaderBytes = http::kMaxResponseHeaderBytes;
// Bytes read from a connection at once.
constexpr std::size_t kReadChunk = 16 << 10;
// Room for an upload's HTTP header in front of its payload (a token is at most kMaxTokenBytes).
constexpr std::size_t kUploadHeadRoom = kMaxTokenBytes + 1024;
// As http::Client: TLS 1.2 suites forward secret (ECDHE) and AEAD only; TLS 1.3's are all both.
constexpr const char* kTls12Ciphers = "ECDHE+AESGCM:ECDHE+CHACHA20";

struct Options {
  std::string collector;
  std::string token_file;
  std::string ca_file;  // for an https:// collector
  bool keep_alive = true;
  std::uint32_t workers = 64;
  std::uint32_t slots = 1;  // lease/upload loops per simulated worker, as a worker's render threads
  std::uint32_t seconds = 10;
  std::uint64_t job = 0;  // 0: no job, idle workers
  bool json = false;
  bool lease_only = false;
  bool next_lease = false;           // uploads ask for the next lease (protocol::kNextLeaseHeader)
  std::uint32_t render_ms = 0;       // simulated render time of a tile
  std::uint32_t render_jitter = 20;  // percent, either side of render_ms
  std::uint32_t ramp_ms = 0;         // first requests spread over this long
  std::uint32_t warmup_seconds = 0;  // before the measured window
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
  std::uint64_t upload_leases = 0;   // of which in the answer to an upload (--next-lease)
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

// Counters of the simulated workers' connections, summed over all slots.
struct WireStats {
  std::uint64_t connections_opened = 0;  // TCP connections connected (and TLS handshaken)
  std::uint64_t tls_handshakes = 0;
  std::uint64_t reuses = 0;   // exchanges sent on a kept-alive connection
  std::uint64_t retries = 0;  // sent again after a reused connection failed before answering
};

class Wire;

struct Run {
  http::Url url;
  http::Client* client = nullptr;  // the job check
  tcp::endpoint endpoint;          // the collector's address, resolved once
  ssl::context* tls = nullptr;     // for an https:// collector
  bool keep_alive = true;
  std::vector<Wire*> wires;  // one connection per slot, in slot order; the watchdog's
  std::uint32_t active = 0;  // slots still running
  WireStats wire_stats;
  std::string authorization;
  std::uint64_t job = 0;  // 0: idle workers, no lease may be granted
  bool lease_only = false;
  bool next_lease = false;
  std::uint32_t slots = 1;
  std::uint32_t render_ms = 0;
  std::uint32_t render_jitter = 0;  // percent
  std::uint32_t ramp_ms = 0;
  std::mt19937_64 rng{0x64747261636564};  // jitter; fixed seed: runs draw the same waits
  Clock::time_point start;                // first request may go
  Clock::time_point measure_from;         // start + warm-up: the measured window opens
  Clock::time_point deadline;
  Clock::time_point last_answer;  // when the last simulated worker ended
  bool stopped = false;           // a condition that makes the figures meaningless; see reason
  std::string reason;
  Tally tally;         // the measured window
  Tally warmup_tally;  // before it; discarded

  bool running() const { return !stopped && Clock::now() < deadline; }
  // Where an exchange that started at `sent` is counted.
  Tally& tally_for(Clock::time_point sent) { return sent < measure_from ? warmup_tally : tally; }
  // A tile's simulated render time: render_ms +/- render_jitter percent, uniformly.
  Clock::duration render_time() {
    if (render_ms == 0) return Clock::duration::zero();
    const double spread = render_ms * (render_jitter / 100.0);
    std::uniform_real_distribution<double> uniform(render_ms - spread, render_ms + spread);
    return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double, std::milli>(uniform(rng)));
  }
  // The wait after "nothing now, ask again in `asked`", as the real worker draws it.
  Clock::duration retry_wait(std::chrono::milliseconds asked) {
    const auto base = std::max(asked, kMinRetryAfter).count();
    std::uniform_int_distribution<std::chrono::milliseconds::rep> uniform(base, base + base / 2);
    return std::chrono::milliseconds(uniform(rng));
  }
  void stop(std::string why) {
    if (stopped) return;
    stopped = true;
    reason = std::move(why);
  }
  void note_problem(std::string what) {
    if (tally.first_problem.empty()) tally.first_problem = std::move(what);
  }
};

std::string quote(unsigned status, std::string_view body) {
  std::string text(body.substr(0, kMaxQuotedBytes));
  for (char& c : text) {
    if (c < 0x20 || c > 0x7e) c = '?';
  }
  return fmt::format("HTTP {}: {}", status, text);
}

std::string quote(const http::Response& res) { return quote(res.result_int(), res.body()); }

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

net::awaitable<http::ClientResult> exchange(const Run& run, http::Client& client, http::Request req,
                                            std::string_view worker) {
  req.set(bhttp::field::authorization, run.authorization);
  req.set(protocol::kWorkerHeader, worker);
  // A worker of this build: leases need its pixel version.
  req.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
  co_return co_await client.request(run.url, std::move(req), kMaxAnswerBytes);
}

net::awaitable<void> pause_for(net::steady_timer& timer, Clock::duration d) {
  timer.expires_after(d);
  co_await timer.async_wait(net::use_awaitable);
}

// Before the run: the job must exist and still have tiles to lease.
net::awaitable<util::Status> check_job(const Run& run) {
  const std::string target = fmt::format("/v1/jobs/{}", run.job);
  http::ClientResult r =
      co_await exchange(run, *run.client, http::make_request(http::Verb::get, target), "dtraced-load");
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

template <typename U>
void put_le(char* at, U value) {
  for (std::size_t i = 0; i < sizeof(U); ++i) at[i] = static_cast<char>((value >> (8 * i)) & 0xff);
}

// An answer as Wire::receive read it; the body is a view into the wire's parser, valid until its
// next receive.
struct Answer {
  unsigned status = 0;
  std::string_view body;
  bool close = false;  // the collector closes the connection after it
};

// The connection of one slot: plain TCP or TLS, with its read buffer kept from one answer to the
// next. Why not http::Client: the generator must cost the collector's core's worth of tiles on one
// core of its own, and a Beast message built, serialised (as two TLS records: Asio's TLS stream
// writes 8 KiB of a gathered request at a time) and parsed for every tile cost about as much as
// the collector spends storing it. A Wire sends a request that is one contiguous buffer in one
// write (one TLS record, one sendmsg) and feeds what it reads to Beast's parser itself (no
// composed read operations); the rules that shape the collector's
// load (kept-alive connections, kMaxRequestsPerConnection, kMaxIdle, the fields a worker sends)
// are the client's.
class Wire {
 public:
  explicit Wire(net::any_io_executor executor) : executor_(std::move(executor)) {}

  bool is_open() const { return socket() != nullptr && socket()->is_open(); }
  std::uint32_t requests() const { return requests_; }
  Clock::time_point idle_since() const { return idle_since_; }

  // Connects to `to` (and with `tls`, shakes hands and checks that the certificate names `host`);
  // an empty string, or why not.
  net::awaitable<std::string> open(const tcp::endpoint& to, ssl::context* tls, const std::string& host,
                                   WireStats& stats) {
    close();
    plain_.reset();
    tls_.reset();
    have_ = consumed_ = 0;
    requests_ = 0;
    timed_out_ = false;
    busy_since_ = Clock::now();
    if (tls != nullptr) {
      tls_ = std::make_unique<ssl::stream<tcp::socket>>(executor_, *tls);
    } else {
      plain_ = std::make_unique<tcp::socket>(executor_);
    }
    auto [connect_ec] = co_await socket()->async_connect(to, kAwaitTuple);
    if (connect_ec) co_return problem("connecting", connect_ec);
    error_code ignored;
    socket()->set_option(tcp::no_delay(true), ignored);
    ++stats.connections_opened;
    if (tls_) {
      SSL* handle = tls_->native_handle();
      X509_VERIFY_PARAM* param = SSL_get0_param(handle);
      X509_VERIFY_PARAM_set_hostflags(param, X509_CHECK_FLAG_NO_PARTIAL_WILDCARDS);
      error_code not_ip;
      net::ip::make_address(host, not_ip);
      const bool set =
          !not_ip ? X509_VERIFY_PARAM_set1_ip_asc(param, host.c_str()) == 1
                  : SSL_set_tlsext_host_name(handle, host.c_str()) == 1 && SSL_set1_host(handle, host.c_str()) == 1;
      if (!set) co_return fmt::format("cannot set up TLS for {}", host);
      auto [handshake_ec] = co_await tls_->async_handshake(ssl::stream_base::client, kAwaitTuple);
      if (handshake_ec) co_return problem("the TLS handshake", handshake_ec);
      ++stats.tls_handshakes;
    }
    busy_since_ = {};
    idle_since_ = Clock::now();
    co_return std::string();
  }

  // Sends `request` and reads the whole answer into `answer`; an empty string, or why not.
  // `started`: some byte of the answer came (a request that failed before is safe to send again).
  net::awaitable<std::string> exchange(std::string_view request, Answer& answer, bool& started) {
    ++requests_;
    busy_since_ = Clock::now();
    started = false;
    error_code write_ec;
    if (tls_) {
      std::tie(write_ec, std::ignore) = co_await net::async_write(*tls_, net::buffer(request), kAwaitTuple);
    } else {
      std::tie(write_ec, std::ignore) = co_await net::async_write(*plain_, net::buffer(request), kAwaitTuple);
    }
    if (write_ec) co_return problem("sending the request", write_ec);
    std::string failed = co_await receive(answer, started);
    busy_since_ = {};
    idle_since_ = Clock::now();
    co_return failed;
  }

  void close() {
    if (socket() == nullptr) return;
    error_code ignored;
    socket()->shutdown(tcp::socket::shutdown_both, ignored);
    socket()->close(ignored);
  }

  // The watchdog: closes the connection when a connect, handshake or exchange has been going on
  // for longer than `limit`; its operations then fail, as a timeout.
  void expire_if_older(Clock::time_point now, Clock::duration limit) {
    if (busy_since_ == Clock::time_point{} || now - busy_since_ <= limit || !is_open()) return;
    timed_out_ = true;
    close();
  }

 private:
  const tcp::socket* socket() const { return tls_ ? &tls_->next_layer() : plain_.get(); }
  tcp::socket* socket() { return tls_ ? &tls_->next_layer() : plain_.get(); }

  std::string problem(std::string_view doing, const error_code& ec) const {
    if (timed_out_) {
      return fmt::format("{} timed out after {} s", doing,
                         std::chrono::duration_cast<std::chrono::seconds>(kExchangeTimeout).count());
    }
    if (ec == net::error::eof || ec == ssl::error::stream_truncated) {
      return fmt::format("{}: the collector closed the connection", doing);
    }
    return fmt::format("{}: {}", doing, ec.message());
  }

  // Appends what the connection has to in_; an empty string, or why not.
  net::awaitable<std::string> read_more() {
    if (in_.size() - have_ < kReadChunk) in_.resize(have_ + kReadChunk);
    const net::mutable_buffer free = net::buffer(in_.data() + have_, in_.size() - have_);
    error_code ec;
    std::size_t n = 0;
    if (tls_) {
      std::tie(ec, n) = co_await tls_->async_read_some(free, kAwaitTuple);
    } else {
      std::tie(ec, n) = co_await plain_->async_read_some(free, kAwaitTuple);
    }
    if (ec) co_return problem("reading the answer", ec);
    have_ += n;
    co_return std::string();
  }

  // Reads one answer through Beast's parser, fed from in_ as bytes come (no composed read
  // operation: one async_read_some a chunk).
  net::awaitable<std::string> receive(Answer& answer, bool& started) {
    // What came after the last answer (nothing, from a collector that answers one request at a
    // time) stays for this one.
    if (consumed_ > 0) {
      std::memmove(in_.data(), in_.data() + consumed_, have_ - consumed_);
      have_ -= consumed_;
      consumed_ = 0;
    }
    parser_.emplace();
    parser_->header_limit(static_cast<std::uint32_t>(kMaxAnswerHeaderBytes));
    parser_->body_limit(kMaxAnswerBytes);
    parser_->eager(true);
    for (;;) {
      started = started || have_ > 0;
      if (consumed_ < have_) {
        error_code ec;
        consumed_ += parser_->put(net::buffer(in_.data() + consumed_, have_ - consumed_), ec);
        if (ec && ec != bhttp::error::need_more) co_return fmt::format("a malformed answer: {}", ec.message());
        if (parser_->is_done()) break;
      }
      if (consumed_ == have_) have_ = consumed_ = 0;  // the parser holds what it took
      if (std::string failed = co_await read_more(); !failed.empty()) co_return failed;
    }
    const auto& message = parser_->get();
    answer.status = message.result_int();
    answer.close = !message.keep_alive();
    answer.body = message.body();
    co_return std::string();
  }

  net::any_io_executor executor_;
  std::unique_ptr<tcp::socket> plain_;             // http://
  std::unique_ptr<ssl::stream<tcp::socket>> tls_;  // https://
  std::string in_;                                 // read buffer: [0, have_) came, [0, consumed_) was parsed
  std::optional<bhttp::response_parser<bhttp::string_body>> parser_;  // the last answer's
  std::size_t have_ = 0;
  std::size_t consumed_ = 0;
  std::uint32_t requests_ = 0;    // on this connection
  Clock::time_point busy_since_;  // a connect or exchange in flight since; zero when none
  Clock::time_point idle_since_;
  bool timed_out_ = false;  // the watchdog closed the connection
};

// The bytes of one slot's requests, serialised by Beast. A lease request is the same every time
// (built once). An upload's payload sits right behind room for its HTTP header, and its pixels
// (one constant, kPixelValue) stay in place from one tile to the next of the same size: only the
// tile's header (job, tile, rectangle), its checksum and the request's header change, and the
// whole request is one contiguous buffer. The fields are those http::Client and the real worker
// send.
class Requests {
 public:
  Requests(const Run& run, std::string_view worker, std::string_view lease_body) {
    const auto common = [&](auto& req) {
      req.set(bhttp::field::host, run.url.host_header());
      req.set(bhttp::field::user_agent, "dtraced");
      req.set(bhttp::field::authorization, run.authorization);
      req.set(protocol::kWorkerHeader, worker);
      req.set(protocol::kPixelVersionHeader, std::to_string(protocol::kPixelVersion));
    };
    for (const bool close : {false, true}) {
      bhttp::request<bhttp::string_body> req{bhttp::verb::post, "/v1/lease", 11};
      common(req);
      req.set(bhttp::field::content_type, http::kJsonContentType);
      req.body() = std::string(lease_body);
      req.prepare_payload();
      req.keep_alive(!close);
      if (!http::append_serialised(req, lease_[close])) throw std::runtime_error("cannot serialise a lease request");
    }
    common(upload_head_);
    upload_head_.version(11);
    upload_head_.method(bhttp::verb::put);
    upload_head_.set(bhttp::field::content_type, http::kBinaryContentType);
    if (run.next_lease) upload_head_.set(protocol::kNextLeaseHeader, "1");
  }

  // POST /v1/lease; `close`: the connection's last request.
  std::string_view lease(bool close) const { return lease_[close]; }

  // PUT /v1/jobs/{job}/tiles/{tile} with a payload for the lease's rectangle. Throws when its
  // header does not fit in front of the payload (check_payload_encoding tries the longest).
  std::string_view upload(const protocol::Lease& lease, bool close) {
    const std::string_view body = payload(lease);
    target_.clear();
    fmt::format_to(std::back_inserter(target_), "/v1/jobs/{}/tiles/{}", lease.job, lease.tile);
    upload_head_.target(std::string_view(target_.data(), target_.size()));
    upload_head_.content_length(body.size());
    upload_head_.keep_alive(!close);
    head_.clear();
    if (!http::append_serialised(upload_head_, head_) || head_.size() > kUploadHeadRoom) {
      throw std::runtime_error(fmt::format("an upload's HTTP header does not fit in {} bytes", kUploadHeadRoom));
    }
    char* start = upload_.data() + kUploadHeadRoom - head_.size();
    std::memcpy(start, head_.data(), head_.size());
    return std::string_view{start, head_.size() + body.size()};
  }

  // The tile payload alone (protocol::encode_tile_payload's bytes for constant pixels); valid
  // until the next call.
  std::string_view payload(const protocol::Lease& lease) {
    const std::uint32_t width = lease.rect.width;
    const std::uint32_t height = lease.rect.height;
    const std::size_t size = protocol::tile_payload_size(width, height);
    if (width != width_ || height != height_) {
      upload_.assign(kUploadHeadRoom + size, '\0');
      char* pixels = upload_.data() + kUploadHeadRoom + protocol::kTileHeaderBytes;
      const auto bits = std::bit_cast<std::uint32_t>(kPixelValue);
      for (std::size_t i = 0; i < std::size_t{width} * height * 3; ++i) put_le(pixels + 4 * i, bits);
      width_ = width;
      height_ = height;
    }
    char* out = upload_.data() + kUploadHeadRoom;
    std::memcpy(out, protocol::kTileMagic.data(), protocol::kTileMagic.size());
    put_le<std::uint64_t>(out + 8, lease.job);
    put_le<std::uint32_t>(out + 16, lease.tile);
    put_le<std::uint32_t>(out + 20, lease.rect.x0);
    put_le<std::uint32_t>(out + 24, lease.rect.y0);
    put_le<std::uint32_t>(out + 28, width);
    put_le<std::uint32_t>(out + 32, height);
    put_le<std::uint32_t>(out + 36, 0);  // flags: no sample counts
    const std::size_t summed = size - protocol::kTileChecksumBytes;
    const util::Sha256Digest sum = util::sha256_bytes(std::string_view(out, summed));
    std::memcpy(out + summed, sum.data(), sum.size());
    return {out, size};
  }

 private:
  std::array<std::string, 2> lease_;
  bhttp::request<bhttp::empty_body> upload_head_;  // the fields every upload of the slot shares
  std::string upload_;                             // kUploadHeadRoom bytes, then the payload
  std::uint32_t width_ = 0, height_ = 0;
  fmt::memory_buffer target_;
  std::string head_;
};

// The packed payload must be the protocol encoder's, byte for byte: checked once before a run, so
// that a change of the format cannot leave the generator uploading something else.
util::Status check_payload_encoding(const Run& run) {
  protocol::Lease lease;
  lease.job = 0x0102030405060708;
  lease.tile = 77;
  lease.rect = scene::TileRect{96, 64, 7, 5};
  Requests requests(run, "check", "{}");
  protocol::TilePayload expected;
  expected.job = lease.job;
  expected.tile = lease.tile;
  expected.rect = lease.rect;
  expected.rgb.assign(std::size_t{lease.rect.width} * lease.rect.height * 3, kPixelValue);
  if (requests.payload(lease) != protocol::encode_tile_payload(expected)) {
    return util::Error{"the generator's tile payload differs from protocol::encode_tile_payload's"};
  }
  // The longest upload header (the largest job and tile numbers) must fit in front of a payload.
  lease.job = std::numeric_limits<std::uint64_t>::max();
  lease.tile = std::numeric_limits<std::uint32_t>::max();
  try {
    requests.upload(lease, true);
  } catch (const std::exception& e) {
    return util::Error{e.what()};
  }
  return util::Status();
}

// One request on a slot's connection: opens one when there is none (or the last is too old, or
// was closed), sends what `make(last)` builds (`last`: the connection's last request, which says
// Connection: close) and reads the answer. As http::Client does, a request that failed on a
// reused connection before any byte of the answer came is sent once more on a fresh one. An
// empty string, or why not.
template <typename Make>
net::awaitable<std::string> exchange(Run& run, Wire& wire, Make make, Answer& answer) {
  for (int attempt = 0;; ++attempt) {
    const bool reused = attempt == 0 && wire.is_open() && Clock::now() - wire.idle_since() < kMaxIdle;
    if (reused) {
      ++run.wire_stats.reuses;
    } else if (std::string failed = co_await wire.open(run.endpoint, run.tls, run.url.host, run.wire_stats);
               !failed.empty()) {
      wire.close();
      co_return failed;
    }
    const bool last = !run.keep_alive || wire.requests() + 1 >= kMaxRequestsPerConnection;
    bool started = false;
    std::string failed = co_await wire.exchange(make(last), answer, started);
    if (failed.empty()) {
      if (last || answer.close) wire.close();
      co_return failed;
    }
    wire.close();
    if (reused && !started) {
      ++run.wire_stats.retries;
      continue;
    }
    co_return failed;
  }
}

// Closes the connections whose exchange has taken too long, until every slot has ended (then its
// timer is cancelled).
net::awaitable<void> watchdog(Run& run, net::steady_timer& timer) {
  while (run.active > 0) {
    timer.expires_after(kWatchdogPeriod);
    auto [ec] = co_await timer.async_wait(kAwaitTuple);
    if (ec) co_return;
    const Clock::time_point now = Clock::now();
    for (Wire* wire : run.wires) wire->expire_if_older(now, kExchangeTimeout);
  }
}

// One slot of simulated worker `index`: its slots share its name; each has its own connection.
net::awaitable<void> simulated_worker(Run& run, std::uint32_t index, Wire& wire) {
  const std::string name = fmt::format("dtraced-load-{}-{}", ::getpid(), index);
  Requests requests(run, name, protocol::encode(protocol::LeaseRequest{name, run.slots}));
  Answer answer;
  net::steady_timer pause(co_await net::this_coro::executor);
  if (run.ramp_ms > 0) {
    std::uniform_int_distribution<std::uint32_t> uniform(0, run.ramp_ms);
    co_await pause_for(pause, std::chrono::milliseconds(uniform(run.rng)));
  }

  // The next lease the last upload's answer carried (--next-lease).
  std::optional<protocol::LeaseReply> offered;
  while (run.running()) {
    // ---- lease ----
    Clock::time_point sent = Clock::now();
    Tally* tp = &run.tally_for(sent);
    protocol::LeaseReply reply;
    if (offered) {
      reply = std::move(*offered);
      offered.reset();
    } else {
      const std::string failed = co_await exchange(
          run, wire, [&requests](bool last) { return requests.lease(last); }, answer);
      Tally& t = *tp;
      if (!failed.empty()) {
        ++t.network_errors;
        run.note_problem("POST /v1/lease: " + failed);
        co_await pause_for(pause, kErrorPause);
        continue;
      }
      t.lease.add(Clock::now() - sent);
      if (answer.status == static_cast<unsigned>(http::Status::service_unavailable)) {
        ++t.busy;
        co_await pause_for(pause, kErrorPause);
        continue;
      }
      auto decoded = protocol::decode_lease_reply(answer.body);
      if (answer.status != static_cast<unsigned>(http::Status::ok) || !decoded) {
        ++t.http_errors;
        run.note_problem("POST /v1/lease: " + quote(answer.status, answer.body));
        co_await pause_for(pause, kErrorPause);
        continue;
      }
      reply = std::move(decoded).value();
    }
    Tally& t = *tp;
    if (const auto* retry = std::get_if<protocol::RetryAfter>(&reply)) {
      ++t.retry_after;
      const auto left = run.deadline - Clock::now();
      co_await pause_for(pause, std::min<Clock::duration>(run.retry_wait(std::chrono::milliseconds(retry->ms)), left));
      continue;
    }
    const protocol::Lease lease = std::get<protocol::Lease>(std::move(reply));
    if (lease.job != run.job) {
      // Uploading made-up pixels into someone else's job would corrupt it.
      run.stop(run.job == 0
                   ? fmt::format("the collector leased a tile of job {} to an idle worker: it has work", lease.job)
                   : fmt::format("the collector leased a tile of job {}, not of job {}: it is not idle", lease.job,
                                 run.job));
      co_return;
    }
    ++t.leases;
    if (run.lease_only) continue;

    // ---- render ----
    if (const Clock::duration render = run.render_time(); render > Clock::duration::zero()) {
      if (Clock::now() + render >= run.deadline) {
        // The run ends before this tile would be done: it stays leased, as with a worker stopped.
        co_await pause_for(pause, std::max<Clock::duration>(run.deadline - Clock::now(), Clock::duration::zero()));
        break;
      }
      co_await pause_for(pause, render);
    }

    // ---- upload ----
    sent = Clock::now();
    tp = &run.tally_for(sent);
    const std::string failed = co_await exchange(
        run, wire, [&requests, &lease](bool last) { return requests.upload(lease, last); }, answer);
    Tally& u = *tp;
    if (!failed.empty()) {
      ++u.network_errors;
      run.note_problem("PUT tile: " + failed);
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    u.upload.add(Clock::now() - sent);
    const unsigned status = answer.status;
    if (status == static_cast<unsigned>(http::Status::service_unavailable)) {
      ++u.busy;
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    auto decoded = protocol::decode_upload_answer(answer.body);
    if ((status != static_cast<unsigned>(http::Status::ok) && status != static_cast<unsigned>(http::Status::gone)) ||
        !decoded) {
      ++u.http_errors;
      run.note_problem("PUT tile: " + quote(status, answer.body));
      co_await pause_for(pause, kErrorPause);
      continue;
    }
    if (decoded.value().next) {
      if (!run.next_lease) {
        ++u.http_errors;
        run.note_problem("PUT tile: a next lease nobody asked for: " + quote(status, answer.body));
      } else {
        offered = std::move(decoded.value().next);
        if (std::holds_alternative<protocol::Lease>(*offered)) ++u.upload_leases;
      }
    }
    switch (decoded.value().result) {
      case protocol::SubmitResult::kStored:
        ++u.stored;
        break;
      case protocol::SubmitResult::kAlreadyDone:
        ++u.already_done;
        break;
      case protocol::SubmitResult::kJobGone:
        ++u.job_gone;
        run.stop(fmt::format("job {} is gone (cancelled?)", run.job));
        co_return;
    }
  }
}

// This thread's seconds on a CPU and waiting for one (Linux: /proc/thread-self/schedstat); the rest
// of the wall time it slept, waiting for answers. Nothing where the file cannot be read.
std::optional<std::pair<double, double>> sched_seconds() {
  std::FILE* f = std::fopen("/proc/thread-self/schedstat", "r");
  if (f == nullptr) return std::nullopt;
  unsigned long long on_cpu = 0, waiting = 0;
  const int n = std::fscanf(f, "%llu %llu", &on_cpu, &waiting);
  std::fclose(f);
  if (n != 2) return std::nullopt;
  return std::pair{on_cpu / 1e9, waiting / 1e9};
}

double cpu_seconds() {
  rusage usage{};
  ::getrusage(RUSAGE_SELF, &usage);
  const auto seconds = [](const timeval& tv) { return static_cast<double>(tv.tv_sec) + tv.tv_usec / 1e6; };
  return seconds(usage.ru_utime) + seconds(usage.ru_stime);
}

// idle: the share of the run this process slept waiting for the collector (NaN if unknown); near 0,
// the generator rather than the collector was the limit, even on a core shared with others.
void report(const Options& o, const Run& run, const http::ClientStats& client, double elapsed_s, double cpu_s,
            double idle) {
  const Tally& t = run.tally;
  const double rate = elapsed_s > 0 ? static_cast<double>(t.stored) / elapsed_s : 0;
  const double lease_rate = elapsed_s > 0 ? static_cast<double>(t.leases) / elapsed_s : 0;
  // Every lease request answered, tile or "nothing now" or busy: the polling load.
  const double answer_rate = elapsed_s > 0 ? static_cast<double>(t.lease.count() + t.lease.dropped()) / elapsed_s : 0;
  if (o.json) {
    // A percentile without samples is NaN, which JSON cannot carry: null.
    const auto ms = [](double v) { return std::isnan(v) ? boost::json::value(nullptr) : boost::json::value(v); };
    boost::json::object j;
    j["workers"] = o.workers;
    j["slots"] = o.slots;
    j["job"] = o.job;
    j["idle"] = o.job == 0;
    j["render_ms"] = o.render_ms;
    j["render_jitter_percent"] = o.render_jitter;
    j["ramp_ms"] = o.ramp_ms;
    j["warmup_s"] = o.warmup_seconds;
    j["elapsed_s"] = elapsed_s;
    j["stored"] = t.stored;
    j["stored_per_s"] = rate;
    j["already_done"] = t.already_done;
    j["job_gone"] = t.job_gone;
    j["lease_only"] = o.lease_only;
    j["next_lease"] = o.next_lease;
    j["upload_leases"] = t.upload_leases;
    j["keep_alive"] = o.keep_alive;
    j["tls"] = run.url.tls;
    j["connections_opened"] = client.connections_opened;
    j["tls_handshakes"] = client.tls_handshakes;
    j["leases"] = t.leases;
    j["leases_per_s"] = lease_rate;
    j["lease_answers_per_s"] = answer_rate;
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
    j["generator_us_per_tile"] = t.stored > 0 ? 1e6 * cpu_s / static_cast<double>(t.stored) : 0;
    j["generator_idle"] = ms(idle);
    j["stopped"] = run.reason;
    j["first_problem"] = t.first_problem;
    fmt::print("{}\n", jsonio::to_text(j));
    return;
  }
  fmt::print("dtraced-load: {} simulated workers{} for {:.2f} s against {} ({}){}, {}\n", o.workers,
             o.slots > 1 ? fmt::format(" x {} slots", o.slots) : "", elapsed_s, run.url.to_string(),
             o.job == 0 ? "idle, no job" : fmt::format("job {}", o.job),
             o.lease_only ? ", leases only" : (o.next_lease ? ", next lease in the upload's answer" : ""),
             o.keep_alive ? "kept-alive connections" : "a connection per request");
  if (o.render_ms > 0 || o.ramp_ms > 0 || o.warmup_seconds > 0) {
    fmt::print("  farm            tiles take {} ms +/- {} %, first requests over {} ms, {} s warm-up not counted\n",
               o.render_ms, o.render_jitter, o.ramp_ms, o.warmup_seconds);
  }
  fmt::print("  stored          {:>10}  {:>10.1f} /s\n", t.stored, rate);
  fmt::print("  already_done    {:>10}\n", t.already_done);
  fmt::print("  leases          {:>10}  {:>10.1f} /s  ({} retry_after answers; {:.1f} lease answers/s in all)\n",
             t.leases, lease_rate, t.retry_after, answer_rate);
  if (o.next_lease) fmt::print("  leases in upload answers {:>10}\n", t.upload_leases);
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
  fmt::print("  generator CPU   {:.2f} of one core, idle {:.2f} of the run, {:.0f} us a stored tile\n",
             elapsed_s > 0 ? cpu_s / elapsed_s : 0, idle,
             t.stored > 0 ? 1e6 * cpu_s / static_cast<double>(t.stored) : 0);
  if (!t.first_problem.empty()) fmt::print("  first problem: {}\n", t.first_problem);
  if (t.retry_after > 0 && o.job != 0 && o.render_ms == 0) {
    fmt::print(
        "  warning: the collector had no tile to lease {} times (job finished, or every tile out): the rate "
        "understates its capacity; use a larger job\n",
        t.retry_after);
  }
}

// Raises the soft open-file limit to one descriptor per simulated worker plus a margin, within the
// hard limit; an error when the hard limit is below that (the run would fail to connect).
util::Status raise_fd_limit(std::uint32_t connections) {
  const rlim_t want = static_cast<rlim_t>(connections) + kSpareFds;
  rlimit limit{};
  if (::getrlimit(RLIMIT_NOFILE, &limit) != 0) {
    return util::Error{fmt::format("getrlimit(RLIMIT_NOFILE): {}", std::strerror(errno))};
  }
  if (limit.rlim_cur != RLIM_INFINITY && limit.rlim_cur >= want) return util::Status();
  if (limit.rlim_max != RLIM_INFINITY && limit.rlim_max < want) {
    return util::Error{fmt::format(
        "{} connections need {} open files, but the hard limit (RLIMIT_NOFILE, ulimit -Hn) is {}: raise it or use "
        "fewer workers or slots",
        connections, want, limit.rlim_max)};
  }
  limit.rlim_cur = want;
  if (::setrlimit(RLIMIT_NOFILE, &limit) != 0) {
    return util::Error{fmt::format("setrlimit(RLIMIT_NOFILE, {}): {}", want, std::strerror(errno))};
  }
  return util::Status();
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
  if (o.workers * std::uint64_t{o.slots} > kMaxWorkers) {
    fmt::print(stderr, "--workers x --slots: at most {} in all\n", kMaxWorkers);
    return 2;
  }
  // One connection per slot at most: each slot has one request in flight.
  const std::uint32_t loops = o.workers * o.slots;
  if (util::Status fds = raise_fd_limit(loops); !fds) {
    fmt::print(stderr, "dtraced-load: {}\n", fds.error().to_string());
    return 1;
  }
  http::ClientOptions client_options;
  client_options.timeouts = kTimeouts;
  std::optional<ssl::context> tls_context;
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
    http::ClientTls tls{*pem, o.ca_file, std::nullopt};
    if (util::Status usable = http::check_client_tls(tls); !usable) {
      fmt::print(stderr, "--ca-file: {}\n", usable.error().to_string());
      return 2;
    }
    client_options.tls = std::move(tls);
    // The simulated workers' context: http::Client's settings (see make_context in http/client.cpp).
    tls_context.emplace(ssl::context::tls_client);
    SSL_CTX* handle = tls_context->native_handle();
    error_code ec;
    tls_context->add_certificate_authority(net::buffer(*pem), ec);
    if (ec || SSL_CTX_set_min_proto_version(handle, TLS1_2_VERSION) != 1 ||
        SSL_CTX_set_cipher_list(handle, kTls12Ciphers) != 1) {
      fmt::print(stderr, "--ca-file: cannot set up TLS with {}: {}\n", o.ca_file, ec ? ec.message() : "OpenSSL");
      return 2;
    }
    SSL_CTX_set_options(handle, SSL_OP_NO_COMPRESSION | SSL_OP_NO_RENEGOTIATION);
    SSL_CTX_set_verify(handle, SSL_VERIFY_PEER, nullptr);
  }
  Run run;
  run.url = *url;
  run.tls = tls_context ? &*tls_context : nullptr;
  run.keep_alive = o.keep_alive;
  run.authorization = "Bearer " + *token;
  run.job = o.job;
  run.lease_only = o.lease_only;
  run.next_lease = o.next_lease;
  run.slots = o.slots;
  run.render_ms = o.render_ms;
  run.render_jitter = o.render_jitter;
  run.ramp_ms = o.ramp_ms;

  net::io_context io{1};
  http::Client client(io.get_executor(), client_options);  // after io: destroyed before it
  run.client = &client;
  {
    tcp::resolver resolver(io);
    error_code ec;
    const tcp::resolver::results_type found = resolver.resolve(url->host, std::to_string(url->port), ec);
    if (ec || found.empty()) {
      fmt::print(stderr, "dtraced-load: cannot resolve {}: {}\n", url->host, ec ? ec.message() : "no address");
      return 1;
    }
    run.endpoint = found.begin()->endpoint();
  }
  if (util::Status encoded = check_payload_encoding(run); !encoded) {
    fmt::print(stderr, "dtraced-load: {}\n", encoded.error().to_string());
    return 1;
  }
  util::Status checked = util::Error{"the job check did not finish"};
  if (o.job == 0) checked = util::Status();  // idle workers: the first granted lease stops the run
  if (o.job != 0)
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
  // One connection per slot, kept alive between its requests however long it pauses (as each
  // slot of a real worker has one request in flight at a time); after io, so destroyed before it.
  std::vector<std::unique_ptr<Wire>> wires;
  wires.reserve(loops);
  for (std::uint32_t n = 0; n < loops; ++n) {
    wires.push_back(std::make_unique<Wire>(io.get_executor()));
    run.wires.push_back(wires.back().get());
  }
  net::steady_timer watchdog_timer(io);
  const double cpu_before = cpu_seconds();
  const auto sched_before = sched_seconds();
  run.start = Clock::now();
  run.measure_from = run.start + std::chrono::seconds(o.warmup_seconds);
  run.deadline = run.measure_from + std::chrono::seconds(o.seconds);
  run.last_answer = run.measure_from;
  net::steady_timer window(io);
  if (o.warmup_seconds > 0) {
    window.expires_at(run.measure_from);
    window.async_wait([](boost::system::error_code ec) {
      if (!ec) fmt::print(stderr, "dtraced-load: the measured window opens\n");
    });
  }
  run.active = loops;
  for (std::uint32_t n = 0; n < loops; ++n) {
    const std::uint32_t i = n % o.workers;  // slot n / workers of worker i: first slots start first
    net::co_spawn(io, simulated_worker(run, i, *wires[n]), [&run, &watchdog_timer, i](std::exception_ptr e) {
      run.last_answer = std::max(run.last_answer, Clock::now());
      if (--run.active == 0) watchdog_timer.cancel();
      if (!e) return;
      try {
        std::rethrow_exception(e);
      } catch (const std::exception& ex) {
        util::log_error("dtraced-load: simulated worker {} failed: {}", i, ex.what());
        run.stop(fmt::format("simulated worker {} failed: {}", i, ex.what()));
      }
    });
  }
  net::co_spawn(io, watchdog(run, watchdog_timer), async::log_failure("dtraced-load's watchdog"));
  io.run();
  const double elapsed = std::chrono::duration<double>(run.last_answer - run.measure_from).count();
  // CPU over the whole run, warm-up included, as a share of the measured window alone would
  // overstate it: spread over the run's full length instead.
  const double total = std::chrono::duration<double>(run.last_answer - run.start).count();
  const double cpu = total > 0 ? (cpu_seconds() - cpu_before) * elapsed / total : 0;
  const auto sched_after = sched_seconds();
  const double idle =
      sched_before && sched_after && total > 0
          ? std::max(0.0, 1 - (sched_after->first - sched_before->first + sched_after->second - sched_before->second) /
                                  std::chrono::duration<double>(Clock::now() - run.start).count())
          : std::nan("");
  run.tally.lease.finish();
  run.tally.upload.finish();
  http::ClientStats stats = client.stats();
  stats.connections_opened += run.wire_stats.connections_opened;
  stats.tls_handshakes += run.wire_stats.tls_handshakes;
  stats.reuses += run.wire_stats.reuses;
  stats.retries += run.wire_stats.retries;
  report(o, run, stats, elapsed, cpu, idle);
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
      "dtraced-load: simulated workers lease tiles from a collector and upload made-up pixels, as fast as it answers "
      "or after a simulated render time; without --job, idle workers poll a collector that has no work. Prints "
      "durable submissions per second and lease latency. Writes into the job it is given: use a throwaway collector.",
      "dtraced-load"};
  app.add_option("--collector", o.collector, "Collector base URL, http://HOST:PORT or https://HOST:PORT")->required();
  app.add_option("--ca-file", o.ca_file, "The collector's CA certificate (PEM), for an https:// collector");
  app.add_flag("--keep-alive,!--no-keep-alive", o.keep_alive,
               "Kept-alive connections (the default, as workers speak), or a connection per request");
  app.add_option("--token-file", o.token_file, "File holding the farm's bearer token")->required();
  app.add_option("--job", o.job,
                 "The job to lease from and upload into (must be unfinished); without it the workers are idle and "
                 "the collector must have no work")
      ->check(CLI::Range(std::uint64_t{1}, dtraced::protocol::kMaxId));
  app.add_option("--workers", o.workers, "Simulated workers (concurrent coroutines on one thread)")
      ->check(CLI::Range(std::uint32_t{1}, dtraced::bench::kMaxWorkers))
      ->capture_default_str();
  app.add_option("--seconds", o.seconds, "Length of the run")
      ->check(CLI::Range(std::uint32_t{1}, dtraced::bench::kMaxSeconds))
      ->capture_default_str();
  app.add_option("--slots", o.slots,
                 "Lease/upload loops per simulated worker, all under its name (a worker's render threads: each "
                 "has a tile in flight)")
      ->check(CLI::Range(std::uint32_t{1}, dtraced::bench::kMaxSlots))
      ->capture_default_str();
  app.add_flag("--lease-only", o.lease_only, "Lease without uploading: the rate of bare requests");
  app.add_flag("--next-lease", o.next_lease,
               "Each upload asks for the next lease in its answer (X-Dtraced-Next-Lease), as the real worker does");
  app.add_option("--render-ms", o.render_ms, "Hold each leased tile this long before uploading it (simulated render)")
      ->check(CLI::Range(std::uint32_t{0}, dtraced::bench::kMaxRenderMs))
      ->capture_default_str();
  app.add_option("--render-jitter", o.render_jitter, "Spread of the render time, percent either side of --render-ms")
      ->check(CLI::Range(std::uint32_t{0}, dtraced::bench::kMaxJitterPercent))
      ->capture_default_str();
  app.add_option("--ramp-ms", o.ramp_ms, "Start the simulated workers at random times over this long")
      ->check(CLI::Range(std::uint32_t{0}, dtraced::bench::kMaxRampMs))
      ->capture_default_str();
  app.add_option("--warmup-seconds", o.warmup_seconds, "Run this long before the measured window (not counted)")
      ->check(CLI::Range(std::uint32_t{0}, dtraced::bench::kMaxWarmupSeconds))
      ->capture_default_str();
  app.add_flag("--json", o.json, "Print the figures as one JSON object");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  return dtraced::bench::run_load(o);
}
