// Tests for the store's credentials and join codes (schema version 3): what is stored survives a
// reopen, a revoked credential stays revoked, a join code enrolls once, and a version 2 database
// gets the two tables in place.
#include <cstdint>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "store_testing.h"

namespace {
using namespace dtraced::testing;
using dtraced::store::EnrollOutcome;
using dtraced::store::StoredCredential;
using dtraced::store::StoredJoinCode;

Blob digest_of(std::uint8_t fill) { return Blob(32, fill); }

StoredCredential credential(std::string name, std::string role, std::uint8_t fill) {
  return StoredCredential{std::move(name), std::move(role), digest_of(fill), 1000, std::nullopt};
}

StoredJoinCode join_code(std::uint8_t fill, std::int64_t expires, std::optional<std::string> hint = std::nullopt) {
  StoredJoinCode c;
  c.secret_sha256 = digest_of(fill);
  c.name_hint = std::move(hint);
  c.created_unix = 1000;
  c.expires_unix = expires;
  return c;
}

}  // namespace

TEST_CASE("credentials are stored once and listed by name and survive a reopen and revoked stays revoked", "[store]") {
  StoreDir tmp;
  {
    Store s = open_ok(tmp.path());
    CHECK(s.insert_credential(credential("w1", "worker", 1)).value());
    CHECK(s.insert_credential(credential("alice", "client", 2)).value());
    // The same name, or the same token digest, changes nothing.
    CHECK_FALSE(s.insert_credential(credential("w1", "viewer", 3)).value());
    CHECK_FALSE(s.insert_credential(credential("bob", "viewer", 2)).value());
    // An unknown role is no credential.
    CHECK_FALSE(s.insert_credential(credential("eve", "operator", 4)).ok());
    CHECK(s.revoke_credential("w1", 2000).value());
    CHECK_FALSE(s.revoke_credential("w1", 3000).value());  // the first revocation time stays
    CHECK_FALSE(s.revoke_credential("nobody", 3000).value());
  }
  Store s = open_ok(tmp.path());
  const std::vector<StoredCredential> all = s.list_credentials().value();
  REQUIRE(all.size() == 2);
  CHECK(all[0] == credential("alice", "client", 2));
  StoredCredential w1 = credential("w1", "worker", 1);
  w1.revoked_unix = 2000;
  CHECK(all[1] == w1);
}

TEST_CASE("a join code enrolls once in one transaction and used or expired or unknown codes change nothing",
          "[store]") {
  StoreDir tmp;
  {
    Store s = open_ok(tmp.path());
    require_ok(s.insert_join_code(join_code(1, 5000, "render")));
    require_ok(s.insert_join_code(join_code(2, 5000)));
    require_ok(s.insert_join_code(join_code(3, 1500)));
    CHECK_FALSE(s.insert_join_code(join_code(1, 9000)).ok());  // the digest exists
    REQUIRE(s.insert_credential(credential("render", "worker", 9)).value());

    const Blob token_a = digest_of(0xa1);
    auto first = s.enroll(digest_of(1), "render", "worker", token_a, 2000);
    REQUIRE(first.ok());
    CHECK(first.value().outcome == EnrollOutcome::kEnrolled);
    CHECK(first.value().name == "render-2");  // "render" is taken

    auto again = s.enroll(digest_of(1), "render", "worker", digest_of(0xa2), 2001);
    REQUIRE(again.ok());
    CHECK(again.value().outcome == EnrollOutcome::kUsed);
    REQUIRE(again.value().code.has_value());
    CHECK(again.value().code->used_by == std::optional<std::string>("render-2"));
    CHECK(again.value().code->used_unix == std::optional<std::int64_t>(2000));

    auto expired = s.enroll(digest_of(3), "x", "worker", digest_of(0xa3), 1500);
    REQUIRE(expired.ok());
    CHECK(expired.value().outcome == EnrollOutcome::kExpired);
    auto unknown = s.enroll(digest_of(7), "x", "worker", digest_of(0xa4), 2000);
    REQUIRE(unknown.ok());
    CHECK(unknown.value().outcome == EnrollOutcome::kUnknown);

    // A token digest in use fails the whole transaction: the code stays unused.
    auto clash = s.enroll(digest_of(2), "other", "worker", token_a, 2000);
    CHECK_FALSE(clash.ok());
    CHECK_FALSE(s.get_join_code(digest_of(2)).value()->used_unix.has_value());
  }
  Store s = open_ok(tmp.path());
  const auto creds = s.list_credentials().value();
  REQUIRE(creds.size() == 2);  // render, render-2: no credential of a refused attempt
  CHECK(creds[1].name == "render-2");
  CHECK(creds[1].token_sha256 == digest_of(0xa1));
  CHECK(creds[1].created_unix == 2000);
  const auto codes = s.list_join_codes().value();
  REQUIRE(codes.size() == 3);
  CHECK(s.get_join_code(digest_of(1)).value()->used_by == std::optional<std::string>("render-2"));
  CHECK(s.get_join_code(digest_of(1)).value()->name_hint == std::optional<std::string>("render"));
  CHECK_FALSE(s.get_join_code(digest_of(3)).value()->used_unix.has_value());
}

TEST_CASE("a version 2 database gets the credential tables in place and keeps its jobs", "[store]") {
  StoreDir tmp;
  {
    Store s = open_ok(tmp.path());
    make_job(s);
  }
  raw_exec(tmp.db(),
           "DROP TABLE credentials; DROP TABLE join_codes; DROP TABLE pixel_files; "
           "ALTER TABLE tiles DROP COLUMN pixels_offset; ALTER TABLE tiles DROP COLUMN pixels_length; "
           "ALTER TABLE tiles DROP COLUMN pixels_crc; UPDATE meta SET value = 2 WHERE key = 'schema_version'");
  {
    Store s = open_ok(tmp.path());
    CHECK(s.list_jobs().value().size() == 1);
    CHECK(s.insert_credential(credential("w", "worker", 1)).value());
  }
  CHECK(raw_query_text(tmp.db(), "SELECT value FROM meta WHERE key = 'schema_version'") == "4");
  // A version 3 file without them is refused, naming the table.
  raw_exec(tmp.db(), "DROP TABLE join_codes");
  CHECK_THAT(open_error(tmp.path()), Contains("join_codes"));
}
