// Enrollment, credentials and revocation through the collector's handler (collector_testing.h),
// on a ManualClock: join codes are single-use and expire, failed attempts are limited, what is
// stored survives a restart, a worker credential is the worker's name, and revoking a worker
// re-offers its leased tiles at once.
#include <string>
#include <vector>

#include <boost/json/parse.hpp>

#include "collector/credentials.h"
#include "collector_testing.h"
#include "protocol/credential_messages.h"
#include "protocol/worker_messages.h"

namespace {

using namespace dtraced;
using namespace dtraced::testing;
namespace json = boost::json;

protocol::EnrollCode make_code(Harness& h, std::string body) {
  const Response res = h.call(Verb::post, "/v1/enroll-codes", std::move(body));
  INFO(res.body());
  REQUIRE(res.result() == Status::created);
  auto code = protocol::decode_enroll_code(res.body());
  REQUIRE(code.ok());
  return code.value();
}

Response enroll(Harness& h, std::string code, std::optional<std::string> name = std::nullopt) {
  // No token: enrollment is how a worker gets one.
  return h.call(Verb::post, "/v1/enroll", protocol::encode(protocol::EnrollRequest{std::move(code), std::move(name)}),
                "");
}

protocol::CredentialIssued enrolled(const Response& res) {
  INFO(res.body());
  REQUIRE(res.result() == Status::created);
  auto issued = protocol::decode_credential_issued(res.body());
  REQUIRE(issued.ok());
  CHECK(issued.value().role == "worker");
  return issued.value();
}

std::optional<protocol::Lease> lease_as(Harness& h, std::string_view token, std::string_view body_name = "liar") {
  const Response res =
      h.call(Verb::post, "/v1/lease", fmt::format(R"({{"worker": "{}", "threads": 1}})", body_name), token);
  INFO(res.body());
  REQUIRE(res.result() == Status::ok);
  auto reply = protocol::decode_lease_reply(res.body());
  REQUIRE(reply.ok());
  if (auto* l = std::get_if<protocol::Lease>(&reply.value())) return *l;
  return std::nullopt;
}

std::string secret_part(const std::string& code) {
  const std::size_t a = code.find('.'), b = code.find('.', a + 1);
  return code.substr(a + 1, b - a - 1);
}

}  // namespace

TEST_CASE("enroll: a join code buys one worker credential and used or expired or unknown codes are refused",
          "[collector][enroll]") {
  TempDir dir;
  std::string render_token;
  {
    Harness h(dir);
    coll::CaFingerprint fp{};
    for (std::size_t i = 0; i < fp.size(); ++i) fp[i] = static_cast<std::uint8_t>(i);
    h.collector.set_certificate_authority("-----BEGIN CERTIFICATE-----\nxx\n-----END CERTIFICATE-----\n", fp);
    const protocol::EnrollCode code = make_code(h, R"({"expires_s": 600, "name": "render"})");
    CHECK(code.expires_unix == h.clock.unix_seconds() + 600);
    REQUIRE(code.code.starts_with("dtj1."));
    CHECK(secret_part(code.code).size() == 22);
    CHECK(code.code.substr(5 + 22 + 1) == tls::base64url_encode(fp.data(), fp.size()));
    REQUIRE(coll::join_code_secret(code.code).ok());

    const protocol::CredentialIssued first = enrolled(enroll(h, code.code));
    CHECK(first.name == "render");  // the code's name
    CHECK(first.token.size() == 43);
    render_token = first.token;
    const Response used = enroll(h, code.code);
    CHECK(used.result() == Status::forbidden);
    CHECK(error_of(used).error == "this join code was already used (by render)");

    // The secret part alone works too; a name taken gets a suffix.
    const protocol::EnrollCode second = make_code(h, "{}");
    CHECK(second.expires_unix == h.clock.unix_seconds() + 3600);
    CHECK(enrolled(enroll(h, secret_part(second.code), "render")).name == "render-2");
    const protocol::EnrollCode third = make_code(h, "{}");
    CHECK(enrolled(enroll(h, third.code)).name == "worker");

    const protocol::EnrollCode brief = make_code(h, R"({"expires_s": 60})");
    h.clock.advance(61s);
    const Response expired = enroll(h, brief.code);
    CHECK(expired.result() == Status::forbidden);
    CHECK(error_of(expired).error.starts_with("this join code expired at 2023-11-14 22:14:20 UTC"));
    CHECK(error_of(enroll(h, std::string(22, 'A'))).error == "unknown join code");
    CHECK(enroll(h, "dtj1.nope").result() == Status::bad_request);
    CHECK(enroll(h, secret_part(third.code), "bad name").result() == Status::bad_request);
    // Out-of-range and unknown fields of the code request.
    CHECK(h.call(Verb::post, "/v1/enroll-codes", R"({"expires_s": 604801})").result() == Status::bad_request);
    CHECK(h.call(Verb::post, "/v1/enroll-codes", R"({"name": "a/b"})").result() == Status::bad_request);

    const auto m = h.metrics();
    CHECK(m.counters.enrollments == 3);
    CHECK(m.counters.enroll_failures == 4);  // used, expired, unknown, malformed
    CHECK(m.credentials_by_role[static_cast<std::size_t>(coll::Role::kWorker)] == 3);
    // The enrolled worker leases under its own name.
    h.submit();
    REQUIRE(lease_as(h, render_token));
  }
  // After a restart: the credential works, the used code stays used.
  Harness h(dir);
  CHECK(lease_as(h, render_token).has_value());
  const Response list = h.call(Verb::get, "/v1/credentials");
  REQUIRE(list.result() == Status::ok);
  CHECK(list.body().find("token") == std::string::npos);
  auto listed = protocol::decode_credential_list(list.body());
  REQUIRE(listed.ok());
  REQUIRE(listed.value().credentials.size() == 3);
  CHECK(listed.value().credentials[0].name == "render");
}

TEST_CASE("enroll: failed attempts are limited like sign-ins", "[collector][enroll]") {
  TempDir dir;
  Harness h(dir);
  // More than 10 failures in a minute: refused before the code is looked at.
  for (int i = 0; i < 11; ++i) CHECK(enroll(h, std::string(22, 'A')).result() == Status::forbidden);
  const protocol::EnrollCode code = make_code(h, "{}");
  const Response limited = enroll(h, code.code);
  CHECK(limited.result() == Status::too_many_requests);
  CHECK_FALSE(limited[boost::beast::http::field::retry_after].empty());
  h.clock.advance(61s);
  enrolled(enroll(h, code.code));  // the code was not spent by the refusal
}

TEST_CASE("credentials: created and listed without tokens and revoked for good across a restart",
          "[collector][enroll]") {
  TempDir dir;
  std::string viewer;
  {
    Harness h(dir);
    const Response made = h.call(Verb::post, "/v1/credentials", R"({"name": "dash", "role": "viewer"})");
    REQUIRE(made.result() == Status::created);
    viewer = protocol::decode_credential_issued(made.body()).value().token;
    CHECK(h.call(Verb::post, "/v1/credentials", R"({"name": "dash", "role": "client"})").result() == Status::conflict);
    CHECK(h.call(Verb::post, "/v1/credentials", R"({"name": "x", "role": "operator"})").result() ==
          Status::bad_request);
    CHECK(h.call(Verb::get, "/metrics", {}, viewer).result() == Status::ok);
    const Response revoked = h.call(Verb::post, "/v1/credentials/dash/revoke");
    REQUIRE(revoked.result() == Status::ok);
    auto r = protocol::decode_credential_revoked(revoked.body());
    REQUIRE(r.ok());
    CHECK(r.value().revoked_unix == h.clock.unix_seconds());
    CHECK(h.call(Verb::post, "/v1/credentials/nobody/revoke").result() == Status::not_found);
    const Response refused = h.call(Verb::get, "/metrics", {}, viewer);
    CHECK(refused.result() == Status::unauthorized);
    CHECK(error_of(refused).error == "this credential was revoked");
    const std::string metrics = h.call(Verb::get, "/metrics").body();
    CHECK(metrics.find("dtraced_revocations_total 1\n") != std::string::npos);
    CHECK(metrics.find("dtraced_credentials{role=\"viewer\"} 0\n") != std::string::npos);
    CHECK(metrics.find("dtraced_credentials_created_total 1\n") != std::string::npos);
    CHECK(metrics.find("dtraced_role_refusals_total{role=\"viewer\"} 0\n") != std::string::npos);
  }
  Harness h(dir);
  const Response refused = h.call(Verb::get, "/metrics", {}, viewer);
  CHECK(refused.result() == Status::unauthorized);
  CHECK(error_of(refused).error == "this credential was revoked");
  // Its name stays taken.
  CHECK(h.call(Verb::post, "/v1/credentials", R"({"name": "dash", "role": "viewer"})").result() == Status::conflict);
}

TEST_CASE("GET /v1/ca: 404 on plain HTTP and the PEM once set", "[collector][enroll]") {
  TempDir dir;
  Harness h(dir);
  CHECK(h.call(Verb::get, "/v1/ca", {}, "").result() == Status::not_found);
  const std::string pem = "-----BEGIN CERTIFICATE-----\nabc\n-----END CERTIFICATE-----\n";
  h.collector.set_certificate_authority(pem, std::nullopt);
  const Response res = h.call(Verb::get, "/v1/ca", {}, "");
  CHECK(res.result() == Status::ok);
  CHECK(res.body() == pem);
  // Without a CA fingerprint, the code's last part is empty.
  CHECK(make_code(h, "{}").code.ends_with("."));
}

TEST_CASE("worker identity: a worker credential is its name whatever it sends and the operator's keeps the header",
          "[collector][enroll]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::string token = enrolled(enroll(h, make_code(h, R"({"name": "w-a"})").code)).token;
  const protocol::Lease l = *lease_as(h, token, "liar");
  Request put =
      make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l.job, l.tile), payload(l.job, l.tile, l.rect), token);
  put.set(protocol::kWorkerHeader, "liar");
  const Response stored = h.collector.handle_sync(std::move(put));
  REQUIRE(stored.result() == Status::ok);
  // The operator token keeps today's behaviour: the header's name.
  const protocol::Lease l2 = *h.lease();
  Request op = make(Verb::put, fmt::format("/v1/jobs/{}/tiles/{}", l2.job, l2.tile), payload(l2.job, l2.tile, l2.rect));
  op.set(protocol::kWorkerHeader, "by-header");
  REQUIRE(h.collector.handle_sync(std::move(op)).result() == Status::ok);

  auto opened = store::Store::open(h.config.state_dir, {.verify_integrity = false});
  REQUIRE(opened.ok());
  const auto tile = opened.value().get_tile(static_cast<std::int64_t>(job), l.tile).value();
  REQUIRE(tile);
  CHECK(tile->worker == "epoch=1 worker=w-a");
  CHECK(opened.value().get_tile(static_cast<std::int64_t>(job), l2.tile).value()->worker == "epoch=1 worker=by-header");
  const Response workers = h.call(Verb::get, "/v1/workers");
  auto list = protocol::decode_worker_list(workers.body());
  REQUIRE(list.ok());
  std::vector<std::string> names;
  for (const auto& w : list.value().workers) names.push_back(w.name);
  CHECK(std::find(names.begin(), names.end(), "w-a") != names.end());
  CHECK(std::find(names.begin(), names.end(), "liar") == names.end());
}

TEST_CASE("revoke: a worker's leased tiles go to another worker at once and its next request is 401",
          "[collector][enroll]") {
  TempDir dir;
  Harness h(dir);
  const std::uint64_t job = h.submit();
  const std::string a = enrolled(enroll(h, make_code(h, R"({"name": "a"})").code)).token;
  const std::string b = enrolled(enroll(h, make_code(h, R"({"name": "b"})").code)).token;
  std::vector<protocol::Lease> held;
  while (auto l = lease_as(h, a)) held.push_back(*l);
  REQUIRE(held.size() == kTiles);
  CHECK_FALSE(lease_as(h, b));  // everything is out, and the re-offer bound has not passed

  const Response revoked = h.call(Verb::post, "/v1/credentials/a/revoke");
  REQUIRE(revoked.result() == Status::ok);
  CHECK(protocol::decode_credential_revoked(revoked.body()).value().leases_released == kTiles);
  // No time has passed: b gets a's tiles now.
  const auto taken = lease_as(h, b);
  REQUIRE(taken);
  CHECK(taken->job == job);
  CHECK(taken->tile == held.front().tile);
  // a's result for a tile is refused, and stores nothing.
  const Response late = h.put(held[1].job, held[1].tile, payload(held[1].job, held[1].tile, held[1].rect), a);
  CHECK(late.result() == Status::unauthorized);
  CHECK(error_of(late).error == "this credential was revoked");
  CHECK(stored_state(h.config).tiles[static_cast<std::int64_t>(job)].empty());
  CHECK(h.metrics().counters.revocations == 1);
}
