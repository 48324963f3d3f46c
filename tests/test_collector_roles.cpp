// Roles (collector/credentials.h) through the collector's handler (collector_testing.h): every
// route x {viewer, client, worker, operator, revoked, none} against a table written here, by hand,
// independently of the collector's own; refused requests change nothing; the page's sessions
// keep the role of the token that signed in.
#include <map>
#include <string>
#include <vector>

#include <boost/json/parse.hpp>

#include "collector/credentials.h"
#include "collector/queue.h"
#include "collector/routes.h"
#include "collector/web_access.h"
#include "collector_testing.h"
#include "page_testing.h"
#include "protocol/credential_messages.h"
#include "util/sha256.h"

namespace {

using namespace dtraced;
using namespace dtraced::testing;
using coll::RouteKind;
namespace bhttp = boost::beast::http;
namespace json = boost::json;

enum class Who { kViewer, kClient, kWorker, kOperator, kRevoked, kNone };
constexpr Who kEveryone[] = {Who::kViewer, Who::kClient, Who::kWorker, Who::kOperator, Who::kRevoked, Who::kNone};

const char* name_of(Who w) {
  switch (w) {
    case Who::kViewer:
      return "viewer";
    case Who::kClient:
      return "client";
    case Who::kWorker:
      return "worker";
    case Who::kOperator:
      return "operator";
    case Who::kRevoked:
      return "revoked";
    case Who::kNone:
      return "none";
  }
  return "?";
}

// What a request gets: 401, 403, or anything else ("passed": admitted, whatever the handler said).
enum class Outcome { k401, k403, kPassed };
const char* name_of(Outcome o) { return o == Outcome::k401 ? "401" : o == Outcome::k403 ? "403" : "passed"; }

Outcome outcome_of(const Response& res) {
  if (res.result() == Status::unauthorized) return Outcome::k401;
  if (res.result() == Status::forbidden) return Outcome::k403;
  return Outcome::kPassed;
}

struct PageSession {
  std::string cookie, csrf;
};

// Creates a credential with the operator token; its token.
std::string make_credential(Harness& h, std::string name, std::string role) {
  const Response res = h.call(Verb::post, "/v1/credentials", protocol::encode(protocol::CredentialRequest{name, role}));
  INFO(res.body());
  REQUIRE(res.result() == Status::created);
  auto issued = protocol::decode_credential_issued(res.body());
  REQUIRE(issued.ok());
  CHECK(issued.value().name == name);
  CHECK(issued.value().role == role);
  return issued.value().token;
}

std::optional<PageSession> page_sign_in(Harness& h, std::string_view token, Status* status = nullptr) {
  const Response res =
      h.collector.handle_sync(browser(Verb::post, "/ui/session", fmt::format(R"({{"token": "{}"}})", token)));
  if (status != nullptr) *status = res.result();
  if (res.result() != Status::ok) return std::nullopt;
  const std::string set = header_of(res, "Set-Cookie");
  PageSession s;
  s.cookie = set.substr(16, 64);
  s.csrf = std::string(json::parse(res.body()).at("csrf").as_string());
  return s;
}

struct Sample {
  Verb verb;
  std::string target;
  std::string body;
};

// One request per route kind, chosen so that an admitted one changes nothing (no such job, a
// body that does not decode) and so that its answer, when admitted, is neither 401 nor 403.
std::map<RouteKind, Sample> samples() {
  std::map<RouteKind, Sample> s;
  s[RouteKind::kHealthz] = {Verb::get, "/healthz", ""};
  s[RouteKind::kMetrics] = {Verb::get, "/metrics", ""};
  s[RouteKind::kSubmitJob] = {Verb::post, "/v1/jobs", "{}"};
  s[RouteKind::kListJobs] = {Verb::get, "/v1/jobs", ""};
  s[RouteKind::kJobStatus] = {Verb::get, "/v1/jobs/999", ""};
  s[RouteKind::kJobImage] = {Verb::get, "/v1/jobs/999/image", ""};
  s[RouteKind::kCancelJob] = {Verb::post, "/v1/jobs/999/cancel", ""};
  s[RouteKind::kLease] = {Verb::post, "/v1/lease", "{}"};
  s[RouteKind::kScene] = {Verb::get, fmt::format("/v1/scenes/{}", std::string(64, 'a')), ""};
  s[RouteKind::kPutTile] = {Verb::put, "/v1/jobs/999/tiles/0", "garbage"};
  s[RouteKind::kJobPriority] = {Verb::post, "/v1/jobs/999/priority", "{}"};
  s[RouteKind::kRequeueJob] = {Verb::post, "/v1/jobs/999/requeue", ""};
  s[RouteKind::kPauseJob] = {Verb::post, "/v1/jobs/999/pause", ""};
  s[RouteKind::kResumeJob] = {Verb::post, "/v1/jobs/999/resume", ""};
  s[RouteKind::kDeleteJob] = {Verb::delete_, "/v1/jobs/999", ""};
  s[RouteKind::kWorkers] = {Verb::get, "/v1/workers", ""};
  s[RouteKind::kCa] = {Verb::get, "/v1/ca", ""};
  s[RouteKind::kCreateEnrollCode] = {Verb::post, "/v1/enroll-codes", R"({"expires_s": 0})"};
  s[RouteKind::kEnroll] = {Verb::post, "/v1/enroll", "{}"};
  s[RouteKind::kCreateCredential] = {Verb::post, "/v1/credentials", "{}"};
  s[RouteKind::kListCredentials] = {Verb::get, "/v1/credentials", ""};
  s[RouteKind::kRevokeCredential] = {Verb::post, "/v1/credentials/nobody/revoke", ""};
  s[RouteKind::kPageAsset] = {Verb::get, "/", ""};
  s[RouteKind::kSessionCreate] = {Verb::post, "/ui/session", ""};  // the body is the role's token
  s[RouteKind::kSessionGet] = {Verb::get, "/ui/session", ""};
  s[RouteKind::kSessionDelete] = {Verb::delete_, "/ui/session", ""};
  s[RouteKind::kJobTiles] = {Verb::get, "/ui/api/jobs/999/tiles?since=0", ""};
  s[RouteKind::kJobFocus] = {Verb::post, "/ui/api/jobs/999/focus", R"({"x0": 0})"};
  return s;
}

// The expected table, by hand: README.md's roles. Columns: viewer, client, worker, operator,
// revoked, none.
using Row = std::array<Outcome, 6>;
constexpr Outcome P = Outcome::kPassed, F = Outcome::k403, U = Outcome::k401;
const std::map<RouteKind, Row> kExpected = {
    {RouteKind::kHealthz, {P, P, P, P, P, P}},
    {RouteKind::kMetrics, {P, P, F, P, U, U}},
    {RouteKind::kSubmitJob, {F, P, F, P, U, U}},
    {RouteKind::kListJobs, {P, P, F, P, U, U}},
    {RouteKind::kJobStatus, {P, P, F, P, U, U}},
    {RouteKind::kJobImage, {P, P, F, P, U, U}},
    {RouteKind::kCancelJob, {F, P, F, P, U, U}},
    {RouteKind::kLease, {F, F, P, P, U, U}},
    {RouteKind::kScene, {F, F, P, P, U, U}},
    {RouteKind::kPutTile, {F, F, P, P, U, U}},
    {RouteKind::kJobPriority, {F, P, F, P, U, U}},
    {RouteKind::kRequeueJob, {F, P, F, P, U, U}},
    {RouteKind::kPauseJob, {F, P, F, P, U, U}},
    {RouteKind::kResumeJob, {F, P, F, P, U, U}},
    {RouteKind::kDeleteJob, {F, P, F, P, U, U}},
    {RouteKind::kWorkers, {P, P, F, P, U, U}},
    {RouteKind::kCa, {P, P, P, P, P, P}},
    {RouteKind::kCreateEnrollCode, {F, P, F, P, U, U}},
    {RouteKind::kEnroll, {P, P, P, P, P, P}},
    {RouteKind::kCreateCredential, {F, P, F, P, U, U}},
    {RouteKind::kListCredentials, {F, P, F, P, U, U}},
    {RouteKind::kRevokeCredential, {F, P, F, P, U, U}},
    {RouteKind::kPageAsset, {P, P, P, P, P, P}},
    // Signing in with the role's token: a worker's is refused, a revoked or wrong one is 401.
    {RouteKind::kSessionCreate, {P, P, F, P, U, U}},
    {RouteKind::kSessionGet, {P, P, P, P, P, P}},
    {RouteKind::kSessionDelete, {P, P, P, P, P, P}},
    // The page's API with the role's session (a worker gets none: its sign-in is 403).
    {RouteKind::kJobTiles, {P, P, F, P, U, U}},
    {RouteKind::kJobFocus, {F, P, F, P, U, U}},
};

bool is_page_kind(RouteKind k) { return k == RouteKind::kJobTiles || k == RouteKind::kJobFocus; }

}  // namespace

TEST_CASE("roles: every route x role against the expected table", "[collector][roles]") {
  TempDir dir;
  Harness h(dir);
  std::map<Who, std::string> tokens;
  tokens[Who::kViewer] = make_credential(h, "v1", "viewer");
  tokens[Who::kClient] = make_credential(h, "c1", "client");
  tokens[Who::kWorker] = make_credential(h, "w1", "worker");
  tokens[Who::kOperator] = std::string(kToken);
  tokens[Who::kRevoked] = make_credential(h, "gone", "client");
  tokens[Who::kNone] = "not-a-token";
  // Page sessions, signed in before the revocation.
  std::map<Who, PageSession> sessions;
  for (const Who w : {Who::kViewer, Who::kClient, Who::kOperator, Who::kRevoked}) {
    auto s = page_sign_in(h, tokens[w]);
    REQUIRE(s);
    sessions[w] = *s;
  }
  Status worker_sign_in = Status::ok;
  CHECK_FALSE(page_sign_in(h, tokens[Who::kWorker], &worker_sign_in));
  CHECK(worker_sign_in == Status::forbidden);
  REQUIRE(h.call(Verb::post, "/v1/credentials/gone/revoke").result() == Status::ok);

  const auto all = samples();
  for (int k = 0; k <= static_cast<int>(RouteKind::kJobFocus); ++k) {
    const auto kind = static_cast<RouteKind>(k);
    INFO("route kind " << k);
    REQUIRE(all.contains(kind));
    REQUIRE(kExpected.contains(kind));
    const Sample& sample = all.at(kind);
    const auto matched = coll::match_route(sample.verb, sample.target);
    REQUIRE(matched.ok());
    REQUIRE(matched.value().kind == kind);
    for (std::size_t i = 0; i < std::size(kEveryone); ++i) {
      const Who who = kEveryone[i];
      INFO(sample.target << " as " << name_of(who));
      Response res;
      if (kind == RouteKind::kSessionCreate) {
        res = h.collector.handle_sync(
            browser(Verb::post, sample.target, fmt::format(R"({{"token": "{}"}})", tokens[who])));
      } else if (is_page_kind(kind)) {
        const PageSession s = sessions.contains(who) ? sessions[who] : PageSession{};
        if (who == Who::kWorker) {
          res = Response{Status::forbidden, 11};  // it has no session: its sign-in was 403 above
        } else {
          res = h.collector.handle_sync(browser(sample.verb, sample.target, sample.body, s.cookie, s.csrf));
        }
      } else if (sample.target == "/" || sample.target.starts_with("/ui/")) {
        res = h.collector.handle_sync(browser(sample.verb, sample.target, sample.body));
      } else {
        res = h.call(sample.verb, sample.target, sample.body, tokens[who]);
      }
      const Outcome expected = kExpected.at(kind)[i];
      INFO("status " << res.result_int() << ": " << res.body());
      CHECK(name_of(outcome_of(res)) == std::string(name_of(expected)));
      if (res.result() == Status::forbidden && kind != RouteKind::kSessionCreate && who != Who::kWorker) {
        CHECK(error_of(res).error.starts_with(fmt::format("this credential (role {}) may not", name_of(who))));
      }
      if (who == Who::kRevoked && expected == Outcome::k401 && !is_page_kind(kind)) {
        CHECK(error_of(res).error == "this credential was revoked");
      }
    }
  }
  // The role refusals were counted by role.
  const auto m = h.metrics();
  CHECK(m.counters.role_refusals[static_cast<std::size_t>(coll::Role::kViewer)] > 0);
  CHECK(m.counters.role_refusals[static_cast<std::size_t>(coll::Role::kWorker)] > 0);
  CHECK(m.counters.role_refusals[static_cast<std::size_t>(coll::Role::kOperator)] == 0);
}

TEST_CASE("roles: a refused request changes nothing", "[collector][roles]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::string worker = make_credential(h, "w1", "worker");
  const std::string viewer = make_credential(h, "v1", "viewer");

  // A worker cannot cancel, pause, delete or reprioritise the job.
  for (const auto& [verb, target, body] : std::vector<std::tuple<Verb, std::string, std::string>>{
           {Verb::post, fmt::format("/v1/jobs/{}/cancel", job), ""},
           {Verb::post, fmt::format("/v1/jobs/{}/pause", job), ""},
           {Verb::delete_, fmt::format("/v1/jobs/{}", job), ""},
           {Verb::post, fmt::format("/v1/jobs/{}/priority", job), R"({"priority": 9})"}}) {
    INFO(target);
    const Response res = h.call(verb, target, body, worker);
    CHECK(res.result() == Status::forbidden);
    CHECK(error_of(res).error.starts_with("this credential (role worker) may not use"));
  }
  const protocol::JobStatus s = h.status(job);
  CHECK(s.state == protocol::JobState::kQueued);
  CHECK(s.priority == 0);
  // The worker still gets work from it.
  const Response lease = h.call(Verb::post, "/v1/lease", R"({"worker": "x", "threads": 1})", worker);
  CHECK(lease.result() == Status::ok);

  // A viewer can read but not submit, and its refused submission stored nothing.
  CHECK(h.call(Verb::post, "/v1/jobs", submit_body(), viewer).result() == Status::forbidden);
  CHECK(h.call(Verb::get, "/v1/jobs", {}, viewer).result() == Status::ok);
  CHECK(stored_state(h.config).jobs.size() == 1);
  CHECK(h.metrics().counters.jobs_submitted == 1);
  CHECK(h.metrics().counters.role_refusals[static_cast<std::size_t>(coll::Role::kWorker)] == 4);
  CHECK(h.metrics().counters.role_refusals[static_cast<std::size_t>(coll::Role::kViewer)] == 1);
}

TEST_CASE("roles: a viewer's page session is read-only and a revoked one is signed out", "[collector][roles]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::string viewer = make_credential(h, "v1", "viewer");
  const std::string client = make_credential(h, "c1", "client");
  const auto vs = page_sign_in(h, viewer);
  const auto cs = page_sign_in(h, client);
  REQUIRE(vs);
  REQUIRE(cs);
  const Response session = h.collector.handle_sync(browser(Verb::get, "/ui/session", {}, vs->cookie));
  CHECK(json::parse(session.body()).at("role").as_string() == "viewer");

  CHECK(h.collector.handle_sync(browser(Verb::get, "/ui/api/jobs", {}, vs->cookie)).result() == Status::ok);
  const Response cancel = h.collector.handle_sync(
      browser(Verb::post, fmt::format("/ui/api/jobs/{}/cancel", job), {}, vs->cookie, vs->csrf));
  CHECK(cancel.result() == Status::forbidden);
  CHECK(h.status(job).state == protocol::JobState::kQueued);
  // The client's session may.
  CHECK(
      h.collector.handle_sync(browser(Verb::post, fmt::format("/ui/api/jobs/{}/pause", job), {}, cs->cookie, cs->csrf))
          .result() == Status::ok);
  CHECK(h.status(job).state == protocol::JobState::kPaused);

  // Revoked: its session is refused from the next request on, and it cannot sign in again.
  REQUIRE(h.call(Verb::post, "/v1/credentials/v1/revoke").result() == Status::ok);
  const Response after = h.collector.handle_sync(browser(Verb::get, "/ui/api/jobs", {}, vs->cookie));
  CHECK(after.result() == Status::unauthorized);
  CHECK(error_of(after).error == "this credential was revoked");
  Status again = Status::ok;
  CHECK_FALSE(page_sign_in(h, viewer, &again));
  CHECK(again == Status::unauthorized);
}

TEST_CASE("roles: route_allows and credential names", "[collector][roles]") {
  CHECK(coll::route_allows(RouteKind::kLease, coll::Role::kOperator));
  CHECK_FALSE(coll::route_allows(RouteKind::kLease, coll::Role::kClient));
  CHECK(coll::is_credential_name("worker-2.farm_a"));
  CHECK_FALSE(coll::is_credential_name(""));
  CHECK_FALSE(coll::is_credential_name("-x"));
  CHECK_FALSE(coll::is_credential_name("a b"));
  CHECK_FALSE(coll::is_credential_name(std::string(65, 'a')));
  CHECK(coll::credential_role("operator") == std::nullopt);
}

TEST_CASE("roles: a token is looked up by its digest, for the operator and the table alike", "[collector][roles]") {
  const coll::TokenCheck op("operator-token");
  coll::CredentialTable table;
  REQUIRE(table.add(coll::Credential{"w1", coll::Role::kWorker, 1, std::nullopt}, util::sha256_bytes("worker-token")));
  REQUIRE(table.add(coll::Credential{"v1", coll::Role::kViewer, 1, 5}, util::sha256_bytes("viewer-token")));
  CHECK(op.accepts_digest(util::sha256_bytes("operator-token")));
  CHECK_FALSE(op.accepts_digest(util::sha256_bytes("worker-token")));
  CHECK(table.find_digest(util::sha256_bytes("worker-token")) == table.find_token("worker-token"));
  CHECK(table.find_digest(util::sha256_bytes("nobody")) == nullptr);
  const auto who = [&](std::string_view token) { return coll::authenticate_token(token, op, table); };
  CHECK(who("operator-token").kind == coll::Authentication::Kind::kLive);
  CHECK(who("operator-token").who.role == coll::Role::kOperator);
  CHECK(who("worker-token").kind == coll::Authentication::Kind::kLive);
  CHECK(who("worker-token").who.name == "w1");
  CHECK(who("viewer-token").kind == coll::Authentication::Kind::kRevoked);
  CHECK(who("other").kind == coll::Authentication::Kind::kNone);
  CHECK(who("").kind == coll::Authentication::Kind::kNone);
}

TEST_CASE("queue: release_holder forgets one holder's leases and puts their tiles first", "[collector][roles]") {
  coll::WorkQueue q;
  const coll::TimePoint t0 = coll::TimePoint{} + std::chrono::hours(5);
  REQUIRE(q.add_job(1, 0, 4));
  REQUIRE(q.add_job(2, 0, 1));
  CHECK(q.lease(t0, "a").grant == coll::LeaseGrant{1, 0});
  CHECK(q.lease(t0, "b").grant == coll::LeaseGrant{1, 1});
  CHECK(q.lease(t0, "a").grant == coll::LeaseGrant{1, 2});
  CHECK(q.lease(t0, "").grant == coll::LeaseGrant{1, 3});
  CHECK(q.lease(t0, "a").grant == coll::LeaseGrant{2, 0});
  REQUIRE(q.complete(1, 2, t0) == coll::CompleteResult::kStored);  // a's result for tile 2 arrived
  CHECK_FALSE(q.lease(t0, "c").grant);                             // everything is out
  CHECK(q.release_holder("") == 0);
  CHECK(q.release_holder("nobody") == 0);
  CHECK(q.release_holder("a") == 2);  // tile 0 of job 1, tile 0 of job 2 (tile 2 is stored)
  CHECK_FALSE(q.has_lease(1, 0, t0));
  CHECK(q.has_lease(1, 1, t0));  // b's stays
  CHECK(q.lease(t0, "c").grant == coll::LeaseGrant{1, 0});
  CHECK(q.lease(t0, "c").grant == coll::LeaseGrant{2, 0});
  CHECK_FALSE(q.lease(t0, "c").grant);
  CHECK(q.release_holder("a") == 0);  // nothing left
}
