// dtraced::collector credentials: who a bearer token is, and what each role may call.
//
// Owns: the roles (viewer, client, worker, and operator: the --token-file token, client + worker),
// the in-memory table of credentials (loaded from the store at start, kept in step with it by the
// handlers, handlers/credentials.cpp), the one table of which roles may call which route
// (route_allows: a pure function), and the collector's view of the secrets of enrollment (random
// tokens, join code secrets and their text form), made and read by tls/join_code.h.
//
// Tokens are looked up by the SHA-256 digest of what was presented (a map keyed by digest: the
// digest of a secret reveals nothing about it); the table never holds a usable token.
//
// Thread safety: a CredentialTable has one owner (the collector's event loop); the free
// functions are stateless (the random ones read OpenSSL's RAND_bytes through tls/join_code.h).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "collector/routes.h"
#include "http/types.h"
#include "tls/join_code.h"
#include "util/sha256.h"

namespace dtraced::collector {

enum class Role { kViewer, kClient, kWorker, kOperator };
inline constexpr std::size_t kRoleCount = 4;

// "viewer", "client", "worker", "operator".
std::string_view role_name(Role role);
// The roles a credential may be given (viewer, client, worker); nullopt for anything else,
// "operator" included (that is the --token-file token only).
std::optional<Role> credential_role(std::string_view name);

// Who sent an admitted request. Public routes (health, CA, enroll) have no credential.
struct Principal {
  std::string name;  // the credential's name; "" for the operator token
  Role role = Role::kViewer;
  bool operator==(const Principal&) const = default;
};

// Whether `role` may call `kind`; the one rule (README.md, "Roles"):
//   viewer:   GET /metrics, the job reads, GET /v1/workers, the page's reads
//   client:   viewer's routes, submitting and managing jobs, credentials and join codes, the
//             page's state-changing routes
//   worker:   POST /v1/lease, GET /v1/scenes/{digest}, PUT /v1/jobs/{id}/tiles/{tile}
//   operator: client's and worker's routes
// Public routes (route_is_public) allow everyone.
bool route_allows(RouteKind kind, Role role);
// The routes that need no credential: GET /healthz, GET /v1/ca, POST /v1/enroll, and the page's
// files and session routes (the page's own rules apply to those, admission.h).
bool route_is_public(RouteKind kind);
// "POST /v1/jobs/{id}/cancel": what a role refusal names.
std::string_view route_label(RouteKind kind);

// Credential names: 1 to kMaxCredentialNameBytes of [A-Za-z0-9._-], starting with a letter or a
// digit (they name workers in logs, metrics and the store).
inline constexpr std::size_t kMaxCredentialNameBytes = 64;
bool is_credential_name(std::string_view name);

struct Credential {
  std::string name;
  Role role = Role::kViewer;
  std::int64_t created_unix = 0;
  std::optional<std::int64_t> revoked_unix;
  bool revoked() const { return revoked_unix.has_value(); }
};

// The credentials of the collector, revoked ones included (a revoked token must keep getting
// "revoked", not "wrong token"), by name and by token digest.
class CredentialTable {
 public:
  // False (changing nothing) when the name or the digest is present.
  bool add(Credential credential, const util::Sha256Digest& token_sha256);
  // The credential whose token is `token`, revoked or not; nullptr for none.
  const Credential* find_token(std::string_view token) const;
  // The same by the token's SHA-256.
  const Credential* find_digest(const util::Sha256Digest& token_sha256) const;
  const Credential* find_name(std::string_view name) const;
  // Marks it revoked at `unix_s`; false when unknown or revoked already.
  bool revoke(std::string_view name, std::int64_t unix_s);
  // Every credential by name.
  std::vector<Credential> list() const;
  // Live (not revoked) credentials of `role`.
  std::size_t live(Role role) const;
  std::size_t size() const { return by_name_.size(); }

 private:
  std::map<std::string, Credential, std::less<>> by_name_;
  std::map<util::Sha256Digest, std::string> name_by_token_;
};

// What a bearer token is: nothing known, a revoked credential, or a live principal.
struct Authentication {
  enum class Kind { kNone, kRevoked, kLive } kind = Kind::kNone;
  Principal who;
};
// `token` against the operator's token (TokenCheck) and the table.
Authentication authenticate_token(std::string_view token, const TokenCheck& operator_token,
                                  const CredentialTable& table);
// The request's `Authorization: Bearer` token, as above (kNone without a well-formed header).
Authentication authenticate(const http::Request& head, const TokenCheck& operator_token, const CredentialTable& table);
// The token of `Authorization: Bearer <token>` (scheme case-insensitive), "" when absent or
// malformed.
std::string_view bearer_token(const http::Request& head);

// ---- secrets (tls/join_code.h makes them; these say "try later" instead of throwing) -------

// tls::random_token (32 random bytes, base64url): a credential's token. nullopt when the random
// source fails (the handler answers 503).
std::optional<std::string> random_token();

using JoinSecret = decltype(tls::JoinCode::secret);
using CaFingerprint = tls::Fingerprint;
// A join code's random secret; nullopt when the random source fails.
std::optional<JoinSecret> random_join_secret();
// tls::format_join_code: "dtj1.<base64url secret>.<base64url fingerprint, or empty>".
std::string format_join_code(const JoinSecret& secret, const std::optional<CaFingerprint>& ca);
// The secret of a join code given whole ("dtj1.S.F", read by tls::parse_join_code) or as its
// secret part alone ("S"); the error says what is wrong.
util::Result<JoinSecret> join_code_secret(std::string_view code);

}  // namespace dtraced::collector
