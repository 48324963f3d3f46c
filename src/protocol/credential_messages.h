// dtraced::protocol credential messages: the bodies of roles and enrollment (README.md,
// "Roles and enrollment"; collector/handlers/credentials.cpp answers them, the CLI sends them).
//
//   POST /v1/enroll-codes     EnrollCodeRequest  -> 201 EnrollCode
//   POST /v1/enroll           EnrollRequest      -> 201 CredentialIssued (role "worker")
//   POST /v1/credentials      CredentialRequest  -> 201 CredentialIssued
//   GET  /v1/credentials                         -> 200 CredentialList (no tokens)
//   POST /v1/credentials/{name}/revoke           -> 200 CredentialRevoked
//
// Names and roles are checked by the collector (collector/credentials.h), not here: a decoder
// checks types, sizes and ranges only.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "protocol/messages.h"

namespace dtraced::protocol {

inline constexpr std::uint32_t kDefaultEnrollCodeSeconds = 3600;
inline constexpr std::uint32_t kMaxEnrollCodeSeconds = 604800;  // a week
inline constexpr std::size_t kMaxCredentialFieldBytes = 256;    // names, roles, codes, tokens
inline constexpr std::size_t kMaxListedCredentials = 10'000;
inline constexpr std::size_t kMaxCredentialListBytes = 4 << 20;

struct EnrollCodeRequest {
  std::uint32_t expires_s = kDefaultEnrollCodeSeconds;  // 1..kMaxEnrollCodeSeconds
  std::optional<std::string> name;                      // the enrolled worker's name, unless it asks for one
  bool operator==(const EnrollCodeRequest&) const = default;
};

struct EnrollCode {
  std::string code;  // "dtj1.<secret>.<fingerprint>"
  std::int64_t expires_unix = 0;
  bool operator==(const EnrollCode&) const = default;
};

struct EnrollRequest {
  std::string code;                 // the whole code or its secret part
  std::optional<std::string> name;  // the name asked for
  bool operator==(const EnrollRequest&) const = default;
};

struct CredentialRequest {
  std::string name;
  std::string role;  // "viewer", "client" or "worker"
  bool operator==(const CredentialRequest&) const = default;
};

struct CredentialIssued {
  std::string name;
  std::string role;
  std::string token;  // shown once: the collector keeps only its digest
  bool operator==(const CredentialIssued&) const = default;
};

struct CredentialInfo {
  std::string name;
  std::string role;
  std::int64_t created_unix = 0;
  std::optional<std::int64_t> revoked_unix;
  bool operator==(const CredentialInfo&) const = default;
};

struct CredentialList {
  std::vector<CredentialInfo> credentials;  // by name
  bool operator==(const CredentialList&) const = default;
};

struct CredentialRevoked {
  std::string name;
  std::string role;
  std::int64_t revoked_unix = 0;
  std::uint64_t leases_released = 0;  // a worker's tiles re-offered at once
  bool operator==(const CredentialRevoked&) const = default;
};

std::string encode(const EnrollCodeRequest& m);
Decoded<EnrollCodeRequest> decode_enroll_code_request(std::string_view body);
std::string encode(const EnrollCode& m);
Decoded<EnrollCode> decode_enroll_code(std::string_view body);
std::string encode(const EnrollRequest& m);
Decoded<EnrollRequest> decode_enroll_request(std::string_view body);
std::string encode(const CredentialRequest& m);
Decoded<CredentialRequest> decode_credential_request(std::string_view body);
std::string encode(const CredentialIssued& m);
Decoded<CredentialIssued> decode_credential_issued(std::string_view body);
std::string encode(const CredentialList& m);
Decoded<CredentialList> decode_credential_list(std::string_view body);
std::string encode(const CredentialRevoked& m);
Decoded<CredentialRevoked> decode_credential_revoked(std::string_view body);

}  // namespace dtraced::protocol
