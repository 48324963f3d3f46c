// Tests for the client verbs' retries (cli/retry.h): the policy on a ManualClock (waits honour
// Retry-After, back off and stop at the budget), which failures count as retryable (a 503 for any
// method, no answer for a GET only), and whole verbs against a server on 127.0.0.1 that answers
// 503 before it answers properly.

#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <optional>
#include <string>

#include <catch2/catch.hpp>

#include "cli/client_verbs.h"
#include "cli/retry.h"
#include "http_testing.h"
#include "temp_dir.h"
#include "util/clock.h"

namespace {

namespace cli = dtraced::cli;
namespace http = dtraced::http;
using cli::Failure;
using cli::RetryPolicy;
using Ms = std::chrono::milliseconds;
using namespace std::chrono_literals;

const Failure kBusy{true, std::nullopt, "collector busy"};

http::ClientResult answer(unsigned code, std::string retry_after = {}) {
  http::ClientResult r;
  r.response.result(code);
  if (!retry_after.empty()) r.response.set(boost::beast::http::field::retry_after, retry_after);
  r.response.body() = R"({"error":"the store is busy; retry later","field":""})";
  return r;
}

http::ClientResult no_answer(http::ClientError error) {
  http::ClientResult r;
  r.error = error;
  r.message = "127.0.0.1:1: connection refused";
  return r;
}

std::string read_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

// A collector stand-in that answers `busy_answers` requests with 503 (Retry-After: 0, so the
// client waits its shortest) and the rest with `ok`.
struct BusyThenOk {
  int busy_answers;
  http::Response ok;
  std::atomic<int> requests{0};

  http::Server::Handler handler() {
    return [this](http::Request) -> boost::asio::awaitable<http::Response> {
      if (requests++ < busy_answers) {
        http::Response busy = http::make_error(http::Status::service_unavailable, "the store is busy; retry later", "");
        busy.set(boost::beast::http::field::retry_after, "0");
        co_return busy;
      }
      co_return ok;
    };
  }
};

cli::ClientArgs client_of(const http_testing::TestServer& server) {
  cli::ClientArgs args;
  args.collector = server.url().to_string();
  args.timeout_ms = 20'000;  // the retry budget too: far more than the few short waits needed
  return args;
}

}  // namespace

TEST_CASE("a retry waits at least what Retry-After asks, then backs off, and a success starts afresh", "[cli][retry]") {
  dtraced::util::ManualClock clock;
  RetryPolicy policy(30s, 7);
  const Failure asked{true, Ms(2000), "collector busy"};
  std::optional<Ms> wait = policy.next_wait(asked, clock.now());
  REQUIRE(wait);
  CHECK(*wait >= 2000ms);
  CHECK(*wait <= 3000ms);  // jittered by at most half again
  clock.advance(*wait);
  wait = policy.next_wait(kBusy, clock.now());
  REQUIRE(wait);
  CHECK(*wait >= RetryPolicy::kMinWait);
  CHECK(*wait <= 2 * RetryPolicy::kInitial);  // the second retry's window
  CHECK(policy.failures() == 2);
  policy.succeeded();
  CHECK(policy.failures() == 0);
  CHECK(policy.spent(clock.now()) == 0ms);
}

TEST_CASE("retries stop once a run of failures has lasted the budget, the last wait ending at it", "[cli][retry]") {
  dtraced::util::ManualClock clock;
  const auto start = clock.now();
  RetryPolicy policy(10s, 11);
  int waits = 0;
  while (std::optional<Ms> wait = policy.next_wait(kBusy, clock.now())) {
    CHECK(*wait > 0ms);
    CHECK(*wait <= RetryPolicy::kMax);
    clock.advance(*wait);
    REQUIRE(++waits < 1000);
  }
  CHECK(waits >= 3);  // backoff windows of 0.5, 1, 2, 4 s: at least three waits fit in 10 s
  CHECK(clock.now() - start == 10s);
  CHECK(policy.spent(clock.now()) == 10s);
}

TEST_CASE("a Retry-After longer than the budget left is cut to what is left", "[cli][retry]") {
  dtraced::util::ManualClock clock;
  RetryPolicy policy(3s, 3);
  REQUIRE(policy.next_wait(kBusy, clock.now()));
  clock.advance(2500ms);
  const std::optional<Ms> wait = policy.next_wait(Failure{true, Ms(60'000), "busy"}, clock.now());
  REQUIRE(wait);
  CHECK(*wait == 500ms);
}

TEST_CASE("a failure that is not retryable ends at once, and a zero budget never retries", "[cli][retry]") {
  dtraced::util::ManualClock clock;
  RetryPolicy policy(30s, 5);
  CHECK_FALSE(policy.next_wait(Failure{false, std::nullopt, "404"}, clock.now()));
  RetryPolicy none(0s, 5);
  CHECK_FALSE(none.next_wait(kBusy, clock.now()));
}

TEST_CASE("a 503 is retryable for any method, with its Retry-After", "[cli][retry]") {
  const Failure get = cli::classify(answer(503, "2"), http::Verb::get, "/v1/jobs/3");
  CHECK(get.retryable);
  CHECK(get.retry_after == Ms(2000));
  CHECK_THAT(get.reason, Catch::Matchers::Contains("collector busy (503 /v1/jobs/3: the store is busy"));
  const Failure post = cli::classify(answer(503), http::Verb::post, "/v1/jobs");
  CHECK(post.retryable);
  CHECK_FALSE(post.retry_after);
}

TEST_CASE("no answer is retryable for a GET only, since a POST may have been applied", "[cli][retry]") {
  for (http::ClientError e : {http::ClientError::kConnect, http::ClientError::kIo, http::ClientError::kTimeout}) {
    CHECK(cli::classify(no_answer(e), http::Verb::get, "/v1/jobs").retryable);
    CHECK_FALSE(cli::classify(no_answer(e), http::Verb::post, "/v1/jobs").retryable);
  }
  CHECK_FALSE(cli::classify(no_answer(http::ClientError::kTooLarge), http::Verb::get, "/v1/jobs").retryable);
  CHECK_FALSE(cli::classify(no_answer(http::ClientError::kProtocol), http::Verb::get, "/v1/jobs").retryable);
  CHECK_THAT(cli::classify(no_answer(http::ClientError::kConnect), http::Verb::get, "/v1/jobs").reason,
             Catch::Matchers::Contains("connection refused"));
  // A certificate the client refused is final, and not called a missing answer.
  const Failure tls = cli::classify(no_answer(http::ClientError::kTls), http::Verb::get, "/v1/jobs");
  CHECK_FALSE(tls.retryable);
  CHECK_THAT(tls.reason, Catch::Matchers::StartsWith("the collector could not be trusted ("));
}

TEST_CASE("other error answers are final and keep their code, path and message", "[cli][retry]") {
  for (unsigned code : {400u, 401u, 404u, 409u, 500u}) {
    const Failure f = cli::classify(answer(code, "1"), http::Verb::get, "/v1/jobs/3");
    CHECK_FALSE(f.retryable);
    CHECK(f.reason == fmt::format("{} /v1/jobs/3: the store is busy; retry later", code));
  }
}

TEST_CASE("a final error names the field the collector named", "[cli][retry]") {
  http::ClientResult r = answer(409);
  r.response.body() = R"({"error":"job 3 holds this output name","field":"/output"})";
  CHECK(cli::classify(r, http::Verb::post, "/v1/jobs").reason == "409 /v1/jobs: /output: job 3 holds this output name");
  r.response.body() = "not JSON";
  CHECK(cli::classify(r, http::Verb::post, "/v1/jobs").reason == "409 /v1/jobs: HTTP 409");
}

TEST_CASE("Retry-After is read as whole seconds and anything else is ignored", "[cli][retry]") {
  CHECK(cli::parse_retry_after("0") == Ms(0));
  CHECK(cli::parse_retry_after("2") == Ms(2000));
  CHECK(cli::parse_retry_after("86400") == Ms(86'400'000));
  for (const char* bad : {"", "-1", "1.5", " 1", "1 ", "86401", "99999999999999", "Wed, 21 Oct 2015 07:28:00 GMT"}) {
    INFO(bad);
    CHECK_FALSE(cli::parse_retry_after(bad));
  }
}

TEST_CASE("fetch rides out a collector that answers 503 twice before the image", "[cli][retry][end_to_end]") {
  BusyThenOk server_state{2, http::make_binary_response(http::Status::ok, "not really a PNG", "image/png")};
  http_testing::TestServer server(http_testing::generous_limits(), server_state.handler());
  dtraced::testing::TempDir dir;
  const std::string out = dir.str() + "/x.png";
  CHECK(cli::run_fetch(client_of(server), 1, out) == 0);
  CHECK(server_state.requests == 3);
  CHECK(read_file(out) == "not really a PNG");
}

TEST_CASE("submit is sent again after a 503, and only once after a success", "[cli][retry][end_to_end]") {
  const std::string digest(64, 'a');
  BusyThenOk server_state{
      1, http::make_json_response(http::Status::created, boost::json::object{{"id", 7}, {"digest", digest}})};
  http_testing::TestServer server(http_testing::generous_limits(), server_state.handler());
  cli::SubmitArgs submit;
  submit.scene = std::string(DTRACED_SOURCE_DIR) + "/scenes/diffuse.json";
  CHECK(cli::run_submit(client_of(server), submit) == 0);
  CHECK(server_state.requests == 2);
}

TEST_CASE("an error answer other than 503 is not sent again", "[cli][retry][end_to_end]") {
  BusyThenOk server_state{0, http::make_error(http::Status::internal_server_error, "broken on purpose", "")};
  http_testing::TestServer server(http_testing::generous_limits(), server_state.handler());
  CHECK(cli::run_cancel(client_of(server), 3) == 1);
  CHECK(server_state.requests == 1);
}

TEST_CASE("a collector busy for longer than the budget fails the verb once the budget is spent",
          "[cli][retry][end_to_end]") {
  BusyThenOk server_state{1'000'000, http::make_text_response(http::Status::ok, "never", "text/plain")};
  http_testing::TestServer server(http_testing::generous_limits(), server_state.handler());
  cli::ClientArgs args = client_of(server);
  args.timeout_ms = 300;  // the budget: a few short waits
  CHECK(cli::run_workers(args, /* json = */ true) == 1);
  CHECK(server_state.requests >= 2);
  CHECK(server_state.requests < 100);
}
