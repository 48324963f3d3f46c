// dtraced::tls: the CA and the certificates it issues (checked with OpenSSL's own verifier, not
// with our code), the CA files in a state directory, key pairs from files, join codes and tokens.
#include <sys/stat.h>

#include <algorithm>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <openssl/bio.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include "temp_dir.h"
#include "tls/join_code.h"
#include "tls/material.h"

using namespace dtraced::tls;
using dtraced::testing::TempDir;

namespace {

constexpr std::int64_t kNow = 1'800'000'000;

struct X509Free {
  void operator()(X509* p) const { X509_free(p); }
};
using X509Ptr = std::unique_ptr<X509, X509Free>;

X509Ptr read_cert(const std::string& pem) {
  BIO* bio = BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size()));
  X509Ptr cert(PEM_read_bio_X509(bio, nullptr, nullptr, nullptr));
  BIO_free(bio);
  REQUIRE(cert);
  return cert;
}

CertSpec spec_for(std::string cn, std::int64_t from, std::int64_t to, bool server = true) {
  CertSpec spec;
  spec.common_name = std::move(cn);
  spec.not_before_unix = from;
  spec.not_after_unix = to;
  spec.server = server;
  return spec;
}

KeyPair test_ca() {
  auto ca = make_self_signed_ca(spec_for("test CA", kNow - 3600, kNow + 86'400 * 365));
  REQUIRE(ca.ok());
  return *ca;
}

// OpenSSL's verdict on `leaf` against `ca` at `at_unix`, for `purpose` (X509_PURPOSE_SSL_SERVER
// or _CLIENT): X509_V_OK or the error.
int verify(const KeyPair& ca, const std::string& leaf_pem, std::int64_t at_unix, int purpose) {
  X509Ptr root = read_cert(ca.cert_pem);
  X509Ptr leaf = read_cert(leaf_pem);
  X509_STORE* store = X509_STORE_new();
  X509_STORE_add_cert(store, root.get());
  X509_STORE_CTX* ctx = X509_STORE_CTX_new();
  X509_STORE_CTX_init(ctx, store, leaf.get(), nullptr);
  X509_STORE_CTX_set_time(ctx, 0, static_cast<time_t>(at_unix));
  X509_STORE_CTX_set_purpose(ctx, purpose);
  const int ok = X509_verify_cert(ctx);
  const int error = X509_STORE_CTX_get_error(ctx);
  X509_STORE_CTX_free(ctx);
  X509_STORE_free(store);
  return ok == 1 ? X509_V_OK : (error == X509_V_OK ? -1 : error);
}

unsigned mode_of(const std::string& path) {
  struct stat st {};
  REQUIRE(::stat(path.c_str(), &st) == 0);
  return st.st_mode & 07777;
}

void write_text(const std::string& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
  REQUIRE(out.good());
}

}  // namespace

TEST_CASE("tls: the collector's CA is created once, then loaded with the same fingerprint", "[tls]") {
  TempDir dir;
  auto first = load_or_create_authority(dir.str(), kNow);
  REQUIRE(first.ok());
  const std::string cert_file = dir.str() + "/tls/ca.pem";
  const std::string key_file = dir.str() + "/tls/ca.key";
  CHECK(mode_of(dir.str() + "/tls") == 0700);
  CHECK(mode_of(key_file) == 0600);
  CHECK(mode_of(cert_file) == 0644);

  auto again = load_or_create_authority(dir.str(), kNow + 60);
  REQUIRE(again.ok());
  CHECK(again->cert_pem == first->cert_pem);
  auto fp1 = fingerprint_of_pem(first->cert_pem);
  auto fp2 = fingerprint_of_pem(again->cert_pem);
  REQUIRE(fp1.ok());
  REQUIRE(fp2.ok());
  CHECK(*fp1 == *fp2);
  CHECK(fingerprint_hex(*fp1).size() == 64);
  CHECK(fingerprint_hex(*fp1).find_first_not_of("0123456789abcdef") == std::string::npos);

  // The fingerprint is SHA-256 of the DER bytes, as `openssl x509 -fingerprint -sha256` says.
  X509Ptr cert = read_cert(first->cert_pem);
  std::array<unsigned char, EVP_MAX_MD_SIZE> md{};
  unsigned int len = 0;
  REQUIRE(X509_digest(cert.get(), EVP_sha256(), md.data(), &len) == 1);
  REQUIRE(len == 32);
  CHECK(std::equal(fp1->begin(), fp1->end(), md.begin()));
  CHECK(X509_check_ca(cert.get()) != 0);
}

TEST_CASE("tls: a half-present, mismatched or expired CA is refused, naming the file", "[tls]") {
  TempDir dir;
  REQUIRE(load_or_create_authority(dir.str(), kNow).ok());
  const std::string cert_file = dir.str() + "/tls/ca.pem";
  const std::string key_file = dir.str() + "/tls/ca.key";

  SECTION("key without certificate") {
    REQUIRE(std::remove(cert_file.c_str()) == 0);
    auto r = load_or_create_authority(dir.str(), kNow);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error().file == cert_file);
    CHECK_THAT(r.error().message, Catch::Contains("missing"));
  }
  SECTION("key from another CA") {
    write_text(key_file, test_ca().key_pem);
    auto r = load_or_create_authority(dir.str(), kNow);
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().to_string(), Catch::Contains("does not match"));
    CHECK_THAT(r.error().to_string(), Catch::Contains(key_file));
  }
  SECTION("a leaf certificate where the CA should be") {
    const KeyPair leaf = *issue(test_ca(), spec_for("leaf", kNow - 10, kNow + 1000));
    write_text(cert_file, leaf.cert_pem);
    write_text(key_file, leaf.key_pem);
    auto r = load_or_create_authority(dir.str(), kNow);
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Catch::Contains("not a CA"));
    CHECK(r.error().file == cert_file);
  }
  SECTION("expired") {
    auto r = load_or_create_authority(dir.str(), kNow + 86'400 * (kCaValidityDays + 1));
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Catch::Contains("expired"));
  }
  SECTION("garbage") {
    write_text(cert_file, "not a certificate\n");
    auto r = load_or_create_authority(dir.str(), kNow);
    REQUIRE_FALSE(r.ok());
    CHECK(r.error().file == cert_file);
    CHECK_THAT(r.error().message, Catch::Contains("no readable PEM certificate"));
  }
}

TEST_CASE("tls: load_key_pair refuses a key that does not match its certificate", "[tls]") {
  TempDir dir;
  const KeyPair a = test_ca();
  const KeyPair b = test_ca();
  write_text(dir.str() + "/a.pem", a.cert_pem);
  write_text(dir.str() + "/a.key", a.key_pem);
  write_text(dir.str() + "/b.key", b.key_pem);

  auto good = load_key_pair(dir.str() + "/a.pem", dir.str() + "/a.key");
  REQUIRE(good.ok());
  CHECK(good->cert_pem == a.cert_pem);

  auto bad = load_key_pair(dir.str() + "/a.pem", dir.str() + "/b.key");
  REQUIRE_FALSE(bad.ok());
  CHECK_THAT(bad.error().to_string(), Catch::Contains("does not match"));
  CHECK_THAT(bad.error().to_string(), Catch::Contains("b.key"));

  auto missing = load_key_pair(dir.str() + "/nope.pem", dir.str() + "/a.key");
  REQUIRE_FALSE(missing.ok());
  CHECK(missing.error().file == dir.str() + "/nope.pem");

  auto mixed = check_key_pair(KeyPair{a.cert_pem, b.key_pem}, "memory");
  REQUIRE_FALSE(mixed.ok());
  CHECK_THAT(mixed.error().to_string(), Catch::Contains("does not match"));

  // issue() also refuses a CA whose key is not its own.
  CertSpec leaf = spec_for("leaf", kNow, kNow + 100);
  auto refused = issue(KeyPair{a.cert_pem, b.key_pem}, leaf);
  REQUIRE_FALSE(refused.ok());
  CHECK_THAT(refused.error().message, Catch::Contains("does not match"));
}

TEST_CASE("tls: an issued server certificate verifies against its CA and names its SANs", "[tls]") {
  const KeyPair ca = test_ca();
  CertSpec spec = spec_for("collector.example", kNow - 60, kNow + 86'400);
  spec.dns_names = {"collector.example", "localhost"};
  spec.ip_addresses = {"127.0.0.1", "::1", "192.0.2.7"};
  auto server = issue(ca, spec);
  REQUIRE(server.ok());
  REQUIRE(check_key_pair(*server, "issued").ok());

  CHECK(verify(ca, server->cert_pem, kNow, X509_PURPOSE_SSL_SERVER) == X509_V_OK);
  // A server certificate is not a client certificate.
  CHECK(verify(ca, server->cert_pem, kNow, X509_PURPOSE_SSL_CLIENT) != X509_V_OK);
  // Another CA does not vouch for it.
  CHECK(verify(test_ca(), server->cert_pem, kNow, X509_PURPOSE_SSL_SERVER) != X509_V_OK);

  X509Ptr cert = read_cert(server->cert_pem);
  CHECK(X509_check_ca(cert.get()) == 0);
  CHECK(X509_check_host(cert.get(), "collector.example", 0, 0, nullptr) == 1);
  CHECK(X509_check_host(cert.get(), "localhost", 0, 0, nullptr) == 1);
  CHECK(X509_check_host(cert.get(), "other.example", 0, 0, nullptr) == 0);
  CHECK(X509_check_ip_asc(cert.get(), "127.0.0.1", 0) == 1);
  CHECK(X509_check_ip_asc(cert.get(), "::1", 0) == 1);
  CHECK(X509_check_ip_asc(cert.get(), "192.0.2.7", 0) == 1);
  CHECK(X509_check_ip_asc(cert.get(), "192.0.2.8", 0) == 0);

  // A client certificate verifies for the client purpose.
  auto client = issue(ca, spec_for("worker-1", kNow - 60, kNow + 86'400, /*server=*/false));
  REQUIRE(client.ok());
  CHECK(verify(ca, client->cert_pem, kNow, X509_PURPOSE_SSL_CLIENT) == X509_V_OK);
}

TEST_CASE("tls: a certificate past its validity fails verification", "[tls]") {
  const KeyPair ca = test_ca();
  auto expired = issue(ca, spec_for("old", kNow - 7200, kNow - 3600));
  REQUIRE(expired.ok());
  CHECK(verify(ca, expired->cert_pem, kNow, X509_PURPOSE_SSL_SERVER) == X509_V_ERR_CERT_HAS_EXPIRED);
  auto future = issue(ca, spec_for("new", kNow + 3600, kNow + 7200));
  REQUIRE(future.ok());
  CHECK(verify(ca, future->cert_pem, kNow, X509_PURPOSE_SSL_SERVER) == X509_V_ERR_CERT_NOT_YET_VALID);
}

TEST_CASE("tls: malformed certificate specs are refused", "[tls]") {
  const KeyPair ca = test_ca();
  CertSpec spec = spec_for("x", kNow, kNow + 10);
  SECTION("empty name") {
    spec.common_name.clear();
    CHECK(issue(ca, spec).error().path == "common_name");
  }
  SECTION("bad IP") {
    spec.ip_addresses = {"300.1.1.1"};
    CHECK(issue(ca, spec).error().path == "ip_addresses");
  }
  SECTION("DNS name with a comma") {
    spec.dns_names = {"a,b"};
    CHECK(issue(ca, spec).error().path == "dns_names");
  }
  SECTION("ends before it starts") {
    spec.not_after_unix = spec.not_before_unix;
    CHECK(make_self_signed_ca(spec).error().path == "not_after_unix");
  }
}

TEST_CASE("tls: server_cert_spec names loopback, the host and the listen address", "[tls]") {
  const CertSpec one = server_cert_spec("192.0.2.9", {"collector.example", "198.51.100.1"}, kNow);
  CHECK_THAT(one.dns_names, Catch::VectorContains(std::string("localhost")));
  CHECK_THAT(one.dns_names, Catch::VectorContains(std::string("collector.example")));
  CHECK_THAT(one.ip_addresses, Catch::VectorContains(std::string("127.0.0.1")));
  CHECK_THAT(one.ip_addresses, Catch::VectorContains(std::string("::1")));
  CHECK_THAT(one.ip_addresses, Catch::VectorContains(std::string("192.0.2.9")));
  CHECK_THAT(one.ip_addresses, Catch::VectorContains(std::string("198.51.100.1")));
  CHECK_FALSE(one.is_ca);
  CHECK(one.server);
  CHECK(one.not_after_unix - one.not_before_unix == kServerCertValidityDays * 86'400 + kBackdateSeconds);

  // A wildcard listens on every interface: loopback is among them, once.
  const CertSpec any = server_cert_spec("0.0.0.0", {}, kNow);
  CHECK(std::count(any.ip_addresses.begin(), any.ip_addresses.end(), "127.0.0.1") == 1);
  // And the spec is one issue() takes.
  CHECK(issue(test_ca(), any).ok());
}

TEST_CASE("tls: write_private_file replaces a file atomically with the mode asked for", "[tls]") {
  TempDir dir;
  const std::string path = dir.str() + "/secret";
  REQUIRE(write_private_file(path, "one", 0600).ok());
  CHECK(mode_of(path) == 0600);
  REQUIRE(write_private_file(path, "two", 0644).ok());
  CHECK(mode_of(path) == 0644);
  std::ifstream in(path);
  std::string text;
  in >> text;
  CHECK(text == "two");
  // No temporary file left behind.
  CHECK(std::distance(std::filesystem::directory_iterator(dir.path()), std::filesystem::directory_iterator()) == 1);
  auto r = write_private_file(dir.str() + "/missing/secret", "x", 0600);
  REQUIRE_FALSE(r.ok());
  CHECK(r.error().file == dir.str() + "/missing/secret");
}

TEST_CASE("tls: join codes round-trip", "[tls]") {
  const Fingerprint fp = *fingerprint_of_pem(test_ca().cert_pem);
  const JoinCode with = make_join_code(fp);
  const std::string text = format_join_code(with);
  CHECK(text.starts_with("dtj1."));
  CHECK(text.size() == 5 + 22 + 1 + 43);
  auto parsed = parse_join_code(text);
  REQUIRE(parsed.ok());
  CHECK(*parsed == with);
  // Pasted with a newline.
  CHECK(parse_join_code("  " + text + "\n").ok());

  const JoinCode without = make_join_code(std::nullopt);
  const std::string plain = format_join_code(without);
  CHECK(plain.back() == '.');
  auto back = parse_join_code(plain);
  REQUIRE(back.ok());
  CHECK(*back == without);
  CHECK_FALSE(back->ca.has_value());
  // Two codes differ.
  CHECK(make_join_code(std::nullopt).secret != without.secret);
}

TEST_CASE("tls: malformed join codes are refused with a message saying why", "[tls]") {
  const std::string good = format_join_code(make_join_code(*fingerprint_of_pem(test_ca().cert_pem)));
  const std::string secret = good.substr(5, 22);
  const std::string fp = good.substr(5 + 23);
  struct Case {
    std::string code;
    std::string says;
  };
  const std::vector<Case> cases = {
      {"", "empty"},
      {"dtj2." + secret + "." + fp, "starts with"},
      {"dtj1." + secret, "no fingerprint part"},
      {"dtj1." + secret + "." + fp + ".x", "too many parts"},
      {"dtj1." + secret.substr(1) + "." + fp, "secret has 21 characters"},
      {"dtj1." + secret + "." + fp.substr(2), "CA fingerprint has 41 characters"},
      {"dtj1." + secret.substr(0, 21) + "+." + fp, "not a base64url character"},
      {"dtj1." + secret.substr(0, 21) + "=." + fp, "not a base64url character"},
      // 16 bytes leave 4 unused bits in the last character: 'B' sets one of them.
      {"dtj1." + secret.substr(0, 21) + "B." + fp, "not valid base64url"},
  };
  for (const Case& c : cases) {
    INFO(c.code);
    auto r = parse_join_code(c.code);
    REQUIRE_FALSE(r.ok());
    CHECK_THAT(r.error().message, Catch::Contains(c.says));
  }
}

TEST_CASE("tls: random tokens are 43 base64url characters and differ", "[tls]") {
  const std::string a = random_token();
  const std::string b = random_token();
  CHECK(a.size() == 43);
  CHECK(a.find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_") == std::string::npos);
  CHECK(a != b);
  auto raw = base64url_decode(a);
  REQUIRE(raw.has_value());
  CHECK(raw->size() == 32);
  CHECK(base64url_encode(reinterpret_cast<const std::uint8_t*>(raw->data()), raw->size()) == a);
  // RFC 4648 test vectors, without padding.
  const std::string foobar = "foobar";
  const auto* bytes = reinterpret_cast<const std::uint8_t*>(foobar.data());
  CHECK(base64url_encode(bytes, 1) == "Zg");
  CHECK(base64url_encode(bytes, 2) == "Zm8");
  CHECK(base64url_encode(bytes, 3) == "Zm9v");
  CHECK(base64url_encode(bytes, 6) == "Zm9vYmFy");
  CHECK(base64url_decode("Zm9vYg") == std::optional<std::string>("foob"));
  CHECK_FALSE(base64url_decode("Zm9vY").has_value());
}
