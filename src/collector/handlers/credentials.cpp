// Roles and enrollment (credentials.h): the CA workers trust, join codes, enrollment, and the
// credentials a client creates, lists and revokes. Every change is durable (the store writer)
// before the table on the loop changes and before the answer.
#include <algorithm>
#include <ctime>
#include <optional>
#include <string>
#include <utility>

#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

#include "collector/handlers.h"
#include "collector/writer_bridge.h"
#include "protocol/credential_messages.h"
#include "util/log.h"
#include "util/sha256.h"

namespace dtraced::collector {
namespace {

namespace bhttp = boost::beast::http;

// The most credentials a collector keeps (revoked ones included): the table is in memory.
constexpr std::size_t kMaxCredentials = protocol::kMaxListedCredentials;
constexpr std::string_view kDefaultWorkerName = "worker";

// "2026-12-02 18:00:00 UTC".
std::string utc_text(std::int64_t unix_s) {
  const std::time_t t = static_cast<std::time_t>(unix_s);
  std::tm tm{};
  if (gmtime_r(&t, &tm) == nullptr) return fmt::format("unix time {}", unix_s);
  char text[32];
  const std::size_t n = std::strftime(text, sizeof text, "%Y-%m-%d %H:%M:%S UTC", &tm);
  return std::string(text, n);
}

store::Blob digest_blob(std::string_view bytes) {
  const util::Sha256Digest d = util::sha256_bytes(bytes);
  return store::Blob(d.begin(), d.end());
}

util::Sha256Digest digest_of_blob(const store::Blob& blob) {
  util::Sha256Digest d{};
  std::copy_n(blob.begin(), std::min(blob.size(), d.size()), d.begin());
  return d;
}

Refusal forbidden(std::string message, std::string field = {}) {
  return Refusal{http::Status::forbidden, util::Error(std::move(message), std::move(field)), {}};
}

Refusal conflict(std::string message, std::string field = {}) {
  return Refusal{http::Status::conflict, util::Error(std::move(message), std::move(field)), {}};
}

util::Result<void, Refusal> check_name(const std::optional<std::string>& name) {
  if (name && !is_credential_name(*name)) {
    return bad_request(fmt::format("a name is 1 to {} characters of A-Z a-z 0-9 . _ -, starting with a letter or digit",
                                   kMaxCredentialNameBytes),
                       "/name");
  }
  return {};
}

std::optional<http::Response> check_room(const Context& c) {
  if (!c.accepting_writes()) return respond(busy("the collector is stopping; retry later"));
  if (c.credentials.size() >= kMaxCredentials) {
    return respond(conflict(fmt::format("the collector keeps at most {} credentials", kMaxCredentials)));
  }
  return std::nullopt;
}

// A refused enrollment: counted against the limit and logged (rate-limited, with the peer).
http::Response enroll_refused(Context& c, const http::Request& req, Refusal refusal) {
  c.enroll_attempts.failed(c.clock.now());
  ++c.counters.enroll_failures;
  std::uint64_t held_back = 0;
  if (c.auth_failure_log.allow(c.clock.now(), held_back)) {
    const std::string peer = request_peer(req);
    util::log_warn(
        "collector: refused an enrollment from {}: {}{}", peer.empty() ? "an unknown address" : peer,
        refusal.error.message,
        held_back == 0 ? std::string() : fmt::format(" ({} more refused since the last such line)", held_back));
  }
  return respond(refusal);
}

}  // namespace

http::Response get_ca(const Context& c) {
  if (c.ca_pem.empty()) {
    return http::make_error(http::Status::not_found, "this collector speaks plain HTTP: it has no CA to trust");
  }
  return http::make_text_response(http::Status::ok, c.ca_pem, "application/x-pem-file");
}

async::Awaitable<http::Response> create_enroll_code(Context& c, const http::Request& req) {
  auto decoded = protocol::decode_enroll_code_request(req.body());
  if (!decoded) co_return respond(decode_failure(decoded.error()));
  const protocol::EnrollCodeRequest& r = decoded.value();
  if (auto named = check_name(r.name); !named) co_return respond(named.error());
  if (!c.accepting_writes()) co_return respond(busy("the collector is stopping; retry later"));
  const std::optional<JoinSecret> secret = random_join_secret();
  if (!secret) co_return respond(busy("no random numbers for a join code; retry later"));
  store::StoredJoinCode code;
  code.secret_sha256 = digest_blob(std::string_view(reinterpret_cast<const char*>(secret->data()), secret->size()));
  code.name_hint = r.name;
  code.created_unix = c.clock.unix_seconds();
  code.expires_unix = code.created_unix + r.expires_s;
  auto insert = [code](store::Store& s) { return s.insert_join_code(code); };
  auto reply = co_await on_writer(*c.writer, std::move(insert));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: cannot store a join code: {}", reply.value->error().message);
    }
    co_return respond(busy("the join code could not be stored; retry later"));
  }
  util::log_info("collector: a join code was created, valid until {}{}", utc_text(code.expires_unix),
                 r.name ? fmt::format(" (for worker '{}')", *r.name) : std::string());
  const protocol::EnrollCode answer{format_join_code(*secret, c.ca_fingerprint), code.expires_unix};
  co_return json_answer(http::Status::created, protocol::encode(answer));
}

async::Awaitable<http::Response> enroll(Context& c, const http::Request& req) {
  const TimePoint now = c.clock.now();
  if (!c.enroll_attempts.allows(now)) {
    ++c.counters.enroll_failures;
    http::Response res =
        http::make_error(http::Status::too_many_requests, "too many failed enrollments; wait a minute and try again");
    const auto wait = std::chrono::duration_cast<std::chrono::seconds>(c.enroll_attempts.retry_after(now)).count();
    res.set(bhttp::field::retry_after, std::to_string(std::max<std::int64_t>(1, wait + 1)));
    co_return res;
  }
  auto decoded = protocol::decode_enroll_request(req.body());
  if (!decoded) co_return respond(decode_failure(decoded.error()));
  const protocol::EnrollRequest& r = decoded.value();
  if (auto named = check_name(r.name); !named) co_return respond(named.error());
  const util::Result<JoinSecret> secret = join_code_secret(r.code);
  if (!secret) co_return enroll_refused(c, req, bad_request(secret.error().message, "/code"));
  if (auto full = check_room(c)) co_return std::move(*full);
  const std::optional<std::string> token = random_token();
  if (!token) co_return respond(busy("no random numbers for a token; retry later"));

  const store::Blob secret_digest =
      digest_blob(std::string_view(reinterpret_cast<const char*>(secret->data()), secret->size()));
  const store::Blob token_digest = digest_blob(*token);
  const std::optional<std::string> requested = r.name;
  const std::int64_t now_unix = c.clock.unix_seconds();
  auto run = [secret_digest, token_digest, requested, now_unix](store::Store& s) -> util::Result<store::Enrollment> {
    // The name asked for, else the code's hint, else "worker"; the store makes it unique.
    std::string base = requested.value_or("");
    if (base.empty()) {
      auto code = s.get_join_code(secret_digest);
      if (!code) return std::move(code).error();
      if (code.value() && code.value()->name_hint) base = *code.value()->name_hint;
    }
    if (base.empty()) base = std::string(kDefaultWorkerName);
    return s.enroll(secret_digest, base, role_name(Role::kWorker), token_digest, now_unix);
  };
  auto reply = co_await on_writer(*c.writer, std::move(run));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: cannot store an enrollment: {}", reply.value->error().message);
    }
    co_return respond(busy("the enrollment could not be stored; retry later"));
  }
  const store::Enrollment& e = reply.value->value();
  switch (e.outcome) {
    case store::EnrollOutcome::kUnknown:
      co_return enroll_refused(c, req, forbidden("unknown join code", "/code"));
    case store::EnrollOutcome::kUsed:
      co_return enroll_refused(
          c, req,
          forbidden(fmt::format("this join code was already used (by {})", e.code->used_by.value_or("?")), "/code"));
    case store::EnrollOutcome::kExpired:
      co_return enroll_refused(
          c, req, forbidden(fmt::format("this join code expired at {}", utc_text(e.code->expires_unix)), "/code"));
    case store::EnrollOutcome::kNoName:
      co_return respond(conflict("every name like the one asked for is taken; ask for another", "/name"));
    case store::EnrollOutcome::kEnrolled:
      break;
  }
  c.credentials.add(Credential{e.name, Role::kWorker, now_unix, std::nullopt}, digest_of_blob(token_digest));
  ++c.counters.enrollments;
  const std::string peer = request_peer(req);
  util::log_info("collector: worker '{}' enrolled from {}", e.name, peer.empty() ? "an unknown address" : peer);
  const protocol::CredentialIssued answer{e.name, std::string(role_name(Role::kWorker)), *token};
  co_return json_answer(http::Status::created, protocol::encode(answer));
}

async::Awaitable<http::Response> create_credential(Context& c, const http::Request& req) {
  auto decoded = protocol::decode_credential_request(req.body());
  if (!decoded) co_return respond(decode_failure(decoded.error()));
  const protocol::CredentialRequest& r = decoded.value();
  if (auto named = check_name(r.name); !named) co_return respond(named.error());
  const std::optional<Role> role = credential_role(r.role);
  if (!role) co_return respond(bad_request("role must be viewer, client or worker", "/role"));
  if (c.credentials.find_name(r.name) != nullptr) {
    co_return respond(conflict(fmt::format("a credential named '{}' exists", r.name), "/name"));
  }
  if (auto full = check_room(c)) co_return std::move(*full);
  const std::optional<std::string> token = random_token();
  if (!token) co_return respond(busy("no random numbers for a token; retry later"));
  const store::StoredCredential row{r.name, r.role, digest_blob(*token), c.clock.unix_seconds(), std::nullopt};
  auto insert = [row](store::Store& s) { return s.insert_credential(row); };
  auto reply = co_await on_writer(*c.writer, std::move(insert));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: cannot store credential '{}': {}", r.name, reply.value->error().message);
    }
    co_return respond(busy("the credential could not be stored; retry later"));
  }
  if (!reply.value->value() || !c.credentials.add(Credential{row.name, *role, row.created_unix, std::nullopt},
                                                  digest_of_blob(row.token_sha256))) {
    co_return respond(conflict(fmt::format("a credential named '{}' exists", r.name), "/name"));
  }
  ++c.counters.credentials_created;
  util::log_info("collector: credential '{}' (role {}) created", row.name, row.role);
  const protocol::CredentialIssued answer{row.name, row.role, *token};
  co_return json_answer(http::Status::created, protocol::encode(answer));
}

http::Response list_credentials(const Context& c) {
  protocol::CredentialList list;
  for (const Credential& cred : c.credentials.list()) {
    list.credentials.push_back(
        protocol::CredentialInfo{cred.name, std::string(role_name(cred.role)), cred.created_unix, cred.revoked_unix});
  }
  return json_answer(http::Status::ok, protocol::encode(list));
}

async::Awaitable<http::Response> revoke_credential(Context& c, std::string name) {
  const Credential* found = c.credentials.find_name(name);
  if (found == nullptr) {
    co_return respond(Refusal{http::Status::not_found, util::Error(fmt::format("no credential named '{}'", name)), {}});
  }
  if (found->revoked()) {
    // Idempotent: revoked once, at that time.
    co_return json_answer(http::Status::ok,
                          protocol::encode(protocol::CredentialRevoked{found->name, std::string(role_name(found->role)),
                                                                       *found->revoked_unix, 0}));
  }
  if (!c.accepting_writes()) co_return respond(busy("the collector is stopping; retry later"));
  const std::int64_t now_unix = c.clock.unix_seconds();
  auto revoke = [name, now_unix](store::Store& s) { return s.revoke_credential(name, now_unix); };
  auto reply = co_await on_writer(*c.writer, std::move(revoke));
  if (!reply.ok() || !reply.value->ok()) {
    ++c.counters.store_busy;
    if (reply.value && !reply.value->ok()) {
      util::log_error("collector: cannot revoke credential '{}': {}", name, reply.value->error().message);
    }
    co_return respond(busy("the revocation could not be stored; retry later"));
  }
  // Looked up again: the table may have changed while the store worked.
  const Credential* cred = c.credentials.find_name(name);
  if (cred == nullptr) co_return respond(busy("the credential changed meanwhile; retry"));
  const bool revoked_now = c.credentials.revoke(name, now_unix);
  std::size_t released = 0;
  if (revoked_now) {
    ++c.counters.revocations;
    if (cred->role == Role::kWorker) released = c.queue.release_holder(name);
    util::log_info("collector: credential '{}' (role {}) revoked{}", name, role_name(cred->role),
                   released == 0 ? std::string() : fmt::format("; {} leased tile(s) re-offered", released));
  }
  const protocol::CredentialRevoked answer{cred->name, std::string(role_name(cred->role)),
                                           cred->revoked_unix.value_or(now_unix), released};
  co_return json_answer(http::Status::ok, protocol::encode(answer));
}

}  // namespace dtraced::collector
