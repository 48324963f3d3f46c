#include "protocol/credential_messages.h"

#include <array>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>

#include "jsonio/write.h"
#include "protocol/codec.h"

namespace dtraced::protocol {
namespace {

namespace json = boost::json;
using namespace detail;

constexpr std::int64_t kMaxUnix = std::int64_t{1} << 53;  // times travel as JSON numbers
constexpr std::size_t kMaxField = kMaxCredentialFieldBytes;

constexpr std::array<std::string_view, 2> kEnrollCodeRequestKeys = {"expires_s", "name"};
constexpr std::array<std::string_view, 2> kEnrollCodeKeys = {"code", "expires_unix"};
constexpr std::array<std::string_view, 2> kEnrollRequestKeys = {"code", "name"};
constexpr std::array<std::string_view, 2> kCredentialRequestKeys = {"name", "role"};
constexpr std::array<std::string_view, 3> kCredentialIssuedKeys = {"name", "role", "token"};
constexpr std::array<std::string_view, 1> kCredentialListKeys = {"credentials"};
constexpr std::array<std::string_view, 4> kCredentialInfoKeys = {"name", "role", "created_unix", "revoked_unix"};
constexpr std::array<std::string_view, 4> kCredentialRevokedKeys = {"name", "role", "revoked_unix", "leases_released"};

// An optional string field: absent, or a string of at most kMaxField bytes.
void optional_string(Fields& f, std::string_view key, std::optional<std::string>& out) {
  if (!f.has(key)) return;
  std::string s;
  if (f.string(key, s, kMaxField)) out = std::move(s);
}

json::object info_object(const CredentialInfo& c) {
  json::object o{{"name", c.name}, {"role", c.role}, {"created_unix", c.created_unix}};
  if (c.revoked_unix) o["revoked_unix"] = *c.revoked_unix;
  return o;
}

void read_info(Fields& f, CredentialInfo& c) {
  f.string("name", c.name, kMaxField);
  f.string("role", c.role, kMaxField);
  f.integer("created_unix", c.created_unix, -kMaxUnix, kMaxUnix);
  f.integer("revoked_unix", c.revoked_unix, -kMaxUnix, kMaxUnix, Need::kOptional);
}

}  // namespace

std::string encode(const EnrollCodeRequest& m) {
  json::object o{{"expires_s", m.expires_s}};
  if (m.name) o["name"] = *m.name;
  return jsonio::to_text(o);
}

Decoded<EnrollCodeRequest> decode_enroll_code_request(std::string_view body) {
  return decode_object<EnrollCodeRequest>(
      body, kMaxMessageBytes, kMaxMessageDepth, kEnrollCodeRequestKeys, [](Fields& f, EnrollCodeRequest& m) {
        f.integer("expires_s", m.expires_s, 1, kMaxEnrollCodeSeconds, Need::kOptional);
        optional_string(f, "name", m.name);
      });
}

std::string encode(const EnrollCode& m) {
  return jsonio::to_text(json::object{{"code", m.code}, {"expires_unix", m.expires_unix}});
}

Decoded<EnrollCode> decode_enroll_code(std::string_view body) {
  return decode_object<EnrollCode>(body, kMaxMessageBytes, kMaxMessageDepth, kEnrollCodeKeys,
                                   [](Fields& f, EnrollCode& m) {
                                     f.string("code", m.code, kMaxField);
                                     f.integer("expires_unix", m.expires_unix, -kMaxUnix, kMaxUnix);
                                   });
}

std::string encode(const EnrollRequest& m) {
  json::object o{{"code", m.code}};
  if (m.name) o["name"] = *m.name;
  return jsonio::to_text(o);
}

Decoded<EnrollRequest> decode_enroll_request(std::string_view body) {
  return decode_object<EnrollRequest>(body, kMaxMessageBytes, kMaxMessageDepth, kEnrollRequestKeys,
                                      [](Fields& f, EnrollRequest& m) {
                                        f.string("code", m.code, kMaxField);
                                        optional_string(f, "name", m.name);
                                      });
}

std::string encode(const CredentialRequest& m) {
  return jsonio::to_text(json::object{{"name", m.name}, {"role", m.role}});
}

Decoded<CredentialRequest> decode_credential_request(std::string_view body) {
  return decode_object<CredentialRequest>(body, kMaxMessageBytes, kMaxMessageDepth, kCredentialRequestKeys,
                                          [](Fields& f, CredentialRequest& m) {
                                            f.string("name", m.name, kMaxField);
                                            f.string("role", m.role, kMaxField);
                                          });
}

std::string encode(const CredentialIssued& m) {
  return jsonio::to_text(json::object{{"name", m.name}, {"role", m.role}, {"token", m.token}});
}

Decoded<CredentialIssued> decode_credential_issued(std::string_view body) {
  return decode_object<CredentialIssued>(body, kMaxMessageBytes, kMaxMessageDepth, kCredentialIssuedKeys,
                                         [](Fields& f, CredentialIssued& m) {
                                           f.string("name", m.name, kMaxField);
                                           f.string("role", m.role, kMaxField);
                                           f.string("token", m.token, kMaxField);
                                         });
}

std::string encode(const CredentialList& m) {
  json::array a;
  for (const CredentialInfo& c : m.credentials) a.push_back(info_object(c));
  return jsonio::to_text(json::object{{"credentials", std::move(a)}});
}

Decoded<CredentialList> decode_credential_list(std::string_view body) {
  return decode_object<CredentialList>(
      body, kMaxCredentialListBytes, kMaxMessageDepth, kCredentialListKeys, [](Fields& f, CredentialList& m) {
        read_object_array(f, "credentials", kMaxListedCredentials, kCredentialInfoKeys, m.credentials, read_info);
      });
}

std::string encode(const CredentialRevoked& m) {
  return jsonio::to_text(json::object{
      {"name", m.name}, {"role", m.role}, {"revoked_unix", m.revoked_unix}, {"leases_released", m.leases_released}});
}

Decoded<CredentialRevoked> decode_credential_revoked(std::string_view body) {
  return decode_object<CredentialRevoked>(body, kMaxMessageBytes, kMaxMessageDepth, kCredentialRevokedKeys,
                                          [](Fields& f, CredentialRevoked& m) {
                                            f.string("name", m.name, kMaxField);
                                            f.string("role", m.role, kMaxField);
                                            f.integer("revoked_unix", m.revoked_unix, -kMaxUnix, kMaxUnix);
                                            f.integer("leases_released", m.leases_released, 0, kMaxUnix);
                                          });
}

}  // namespace dtraced::protocol
