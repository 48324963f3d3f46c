#include "collector/credentials.h"

#include <algorithm>
#include <stdexcept>
#include <utility>

#include <boost/beast/core/string.hpp>
#include <boost/beast/http/field.hpp>
#include <fmt/format.h>

namespace dtraced::collector {
namespace {

constexpr unsigned bit(Role r) { return 1u << static_cast<unsigned>(r); }
constexpr unsigned kReaders = bit(Role::kViewer) | bit(Role::kClient) | bit(Role::kOperator);
constexpr unsigned kClients = bit(Role::kClient) | bit(Role::kOperator);
constexpr unsigned kWorkers = bit(Role::kWorker) | bit(Role::kOperator);
constexpr unsigned kEveryone = bit(Role::kViewer) | bit(Role::kClient) | bit(Role::kWorker) | bit(Role::kOperator);

// The roles of each route: the table route_allows reads.
unsigned route_roles(RouteKind kind) {
  switch (kind) {
    case RouteKind::kHealthz:
    case RouteKind::kCa:
    case RouteKind::kEnroll:
    case RouteKind::kPageAsset:
    case RouteKind::kSessionCreate:
    case RouteKind::kSessionGet:
    case RouteKind::kSessionDelete:
      return kEveryone;
    case RouteKind::kMetrics:
    case RouteKind::kListJobs:
    case RouteKind::kJobStatus:
    case RouteKind::kJobImage:
    case RouteKind::kWorkers:
    case RouteKind::kJobTiles:
      return kReaders;
    case RouteKind::kSubmitJob:
    case RouteKind::kCancelJob:
    case RouteKind::kJobPriority:
    case RouteKind::kRequeueJob:
    case RouteKind::kPauseJob:
    case RouteKind::kResumeJob:
    case RouteKind::kDeleteJob:
    case RouteKind::kJobFocus:
    case RouteKind::kCreateEnrollCode:
    case RouteKind::kCreateCredential:
    case RouteKind::kListCredentials:
    case RouteKind::kRevokeCredential:
      return kClients;
    case RouteKind::kLease:
    case RouteKind::kScene:
    case RouteKind::kPutTile:
      return kWorkers;
  }
  return 0;  // a kind this table does not know: nobody
}

}  // namespace

std::string_view role_name(Role role) {
  switch (role) {
    case Role::kViewer:
      return "viewer";
    case Role::kClient:
      return "client";
    case Role::kWorker:
      return "worker";
    case Role::kOperator:
      return "operator";
  }
  return "unknown";
}

std::optional<Role> credential_role(std::string_view name) {
  if (name == "viewer") return Role::kViewer;
  if (name == "client") return Role::kClient;
  if (name == "worker") return Role::kWorker;
  return std::nullopt;
}

bool route_allows(RouteKind kind, Role role) { return (route_roles(kind) & bit(role)) != 0; }

bool route_is_public(RouteKind kind) {
  switch (kind) {
    case RouteKind::kHealthz:
    case RouteKind::kCa:
    case RouteKind::kEnroll:
    case RouteKind::kPageAsset:
    case RouteKind::kSessionCreate:
    case RouteKind::kSessionGet:
    case RouteKind::kSessionDelete:
      return true;
    default:
      return false;
  }
}

std::string_view route_label(RouteKind kind) {
  switch (kind) {
    case RouteKind::kHealthz:
      return "GET /healthz";
    case RouteKind::kMetrics:
      return "GET /metrics";
    case RouteKind::kSubmitJob:
      return "POST /v1/jobs";
    case RouteKind::kListJobs:
      return "GET /v1/jobs";
    case RouteKind::kJobStatus:
      return "GET /v1/jobs/{id}";
    case RouteKind::kJobImage:
      return "GET /v1/jobs/{id}/image";
    case RouteKind::kCancelJob:
      return "POST /v1/jobs/{id}/cancel";
    case RouteKind::kLease:
      return "POST /v1/lease";
    case RouteKind::kScene:
      return "GET /v1/scenes/{digest}";
    case RouteKind::kPutTile:
      return "PUT /v1/jobs/{id}/tiles/{tile}";
    case RouteKind::kJobPriority:
      return "POST /v1/jobs/{id}/priority";
    case RouteKind::kRequeueJob:
      return "POST /v1/jobs/{id}/requeue";
    case RouteKind::kPauseJob:
      return "POST /v1/jobs/{id}/pause";
    case RouteKind::kResumeJob:
      return "POST /v1/jobs/{id}/resume";
    case RouteKind::kDeleteJob:
      return "DELETE /v1/jobs/{id}";
    case RouteKind::kWorkers:
      return "GET /v1/workers";
    case RouteKind::kCa:
      return "GET /v1/ca";
    case RouteKind::kCreateEnrollCode:
      return "POST /v1/enroll-codes";
    case RouteKind::kEnroll:
      return "POST /v1/enroll";
    case RouteKind::kCreateCredential:
      return "POST /v1/credentials";
    case RouteKind::kListCredentials:
      return "GET /v1/credentials";
    case RouteKind::kRevokeCredential:
      return "POST /v1/credentials/{name}/revoke";
    case RouteKind::kPageAsset:
      return "the page's files";
    case RouteKind::kSessionCreate:
      return "POST /ui/session";
    case RouteKind::kSessionGet:
      return "GET /ui/session";
    case RouteKind::kSessionDelete:
      return "DELETE /ui/session";
    case RouteKind::kJobTiles:
      return "GET /ui/api/jobs/{id}/tiles";
    case RouteKind::kJobFocus:
      return "POST /ui/api/jobs/{id}/focus";
  }
  return "this endpoint";
}

bool is_credential_name(std::string_view name) {
  if (name.empty() || name.size() > kMaxCredentialNameBytes) return false;
  const auto alnum = [](char c) { return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9'); };
  if (!alnum(name.front())) return false;
  return std::all_of(name.begin(), name.end(), [&](char c) { return alnum(c) || c == '.' || c == '_' || c == '-'; });
}

// ---- the table ------------------------------------------------------------------------------

bool CredentialTable::add(Credential credential, const util::Sha256Digest& token_sha256) {
  if (by_name_.contains(credential.name) || name_by_token_.contains(token_sha256)) return false;
  name_by_token_.emplace(token_sha256, credential.name);
  std::string name = credential.name;
  by_name_.emplace(std::move(name), std::move(credential));
  return true;
}

const Credential* CredentialTable::find_token(std::string_view token) const {
  return find_digest(util::sha256_bytes(token));
}

const Credential* CredentialTable::find_digest(const util::Sha256Digest& token_sha256) const {
  const auto it = name_by_token_.find(token_sha256);
  return it == name_by_token_.end() ? nullptr : find_name(it->second);
}

const Credential* CredentialTable::find_name(std::string_view name) const {
  const auto it = by_name_.find(name);
  return it == by_name_.end() ? nullptr : &it->second;
}

bool CredentialTable::revoke(std::string_view name, std::int64_t unix_s) {
  const auto it = by_name_.find(name);
  if (it == by_name_.end() || it->second.revoked()) return false;
  it->second.revoked_unix = unix_s;
  return true;
}

std::vector<Credential> CredentialTable::list() const {
  std::vector<Credential> out;
  out.reserve(by_name_.size());
  for (const auto& [name, c] : by_name_) out.push_back(c);
  return out;
}

std::size_t CredentialTable::live(Role role) const {
  return static_cast<std::size_t>(std::count_if(by_name_.begin(), by_name_.end(), [role](const auto& e) {
    return e.second.role == role && !e.second.revoked();
  }));
}

// ---- authentication -------------------------------------------------------------------------

std::string_view bearer_token(const http::Request& head) {
  constexpr std::string_view kScheme = "bearer";
  const auto it = head.find(boost::beast::http::field::authorization);
  if (it == head.end()) return {};
  const std::string_view value(it->value().data(), it->value().size());
  if (value.size() <= kScheme.size() || !boost::beast::iequals(value.substr(0, kScheme.size()), kScheme) ||
      value[kScheme.size()] != ' ') {
    return {};
  }
  std::string_view presented = value.substr(kScheme.size() + 1);
  while (!presented.empty() && presented.front() == ' ') presented.remove_prefix(1);
  return presented;
}

Authentication authenticate_token(std::string_view token, const TokenCheck& operator_token,
                                  const CredentialTable& table) {
  Authentication a;
  if (token.empty()) return a;
  // One SHA-256 per token, for the operator's token and the table both.
  const util::Sha256Digest digest = util::sha256_bytes(token);
  if (operator_token.accepts_digest(digest)) {
    a.kind = Authentication::Kind::kLive;
    a.who = Principal{"", Role::kOperator};
    return a;
  }
  const Credential* c = table.find_digest(digest);
  if (c == nullptr) return a;
  a.kind = c->revoked() ? Authentication::Kind::kRevoked : Authentication::Kind::kLive;
  a.who = Principal{c->name, c->role};
  return a;
}

Authentication authenticate(const http::Request& head, const TokenCheck& operator_token, const CredentialTable& table) {
  return authenticate_token(bearer_token(head), operator_token, table);
}

// ---- secrets --------------------------------------------------------------------------------

std::optional<std::string> random_token() {
  try {
    return tls::random_token();
  } catch (const std::runtime_error&) {
    return std::nullopt;
  }
}

std::optional<JoinSecret> random_join_secret() {
  try {
    return tls::make_join_code(std::nullopt).secret;
  } catch (const std::runtime_error&) {
    return std::nullopt;
  }
}

std::string format_join_code(const JoinSecret& secret, const std::optional<CaFingerprint>& ca) {
  return tls::format_join_code(tls::JoinCode{secret, ca});
}

util::Result<JoinSecret> join_code_secret(std::string_view code) {
  // White space around it is ignored, as pasted; the secret part alone reads as a whole code
  // without a fingerprint.
  const auto space = [](char ch) { return ch == ' ' || ch == '\t' || ch == '\r' || ch == '\n'; };
  while (!code.empty() && space(code.front())) code.remove_prefix(1);
  while (!code.empty() && space(code.back())) code.remove_suffix(1);
  const bool secret_only = !code.starts_with(tls::kJoinCodePrefix) && code.find('.') == std::string_view::npos;
  auto parsed =
      tls::parse_join_code(secret_only ? fmt::format("{}{}.", tls::kJoinCodePrefix, code) : std::string(code));
  if (!parsed) return util::Error(parsed.error().message, "/code");
  return parsed->secret;
}

}  // namespace dtraced::collector
