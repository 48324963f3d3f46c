// Credentials and join codes: the row accessors of Store (store.h) for enrollment and roles, on
// the connection and statement cache of store_impl.h.
#include <sqlite3.h>

#include <string>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "store/store.h"
#include "store/store_impl.h"

namespace dtraced::store {
namespace {

constexpr std::string_view kSelectCredentials =
    "SELECT name, role, token_sha256, created_unix, revoked_unix FROM credentials ";
constexpr std::string_view kSelectJoinCodes =
    "SELECT secret_sha256, name_hint, created_unix, expires_unix, used_unix, used_by FROM join_codes ";

std::optional<std::int64_t> column_optional_int(sqlite3_stmt* s, int i) {
  if (sqlite3_column_type(s, i) == SQLITE_NULL) return std::nullopt;
  return sqlite3_column_int64(s, i);
}

std::optional<std::string> column_optional_text(sqlite3_stmt* s, int i) {
  if (sqlite3_column_type(s, i) == SQLITE_NULL) return std::nullopt;
  return column_text(s, i);
}

StoredCredential read_credential(sqlite3_stmt* s) {
  StoredCredential c;
  c.name = column_text(s, 0);
  c.role = column_text(s, 1);
  c.token_sha256 = column_blob(s, 2);
  c.created_unix = sqlite3_column_int64(s, 3);
  c.revoked_unix = column_optional_int(s, 4);
  return c;
}

StoredJoinCode read_join_code(sqlite3_stmt* s) {
  StoredJoinCode c;
  c.secret_sha256 = column_blob(s, 0);
  c.name_hint = column_optional_text(s, 1);
  c.created_unix = sqlite3_column_int64(s, 2);
  c.expires_unix = sqlite3_column_int64(s, 3);
  c.used_unix = column_optional_int(s, 4);
  c.used_by = column_optional_text(s, 5);
  return c;
}

}  // namespace

Result<bool> Store::insert_credential(const StoredCredential& credential) {
  constexpr std::string_view kSql =
      "INSERT INTO credentials(name, role, token_sha256, created_unix, revoked_unix) VALUES (?1, ?2, ?3, ?4, ?5) "
      "ON CONFLICT DO NOTHING";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value()
                     .bind(credential.name)
                     .bind(credential.role)
                     .bind_blob(credential.token_sha256)
                     .bind(credential.created_unix)
                     .bind_optional(credential.revoked_unix)
                     .step();
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("storing credential '{}'", credential.name), rc);
  return sqlite3_changes64(impl_->db) == 1;
}

Result<bool> Store::revoke_credential(std::string_view name, std::int64_t revoked_unix) {
  constexpr std::string_view kSql = "UPDATE credentials SET revoked_unix = ?2 WHERE name = ?1 AND revoked_unix IS NULL";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(name).bind(revoked_unix).step();
  if (rc != SQLITE_DONE) return impl_->error(fmt::format("revoking credential '{}'", name), rc);
  return sqlite3_changes64(impl_->db) == 1;
}

Result<std::vector<StoredCredential>> Store::list_credentials() {
  static const std::string kSql = fmt::format("{}ORDER BY name", kSelectCredentials);
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  std::vector<StoredCredential> out;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) out.push_back(read_credential(q.value().get()));
  if (rc != SQLITE_DONE) return impl_->error("listing credentials", rc);
  return out;
}

Status Store::insert_join_code(const StoredJoinCode& code) {
  constexpr std::string_view kSql =
      "INSERT INTO join_codes(secret_sha256, name_hint, created_unix, expires_unix, used_unix, used_by) "
      "VALUES (?1, ?2, ?3, ?4, ?5, ?6)";
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  const int rc = q.value()
                     .bind_blob(code.secret_sha256)
                     .bind_optional(code.name_hint)
                     .bind(code.created_unix)
                     .bind(code.expires_unix)
                     .bind_optional(code.used_unix)
                     .bind_optional(code.used_by)
                     .step();
  if (rc != SQLITE_DONE) return impl_->error("storing a join code", rc);
  return {};
}

Result<std::optional<StoredJoinCode>> Store::Impl::find_join_code(std::span<const std::uint8_t> secret_sha256) {
  static const std::string kSql = fmt::format("{}WHERE secret_sha256 = ?1", kSelectJoinCodes);
  auto q = query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind_blob(secret_sha256).step();
  if (rc == SQLITE_DONE) return std::optional<StoredJoinCode>();
  if (rc != SQLITE_ROW) return error("reading a join code", rc);
  return std::optional<StoredJoinCode>(read_join_code(q.value().get()));
}

Result<std::optional<StoredJoinCode>> Store::get_join_code(std::span<const std::uint8_t> secret_sha256) {
  return impl_->find_join_code(secret_sha256);
}

Result<std::vector<StoredJoinCode>> Store::list_join_codes() {
  static const std::string kSql = fmt::format("{}ORDER BY created_unix, secret_sha256", kSelectJoinCodes);
  auto q = impl_->query(kSql);
  if (!q) return q.error();
  std::vector<StoredJoinCode> out;
  int rc;
  while ((rc = q.value().step()) == SQLITE_ROW) out.push_back(read_join_code(q.value().get()));
  if (rc != SQLITE_DONE) return impl_->error("listing join codes", rc);
  return out;
}

Result<bool> Store::Impl::name_taken(std::string_view name) {
  constexpr std::string_view kSql = "SELECT 1 FROM credentials WHERE name = ?1";
  auto q = query(kSql);
  if (!q) return q.error();
  const int rc = q.value().bind(name).step();
  if (rc == SQLITE_ROW) return true;
  if (rc != SQLITE_DONE) return error("looking up a credential name", rc);
  return false;
}

Result<Enrollment> Store::enroll(std::span<const std::uint8_t> secret_sha256, std::string_view base,
                                 std::string_view role, std::span<const std::uint8_t> token_sha256,
                                 std::int64_t now_unix) {
  Enrollment result;
  const Status st = transaction([&]() -> Status {
    auto found = impl_->find_join_code(secret_sha256);
    if (!found) return found.error();
    result.code = std::move(found).value();
    if (!result.code) {
      result.outcome = EnrollOutcome::kUnknown;
      return {};
    }
    if (result.code->used_unix) {
      result.outcome = EnrollOutcome::kUsed;
      return {};
    }
    if (result.code->expires_unix <= now_unix) {
      result.outcome = EnrollOutcome::kExpired;
      return {};
    }
    std::string name;
    for (int n = 1; n <= kMaxEnrollNameTries; ++n) {
      std::string candidate = n == 1 ? std::string(base) : fmt::format("{}-{}", base, n);
      auto taken = impl_->name_taken(candidate);
      if (!taken) return taken.error();
      if (!taken.value()) {
        name = std::move(candidate);
        break;
      }
    }
    if (name.empty()) {
      result.outcome = EnrollOutcome::kNoName;
      return {};
    }
    StoredCredential credential{name, std::string(role), Blob(token_sha256.begin(), token_sha256.end()), now_unix,
                                std::nullopt};
    auto inserted = insert_credential(credential);
    if (!inserted) return inserted.error();
    if (!inserted.value()) return Error{fmt::format("{}: a credential with this token exists", impl_->path)};
    constexpr std::string_view kUse =
        "UPDATE join_codes SET used_unix = ?2, used_by = ?3 WHERE secret_sha256 = ?1 AND used_unix IS NULL";
    auto q = impl_->query(kUse);
    if (!q) return q.error();
    const int rc = q.value().bind_blob(secret_sha256).bind(now_unix).bind(std::string_view(name)).step();
    if (rc != SQLITE_DONE) return impl_->error("marking a join code used", rc);
    if (sqlite3_changes64(impl_->db) != 1)
      return Error{fmt::format("{}: the join code changed meanwhile", impl_->path)};
    result.outcome = EnrollOutcome::kEnrolled;
    result.name = std::move(name);
    return {};
  });
  if (!st) return st.error();
  return result;
}

}  // namespace dtraced::store
