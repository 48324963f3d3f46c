// dtraced::tls material: the keys and certificates of the collector's private CA and of the
// certificates it issues, as PEM text, built and checked with OpenSSL 3.
//
// Owns: EC P-256 key generation, X.509 v3 certificate building (subject CN, subjectAltName DNS
// and IP names, basicConstraints, keyUsage, extendedKeyUsage, key identifiers), signing with
// SHA-256, the SHA-256 fingerprint of a certificate's DER bytes (what join codes carry), and the
// files of the collector's CA in <state_dir>/tls: ca.pem (0644) and ca.key (0600), created on
// first use, written atomically (temporary file, fsync, rename, fsync of the directory).
//
// Nothing here trusts its input: PEM text from files is parsed, a key must match its certificate,
// a CA must say it is one. Failures come back as util::Error naming the file (when there is one)
// and the problem, with OpenSSL's reason where it gave one.
//
// Thread safety: stateless free functions (OpenSSL 3 is thread-safe for these calls).
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include "util/result.h"

namespace dtraced::tls {

// One certificate (possibly followed by its chain, leaf first) and the private key of the first
// one, both PEM.
struct KeyPair {
  std::string cert_pem;
  std::string key_pem;
};

// SHA-256 of a certificate's DER encoding.
using Fingerprint = std::array<std::uint8_t, 32>;

// The fingerprint of the first certificate in `cert_pem`.
util::Result<Fingerprint> fingerprint_of_pem(std::string_view cert_pem);

// OpenSSL's queued error reasons, oldest first, joined with "; " ("no reason given" when the
// queue is empty); the queue is left empty. Not a secret: safe to log.
std::string openssl_reason();
// 64 lower-case hex digits.
std::string fingerprint_hex(const Fingerprint& fingerprint);

// What a certificate says. Names must be non-empty and free of control characters and commas;
// IP addresses are IPv4 or IPv6 literals; not_after_unix must be after not_before_unix.
struct CertSpec {
  std::string common_name;
  std::vector<std::string> dns_names;     // subjectAltName DNS
  std::vector<std::string> ip_addresses;  // subjectAltName IP ("127.0.0.1", "::1")
  std::int64_t not_before_unix = 0;       // validity; tests make expired certificates with these
  std::int64_t not_after_unix = 0;
  bool is_ca = false;  // basicConstraints CA:TRUE, keyUsage keyCertSign and cRLSign
  bool server = true;  // extendedKeyUsage serverAuth (false: clientAuth); ignored for a CA
};

// A self-signed CA certificate for `spec` (is_ca forced on) with a new P-256 key.
util::Result<KeyPair> make_self_signed_ca(const CertSpec& spec);

// A certificate for `spec` with a new P-256 key, signed by `ca` (whose certificate must be a CA
// and whose key must match it). `spec.is_ca` issues an intermediate CA.
util::Result<KeyPair> issue(const KeyPair& ca, const CertSpec& spec);

// Validity of the collector's CA and of the server certificates it issues.
inline constexpr std::int64_t kCaValidityDays = 3650;
inline constexpr std::int64_t kServerCertValidityDays = 825;
// Certificates start this long before "now", so a peer whose clock is a little behind accepts them.
inline constexpr std::int64_t kBackdateSeconds = 3600;

// The collector's private CA in <state_dir>/tls: loaded when ca.pem and ca.key are both there
// (the key must match, the certificate must be a CA and not expired at `now_unix`), created when
// neither is (directory 0700, key 0600, certificate 0644). One without the other is an error: the
// operator decides whether to restore the missing file or remove the other.
util::Result<KeyPair> load_or_create_authority(const std::string& state_dir, std::int64_t now_unix);

// The spec of the server certificate: names "localhost", 127.0.0.1, ::1, the host name
// (gethostname), every address of every interface (getifaddrs) when `listen_address` is a
// wildcard ("", "0.0.0.0", "::"), else `listen_address` itself; plus `extra` (DNS names or IP
// literals, from --tls-name). Duplicates are dropped. Valid from now_unix - kBackdateSeconds for
// kServerCertValidityDays.
CertSpec server_cert_spec(std::string_view listen_address, const std::vector<std::string>& extra,
                          std::int64_t now_unix);

// Loads a certificate (chain) and its key from two PEM files and checks that the key matches the
// first certificate. Files over 1 MiB are refused.
util::Result<KeyPair> load_key_pair(const std::string& cert_file, const std::string& key_file);

// Checks PEM text already in memory the same way; `what` names its source in errors.
util::Result<KeyPair> check_key_pair(KeyPair pair, std::string_view what);

// Writes `bytes` to `path` with permission bits `mode` (e.g. 0600), atomically: a temporary file
// in the same directory created with that mode, written, fsynced, renamed over `path`, and the
// directory fsynced. Used for keys and credentials.
util::Result<void> write_private_file(const std::string& path, std::string_view bytes, unsigned mode);

}  // namespace dtraced::tls
