// A fake collector for whole-worker tests: an http::Server on 127.0.0.1 (an ephemeral port, or a
// chosen one) that serves one job of a small scene and fails in chosen ways (absent, 500s, a 503
// scene, 503 submissions, refused submissions, a gone job, a bad token, a tampered scene, requests
// left unanswered), and counts what the worker sent (and when, on a clock the test gives it).
//
// Thread safety: the server runs the handler on its own thread; FakeCollector's state is guarded
// by a mutex, so the test thread may read counts and change rules at any time.
#pragma once

#include <chrono>
#include <cstdint>
#include <exception>
#include <functional>
#include <future>
#include <limits>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <variant>
#include <vector>

#include <boost/asio/as_tuple.hpp>
#include <boost/asio/co_spawn.hpp>
#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <boost/asio/use_future.hpp>
#include <boost/beast/http/field.hpp>
#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "http/server.h"
#include "http/types.h"
#include "protocol/messages.h"
#include "protocol/tile_payload.h"
#include "protocol/worker_messages.h"
#include "scene/digest.h"
#include "scene/tiling.h"
#include "util/clock.h"
#include "worker_testing.h"

namespace dtraced::testing {

namespace net = boost::asio;

// A port nobody listens on (just released by the kernel; another process grabbing it in between
// is possible but not on a test machine's loopback in practice).
inline std::uint16_t unused_port() {
  net::io_context io;
  net::ip::tcp::acceptor acceptor(io, net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), 0));
  return acceptor.local_endpoint().port();
}

struct FakeRules {
  bool reject_token = false;                       // every request: 401
  int failing_leases = 0;                          // the first N lease requests: 500
  int failing_scene_fetches = 0;                   // the first N scene fetches: 503
  bool tamper_scene = false;                       // serve another scene under the digest
  std::set<std::uint32_t> fail_first_submit = {};  // these tiles' first submission: 503
  bool submits_unavailable = false;                // every submission: 503
  bool job_gone = false;                           // submissions: 410; after the first, no more leases
  bool lease_after_gone = false;                   // with job_gone: the job is leased all the same
  unsigned refuse_submits = 0;                     // every submission: this 4xx status (0: none)
  bool hang_leases = false;                        // lease requests get no answer until the server stops
  bool hang_submits = false;                       // submissions get no answer until the server stops
  // A tile leased but not stored is offered again after this many "retry after" answers (the
  // fake's stand-in for the real queue's re-offer bound; the worker drops leases it cannot use).
  std::uint32_t reoffer_after = 3;
  // "Retry after" answers carry protocol::kFinishedHeader with this value ("": no header), as a
  // one-shot collector going away sends "1".
  std::string_view finished_header = {};
};

struct FakeCounts {
  std::uint64_t lease_requests = 0;
  std::uint64_t leases = 0;
  std::uint64_t retry_answers = 0;  // lease requests answered "retry after"
  std::uint64_t scene_requests = 0;
  std::uint64_t unauthorized = 0;
  std::uint64_t acknowledged = 0;  // 200 stored or already_done
  std::uint64_t already_done = 0;
  std::uint64_t gone_answers = 0;
  std::uint64_t hung = 0;                      // requests left without an answer
  std::vector<std::uint64_t> submit_requests;  // per tile
  std::vector<std::uint64_t> stored;           // per tile: how often "stored" was answered
  std::vector<std::string> problems;           // anything the worker sent that it should not have
  std::vector<util::TimePoint> request_times;  // of every request, on the clock of stamp_with()
};

// One job (kJob) of the tiny scene (or of `desc`), failing as `rules` say (set_rules changes them
// while the worker runs).
class FakeCollector {
 public:
  explicit FakeCollector(FakeRules rules = {}, scene::SceneDesc desc = load_tiny_scene())
      : desc_(std::move(desc)),
        canonical_(scene::canonical_json(desc_)),
        digest_(scene::scene_digest(desc_)),
        rects_(scene::TileGrid(desc_.render.width, desc_.render.height, kTileSize).all()),
        rules_(std::move(rules)) {
    REQUIRE(rects_.size() == 4);
    counts_.submit_requests.assign(rects_.size(), 0);
    counts_.stored.assign(rects_.size(), 0);
    leased_.assign(rects_.size(), false);
    idle_since_lease_.assign(rects_.size(), 0);
    pixels_.resize(rects_.size());
    spp_.resize(rects_.size());
  }

  http::Server::Handler handler() {
    return [this](http::Request req) -> net::awaitable<http::Response> {
      if (should_hang(req)) {
        // Until the server's stop cancels this handler.
        net::steady_timer never(co_await net::this_coro::executor, net::steady_timer::time_point::max());
        co_await never.async_wait(net::as_tuple(net::use_awaitable));
        co_return http::make_error(http::Status::service_unavailable, "stopping");
      }
      co_return handle(req);
    };
  }

  // From now on every request is stamped with `clock`'s time (which outlives this fake's server).
  void stamp_with(const util::Clock& clock) {
    std::lock_guard lock(mu_);
    clock_ = &clock;
  }

  void set_rules(const std::function<void(FakeRules&)>& change) {
    std::lock_guard lock(mu_);
    change(rules_);
  }

  FakeCounts counts() const {
    std::lock_guard lock(mu_);
    return counts_;
  }

  bool all_stored() const {
    std::lock_guard lock(mu_);
    for (const std::uint64_t n : counts_.stored) {
      if (n == 0) return false;
    }
    return true;
  }

  bool every_tile_submitted() const {
    std::lock_guard lock(mu_);
    for (const std::uint64_t n : counts_.submit_requests) {
      if (n == 0) return false;
    }
    return true;
  }

  std::vector<std::vector<float>> pixels() const {
    std::lock_guard lock(mu_);
    return pixels_;
  }

  std::vector<std::vector<std::uint32_t>> spp() const {
    std::lock_guard lock(mu_);
    return spp_;
  }

  const std::vector<scene::TileRect>& rects() const { return rects_; }
  const scene::SceneDesc& desc() const { return desc_; }

 private:
  http::Response handle(const http::Request& req) {
    std::lock_guard lock(mu_);
    if (clock_ != nullptr) counts_.request_times.push_back(clock_->now());
    const std::string expected = fmt::format("Bearer {}", kToken);
    if (rules_.reject_token || req[boost::beast::http::field::authorization] != expected) {
      ++counts_.unauthorized;
      return http::make_error(http::Status::unauthorized, "missing or wrong token");
    }
    const std::string_view target = req.target();
    const std::string tile_prefix = fmt::format("/v1/jobs/{}/tiles/", kJob);
    if (req.method() == http::Verb::post && target == "/v1/lease") return lease(req);
    if (req.method() == http::Verb::get && target.starts_with("/v1/scenes/")) {
      return scene(target.substr(std::string_view("/v1/scenes/").size()));
    }
    if (req.method() == http::Verb::put && target.starts_with(tile_prefix)) {
      return submit(target.substr(tile_prefix.size()), req.body());
    }
    counts_.problems.push_back(fmt::format("unexpected request {} {}", std::string(req.method_string()), target));
    return http::make_error(http::Status::not_found, "no such route");
  }

  bool should_hang(const http::Request& req) {
    std::lock_guard lock(mu_);
    if (rules_.hang_leases && req.target() == "/v1/lease") {
      ++counts_.hung;
      return true;
    }
    if (rules_.hang_submits && req.method() == http::Verb::put) {
      ++counts_.hung;
      return true;
    }
    return false;
  }

  static http::Response json(http::Status status, std::string body) {
    return http::make_text_response(status, std::move(body), http::kJsonContentType);
  }

  http::Response lease(const http::Request& req) {
    ++counts_.lease_requests;
    const auto decoded = protocol::decode_lease_request(req.body());
    const auto version =
        req.find(boost::beast::string_view(protocol::kPixelVersionHeader.data(), protocol::kPixelVersionHeader.size()));
    if (version == req.end() || version->value() != std::to_string(protocol::kPixelVersion)) {
      counts_.problems.push_back("a lease request without this build's pixel version");
      return http::make_error(http::Status::conflict, "wrong pixel version");
    }
    if (!decoded || decoded.value().worker != "test-worker" || decoded.value().threads != 2) {
      counts_.problems.push_back(fmt::format("bad lease request: {}", req.body()));
      return http::make_error(http::Status::bad_request, "bad lease request");
    }
    if (rules_.failing_leases > 0) {
      --rules_.failing_leases;
      return http::make_error(http::Status::internal_server_error, "failing on purpose");
    }
    std::optional<std::uint32_t> tile;
    if (!(rules_.job_gone && counts_.gone_answers > 0 && !rules_.lease_after_gone)) {
      for (std::uint32_t t = 0; t < rects_.size() && !tile; ++t) {
        if (!leased_[t]) tile = t;
      }
      for (std::uint32_t t = 0; t < rects_.size() && !tile; ++t) {
        if (counts_.stored[t] == 0 && idle_since_lease_[t] >= rules_.reoffer_after) tile = t;
      }
    }
    if (!tile) {
      for (std::uint32_t t = 0; t < rects_.size(); ++t) ++idle_since_lease_[t];
      ++counts_.retry_answers;
      http::Response res = json(http::Status::ok, protocol::encode(protocol::LeaseReply{protocol::RetryAfter{5}}));
      if (!rules_.finished_header.empty()) res.set(protocol::kFinishedHeader, rules_.finished_header);
      return res;
    }
    leased_[*tile] = true;
    idle_since_lease_[*tile] = 0;
    ++counts_.leases;
    protocol::Lease lease{kJob, digest_, *tile, rects_[*tile], desc_.render};
    return json(http::Status::ok, protocol::encode(protocol::LeaseReply{lease}));
  }

  http::Response scene(std::string_view digest) {
    ++counts_.scene_requests;
    if (digest != digest_) {
      counts_.problems.push_back(fmt::format("fetch of unknown scene {}", digest));
      return http::make_error(http::Status::not_found, "no such scene");
    }
    if (rules_.failing_scene_fetches > 0) {
      --rules_.failing_scene_fetches;
      return http::make_error(http::Status::service_unavailable, "failing on purpose");
    }
    if (rules_.tamper_scene) return json(http::Status::ok, scene::canonical_json(other_scene(0.5)));
    return json(http::Status::ok, canonical_);
  }

  http::Response submit(std::string_view tile_text, const std::string& body) {
    std::uint32_t t = 0;
    try {
      t = static_cast<std::uint32_t>(std::stoul(std::string(tile_text)));
    } catch (const std::exception&) {
      t = std::numeric_limits<std::uint32_t>::max();
    }
    if (t >= rects_.size()) {
      counts_.problems.push_back(fmt::format("submission of unknown tile {}", tile_text));
      return http::make_error(http::Status::not_found, "no such tile");
    }
    const bool first = counts_.submit_requests[t]++ == 0;
    if (rules_.job_gone) {
      ++counts_.gone_answers;
      return json(http::Status::gone, protocol::encode(protocol::SubmitResult::kJobGone));
    }
    if (rules_.refuse_submits != 0) {
      return http::make_error(static_cast<http::Status>(rules_.refuse_submits), "refused on purpose");
    }
    if (rules_.submits_unavailable || (first && rules_.fail_first_submit.contains(t))) {
      return http::make_error(http::Status::service_unavailable, "failing on purpose");
    }
    auto decoded = protocol::decode_tile_payload(body);
    if (!decoded) {
      counts_.problems.push_back(fmt::format("tile {}: bad payload: {}", t, decoded.error().message));
      return http::make_error(http::Status::bad_request, decoded.error().message);
    }
    protocol::TilePayload& payload = decoded.value();
    if (payload.job != kJob || payload.tile != t || !(payload.rect == rects_[t])) {
      counts_.problems.push_back(fmt::format("tile {}: payload names job {} tile {}", t, payload.job, payload.tile));
      return http::make_error(http::Status::bad_request, "payload does not match the tile");
    }
    ++counts_.acknowledged;
    if (counts_.stored[t] > 0) {
      ++counts_.already_done;
      if (!same_bits(pixels_[t], payload.rgb)) counts_.problems.push_back(fmt::format("tile {}: duplicate differs", t));
      return json(http::Status::ok, protocol::encode(protocol::SubmitResult::kAlreadyDone));
    }
    ++counts_.stored[t];
    pixels_[t] = std::move(payload.rgb);
    spp_[t] = std::move(payload.spp);
    return json(http::Status::ok, protocol::encode(protocol::SubmitResult::kStored));
  }

  const scene::SceneDesc desc_;
  const std::string canonical_;
  const std::string digest_;
  const std::vector<scene::TileRect> rects_;

  mutable std::mutex mu_;
  const util::Clock* clock_ = nullptr;
  FakeRules rules_;
  FakeCounts counts_;
  std::vector<bool> leased_;
  std::vector<std::uint32_t> idle_since_lease_;
  std::vector<std::vector<float>> pixels_;
  std::vector<std::vector<std::uint32_t>> spp_;  // per tile: the counts it carried (adaptive jobs)
};

// An http::Server on 127.0.0.1:port with its io_context on a thread of its own; destroying it
// stops the server (connections refused from then on).
class RunningServer {
 public:
  RunningServer(std::uint16_t port, http::Server::Handler handler)
      : server_(io_.get_executor(), net::ip::make_address("127.0.0.1"), port, limits(), std::move(handler)) {
    REQUIRE(!server_.start());
    REQUIRE(server_.port() != 0);
    thread_ = std::thread([this] { io_.run(); });
  }

  ~RunningServer() {
    std::future<void> stopped = net::co_spawn(io_, server_.stop(0ms), net::use_future);
    stopped.wait_for(kBound);
    work_.reset();
    io_.stop();
    thread_.join();
  }

  std::uint16_t port() const { return server_.port(); }

 private:
  static http::ServerLimits limits() {
    http::ServerLimits limits;
    limits.read_timeout = kBound;
    limits.write_timeout = kBound;
    limits.idle_keepalive_timeout = kBound;
    return limits;
  }

  net::io_context io_;
  net::executor_work_guard<net::io_context::executor_type> work_ = net::make_work_guard(io_);
  http::Server server_;
  std::thread thread_;
};

}  // namespace dtraced::testing
