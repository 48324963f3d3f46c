#include "tls/material.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <filesystem>
#include <memory>
#include <utility>

#include <fmt/format.h>
#include <openssl/asn1.h>
#include <openssl/bio.h>
#include <openssl/bn.h>
#include <openssl/err.h>
#include <openssl/evp.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>

#include "util/file.h"

namespace dtraced::tls {
namespace {

constexpr std::uint64_t kMaxPemFileBytes = 1 << 20;
constexpr std::int64_t kSecondsPerDay = 86'400;
constexpr int kSerialBits = 127;  // positive, and under the 20 octets RFC 5280 allows

struct BioFree {
  void operator()(BIO* p) const { BIO_free(p); }
};
struct X509Free {
  void operator()(X509* p) const { X509_free(p); }
};
struct PkeyFree {
  void operator()(EVP_PKEY* p) const { EVP_PKEY_free(p); }
};
struct ExtFree {
  void operator()(X509_EXTENSION* p) const { X509_EXTENSION_free(p); }
};
struct NamesFree {
  void operator()(GENERAL_NAMES* p) const { GENERAL_NAMES_free(p); }
};
struct BnFree {
  void operator()(BIGNUM* p) const { BN_free(p); }
};
using BioPtr = std::unique_ptr<BIO, BioFree>;
using X509Ptr = std::unique_ptr<X509, X509Free>;
using PkeyPtr = std::unique_ptr<EVP_PKEY, PkeyFree>;
using ExtPtr = std::unique_ptr<X509_EXTENSION, ExtFree>;
using NamesPtr = std::unique_ptr<GENERAL_NAMES, NamesFree>;
using BnPtr = std::unique_ptr<BIGNUM, BnFree>;

util::Error failure(std::string_view what, std::string_view file = {}) {
  return util::Error(fmt::format("{} ({})", what, openssl_reason()), "", std::string(file));
}

BioPtr memory_bio(std::string_view text) { return BioPtr(BIO_new_mem_buf(text.data(), static_cast<int>(text.size()))); }

util::Result<X509Ptr> parse_cert(std::string_view pem, std::string_view what) {
  ERR_clear_error();
  BioPtr bio = memory_bio(pem);
  X509Ptr cert(bio ? PEM_read_bio_X509(bio.get(), nullptr, nullptr, nullptr) : nullptr);
  if (!cert) return failure("holds no readable PEM certificate", what);
  return cert;
}

util::Result<PkeyPtr> parse_key(std::string_view pem, std::string_view what) {
  ERR_clear_error();
  BioPtr bio = memory_bio(pem);
  PkeyPtr key(bio ? PEM_read_bio_PrivateKey(bio.get(), nullptr, nullptr, nullptr) : nullptr);
  if (!key) return failure("holds no readable PEM private key (an encrypted key is not supported)", what);
  return key;
}

std::string bio_text(BIO* bio) {
  char* data = nullptr;
  const long n = BIO_get_mem_data(bio, &data);
  return n > 0 ? std::string(data, static_cast<std::size_t>(n)) : std::string();
}

std::string cert_pem(X509* cert) {
  BioPtr bio(BIO_new(BIO_s_mem()));
  if (!bio || PEM_write_bio_X509(bio.get(), cert) != 1) return {};
  return bio_text(bio.get());
}

std::string key_pem(EVP_PKEY* key) {
  BioPtr bio(BIO_new(BIO_s_mem()));
  if (!bio || PEM_write_bio_PrivateKey(bio.get(), key, nullptr, nullptr, 0, nullptr, nullptr) != 1) return {};
  return bio_text(bio.get());
}

util::Result<PkeyPtr> new_p256_key() {
  ERR_clear_error();
  PkeyPtr key(EVP_EC_gen("P-256"));
  if (!key) return failure("cannot generate a P-256 key");
  return key;
}

bool has_control_or_comma(std::string_view s) {
  return std::any_of(s.begin(), s.end(), [](char c) {
    const auto u = static_cast<unsigned char>(c);
    return u < 0x20 || u == 0x7f || c == ',';
  });
}

bool is_ip_literal(const std::string& s) {
  in6_addr scratch{};
  return ::inet_pton(AF_INET, s.c_str(), &scratch) == 1 || ::inet_pton(AF_INET6, s.c_str(), &scratch) == 1;
}

util::Result<void> check_spec(const CertSpec& spec) {
  if (spec.common_name.empty() || spec.common_name.size() > 64 || has_control_or_comma(spec.common_name)) {
    return util::Error("the common name must be 1 to 64 characters without control characters or commas",
                       "common_name");
  }
  for (const std::string& name : spec.dns_names) {
    if (name.empty() || name.size() > 253 || has_control_or_comma(name) || name.find(' ') != std::string::npos) {
      return util::Error(fmt::format("\"{}\" is not a usable DNS name", name), "dns_names");
    }
  }
  for (const std::string& ip : spec.ip_addresses) {
    if (!is_ip_literal(ip)) return util::Error(fmt::format("\"{}\" is not an IP address", ip), "ip_addresses");
  }
  if (spec.not_after_unix <= spec.not_before_unix) {
    return util::Error("the certificate would end before it starts", "not_after_unix");
  }
  return {};
}

util::Result<void> add_conf_extension(X509* cert, X509V3_CTX* ctx, int nid, const char* value) {
  ExtPtr ext(X509V3_EXT_conf_nid(nullptr, ctx, nid, value));
  if (!ext || X509_add_ext(cert, ext.get(), -1) != 1) {
    return failure(fmt::format("cannot add the extension {} = {}", OBJ_nid2sn(nid), value));
  }
  return {};
}

util::Result<void> add_subject_alt_names(X509* cert, const CertSpec& spec) {
  if (spec.dns_names.empty() && spec.ip_addresses.empty()) return {};
  NamesPtr names(sk_GENERAL_NAME_new_null());
  if (!names) return failure("out of memory for subjectAltName");
  for (const std::string& dns : spec.dns_names) {
    GENERAL_NAME* name = GENERAL_NAME_new();
    ASN1_IA5STRING* text = ASN1_IA5STRING_new();
    if (name == nullptr || text == nullptr || ASN1_STRING_set(text, dns.data(), static_cast<int>(dns.size())) != 1) {
      GENERAL_NAME_free(name);
      ASN1_IA5STRING_free(text);
      return failure(fmt::format("cannot encode the DNS name \"{}\"", dns));
    }
    GENERAL_NAME_set0_value(name, GEN_DNS, text);
    sk_GENERAL_NAME_push(names.get(), name);
  }
  for (const std::string& ip : spec.ip_addresses) {
    ASN1_OCTET_STRING* octets = a2i_IPADDRESS(ip.c_str());
    GENERAL_NAME* name = GENERAL_NAME_new();
    if (octets == nullptr || name == nullptr) {
      ASN1_OCTET_STRING_free(octets);
      GENERAL_NAME_free(name);
      return failure(fmt::format("cannot encode the IP address \"{}\"", ip));
    }
    GENERAL_NAME_set0_value(name, GEN_IPADD, octets);
    sk_GENERAL_NAME_push(names.get(), name);
  }
  if (X509_add1_ext_i2d(cert, NID_subject_alt_name, names.get(), /*crit=*/0, X509V3_ADD_DEFAULT) != 1) {
    return failure("cannot add subjectAltName");
  }
  return {};
}

// Builds and signs a certificate for `spec` and `subject_key`. `issuer` null: self-signed.
util::Result<X509Ptr> build_cert(const CertSpec& spec, EVP_PKEY* subject_key, X509* issuer, EVP_PKEY* issuer_key) {
  if (auto ok = check_spec(spec); !ok) return std::move(ok).error();
  ERR_clear_error();
  X509Ptr cert(X509_new());
  if (!cert || X509_set_version(cert.get(), X509_VERSION_3) != 1) return failure("cannot create a certificate");

  BnPtr serial(BN_new());
  if (!serial || BN_rand(serial.get(), kSerialBits, BN_RAND_TOP_ANY, BN_RAND_BOTTOM_ANY) != 1 ||
      BN_to_ASN1_INTEGER(serial.get(), X509_get_serialNumber(cert.get())) == nullptr) {
    return failure("cannot make a serial number");
  }
  if (ASN1_TIME_set(X509_getm_notBefore(cert.get()), static_cast<time_t>(spec.not_before_unix)) == nullptr ||
      ASN1_TIME_set(X509_getm_notAfter(cert.get()), static_cast<time_t>(spec.not_after_unix)) == nullptr) {
    return failure("cannot set the validity period");
  }
  X509_NAME* subject = X509_get_subject_name(cert.get());
  if (X509_NAME_add_entry_by_txt(subject, "CN", MBSTRING_UTF8,
                                 reinterpret_cast<const unsigned char*>(spec.common_name.data()),
                                 static_cast<int>(spec.common_name.size()), -1, 0) != 1) {
    return failure("cannot set the subject name");
  }
  X509* signer = issuer != nullptr ? issuer : cert.get();
  if (X509_set_issuer_name(cert.get(), X509_get_subject_name(signer)) != 1 ||
      X509_set_pubkey(cert.get(), subject_key) != 1) {
    return failure("cannot set the issuer or the public key");
  }

  X509V3_CTX ctx;
  X509V3_set_ctx(&ctx, signer, cert.get(), nullptr, nullptr, 0);
  const bool ca = spec.is_ca;
  struct Ext {
    int nid;
    const char* value;
  };
  std::vector<Ext> exts = {
      {NID_basic_constraints, ca ? "critical,CA:TRUE" : "critical,CA:FALSE"},
      {NID_key_usage, ca ? "critical,keyCertSign,cRLSign" : "critical,digitalSignature"},
      {NID_subject_key_identifier, "hash"},
      // After the subject key identifier: a self-signed certificate is its own issuer.
      {NID_authority_key_identifier, "keyid:always"},
  };
  if (!ca) exts.push_back({NID_ext_key_usage, spec.server ? "serverAuth" : "clientAuth"});
  for (const Ext& ext : exts) {
    if (auto ok = add_conf_extension(cert.get(), &ctx, ext.nid, ext.value); !ok) return std::move(ok).error();
  }
  if (auto ok = add_subject_alt_names(cert.get(), spec); !ok) return std::move(ok).error();

  if (X509_sign(cert.get(), issuer_key, EVP_sha256()) <= 0) return failure("cannot sign the certificate");
  return cert;
}

util::Result<KeyPair> to_key_pair(X509* cert, EVP_PKEY* key) {
  KeyPair pair{cert_pem(cert), key_pem(key)};
  if (pair.cert_pem.empty() || pair.key_pem.empty()) return failure("cannot write PEM");
  return pair;
}

util::Result<void> write_all(int fd, std::string_view bytes) {
  std::size_t off = 0;
  while (off < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + off, bytes.size() - off);
    if (n < 0) {
      if (errno == EINTR) continue;
      return util::Error(fmt::format("write failed: {}", std::strerror(errno)));
    }
    off += static_cast<std::size_t>(n);
  }
  return {};
}

std::string directory_of(const std::string& path) {
  const auto slash = path.rfind('/');
  if (slash == std::string::npos) return ".";
  return slash == 0 ? "/" : path.substr(0, slash);
}

bool exists(const std::string& path) {
  struct stat st {};
  return ::lstat(path.c_str(), &st) == 0;
}

std::string host_name() {
  std::array<char, 256> buf{};
  if (::gethostname(buf.data(), buf.size() - 1) != 0) return {};
  return std::string(buf.data());
}

// Every address of every interface that is up, as text (no IPv6 zone).
std::vector<std::string> interface_addresses() {
  std::vector<std::string> out;
  ifaddrs* list = nullptr;
  if (::getifaddrs(&list) != 0) return out;
  for (const ifaddrs* it = list; it != nullptr; it = it->ifa_next) {
    if (it->ifa_addr == nullptr) continue;
    std::array<char, INET6_ADDRSTRLEN> text{};
    const void* raw = nullptr;
    if (it->ifa_addr->sa_family == AF_INET) {
      raw = &reinterpret_cast<const sockaddr_in*>(it->ifa_addr)->sin_addr;
    } else if (it->ifa_addr->sa_family == AF_INET6) {
      raw = &reinterpret_cast<const sockaddr_in6*>(it->ifa_addr)->sin6_addr;
    } else {
      continue;
    }
    if (::inet_ntop(it->ifa_addr->sa_family, raw, text.data(), text.size()) != nullptr) out.emplace_back(text.data());
  }
  ::freeifaddrs(list);
  return out;
}

void add_unique(std::vector<std::string>& to, std::string value) {
  if (std::find(to.begin(), to.end(), value) == to.end()) to.push_back(std::move(value));
}

}  // namespace

std::string openssl_reason() {
  std::string out;
  while (const unsigned long code = ERR_get_error()) {
    std::array<char, 256> text{};
    ERR_error_string_n(code, text.data(), text.size());
    if (!out.empty()) out += "; ";
    out += text.data();
  }
  return out.empty() ? std::string("no reason given") : out;
}

util::Result<Fingerprint> fingerprint_of_pem(std::string_view cert_pem_text) {
  auto cert = parse_cert(cert_pem_text, "certificate");
  if (!cert) return std::move(cert).error();
  std::array<unsigned char, EVP_MAX_MD_SIZE> md{};
  unsigned int len = 0;
  if (X509_digest(cert->get(), EVP_sha256(), md.data(), &len) != 1 || len != Fingerprint{}.size()) {
    return failure("cannot compute the SHA-256 fingerprint");
  }
  Fingerprint out{};
  std::copy_n(md.begin(), out.size(), out.begin());
  return out;
}

std::string fingerprint_hex(const Fingerprint& fingerprint) {
  std::string out;
  out.reserve(2 * fingerprint.size());
  for (const std::uint8_t b : fingerprint) out += fmt::format("{:02x}", b);
  return out;
}

util::Result<KeyPair> make_self_signed_ca(const CertSpec& spec) {
  CertSpec ca_spec = spec;
  ca_spec.is_ca = true;
  auto key = new_p256_key();
  if (!key) return std::move(key).error();
  auto cert = build_cert(ca_spec, key->get(), nullptr, key->get());
  if (!cert) return std::move(cert).error();
  return to_key_pair(cert->get(), key->get());
}

util::Result<KeyPair> issue(const KeyPair& ca, const CertSpec& spec) {
  auto ca_cert = parse_cert(ca.cert_pem, "the CA certificate");
  if (!ca_cert) return std::move(ca_cert).error();
  auto ca_key = parse_key(ca.key_pem, "the CA key");
  if (!ca_key) return std::move(ca_key).error();
  if (X509_check_ca(ca_cert->get()) == 0) return util::Error("the issuing certificate is not a CA");
  if (X509_check_private_key(ca_cert->get(), ca_key->get()) != 1) {
    ERR_clear_error();
    return util::Error("the CA key does not match the CA certificate");
  }
  auto key = new_p256_key();
  if (!key) return std::move(key).error();
  auto cert = build_cert(spec, key->get(), ca_cert->get(), ca_key->get());
  if (!cert) return std::move(cert).error();
  return to_key_pair(cert->get(), key->get());
}

util::Result<KeyPair> check_key_pair(KeyPair pair, std::string_view what) {
  auto cert = parse_cert(pair.cert_pem, what);
  if (!cert) return std::move(cert).error();
  auto key = parse_key(pair.key_pem, what);
  if (!key) return std::move(key).error();
  if (X509_check_private_key(cert->get(), key->get()) != 1) {
    ERR_clear_error();
    return util::Error("the private key does not match the certificate", "", std::string(what));
  }
  return pair;
}

util::Result<KeyPair> load_key_pair(const std::string& cert_file, const std::string& key_file) {
  auto cert = util::read_file_limited(cert_file, kMaxPemFileBytes);
  if (!cert) return std::move(cert).error();
  auto key = util::read_file_limited(key_file, kMaxPemFileBytes);
  if (!key) return std::move(key).error();
  if (auto ok = parse_cert(*cert, cert_file); !ok) return std::move(ok).error();
  if (auto ok = parse_key(*key, key_file); !ok) return std::move(ok).error();
  return check_key_pair(KeyPair{std::move(*cert), std::move(*key)}, fmt::format("{} and {}", cert_file, key_file));
}

util::Result<KeyPair> load_or_create_authority(const std::string& state_dir, std::int64_t now_unix) {
  const std::string dir = state_dir + "/tls";
  const std::string cert_file = dir + "/ca.pem";
  const std::string key_file = dir + "/ca.key";
  const bool have_cert = exists(cert_file);
  const bool have_key = exists(key_file);
  if (have_cert != have_key) {
    const std::string& present = have_cert ? cert_file : key_file;
    const std::string& missing = have_cert ? key_file : cert_file;
    return util::Error(fmt::format("{} is missing while {} exists: restore it, or remove {} to create a new CA "
                                   "(workers enrolled with the old CA must then be enrolled again)",
                                   missing, present, present),
                       "", missing);
  }
  if (have_cert) {
    auto pair = load_key_pair(cert_file, key_file);
    if (!pair) return pair;
    auto cert = parse_cert(pair->cert_pem, cert_file);
    if (!cert) return std::move(cert).error();
    if (X509_check_ca(cert->get()) == 0) return util::Error("the certificate is not a CA", "", cert_file);
    const time_t now = static_cast<time_t>(now_unix);
    if (X509_cmp_time(X509_get0_notAfter(cert->get()), const_cast<time_t*>(&now)) <= 0) {
      return util::Error("the CA certificate has expired: remove tls/ca.pem and tls/ca.key to create a new one", "",
                         cert_file);
    }
    return pair;
  }

  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  if (ec) return util::Error(fmt::format("cannot create the directory: {}", ec.message()), "", dir);
  if (::chmod(dir.c_str(), 0700) != 0) {
    return util::Error(fmt::format("cannot set permissions: {}", std::strerror(errno)), "", dir);
  }
  CertSpec spec;
  const std::string host = host_name();
  spec.common_name = fmt::format("dtraced CA {}", host.empty() ? "collector" : host.substr(0, 40));
  if (has_control_or_comma(spec.common_name)) spec.common_name = "dtraced CA";
  spec.not_before_unix = now_unix - kBackdateSeconds;
  spec.not_after_unix = now_unix + kCaValidityDays * kSecondsPerDay;
  auto pair = make_self_signed_ca(spec);
  if (!pair) return pair;
  // The key first: a crash in between leaves a key without a certificate, which the next start
  // reports instead of silently making a second CA.
  if (auto ok = write_private_file(key_file, pair->key_pem, 0600); !ok) return std::move(ok).error();
  if (auto ok = write_private_file(cert_file, pair->cert_pem, 0644); !ok) return std::move(ok).error();
  return pair;
}

CertSpec server_cert_spec(std::string_view listen_address, const std::vector<std::string>& extra,
                          std::int64_t now_unix) {
  CertSpec spec;
  std::vector<std::string> names = {"localhost", "127.0.0.1", "::1"};
  const std::string host = host_name();
  if (!host.empty()) add_unique(names, host);
  const bool wildcard =
      listen_address.empty() || listen_address == "0.0.0.0" || listen_address == "::" || listen_address == "[::]";
  if (wildcard) {
    for (std::string& address : interface_addresses()) add_unique(names, std::move(address));
  } else {
    std::string address(listen_address);
    if (address.size() > 2 && address.front() == '[' && address.back() == ']')
      address = address.substr(1, address.size() - 2);
    add_unique(names, std::move(address));
  }
  for (const std::string& name : extra) add_unique(names, name);
  for (std::string& name : names) {
    if (is_ip_literal(name)) {
      spec.ip_addresses.push_back(std::move(name));
    } else if (!name.empty() && !has_control_or_comma(name)) {
      spec.dns_names.push_back(std::move(name));
    }
  }
  spec.common_name = host.empty() || host.size() > 64 || has_control_or_comma(host) ? "localhost" : host;
  spec.not_before_unix = now_unix - kBackdateSeconds;
  spec.not_after_unix = now_unix + kServerCertValidityDays * kSecondsPerDay;
  spec.is_ca = false;
  spec.server = true;
  return spec;
}

util::Result<void> write_private_file(const std::string& path, std::string_view bytes, unsigned mode) {
  std::string tmp = path + ".tmp.XXXXXX";
  const int fd = ::mkstemp(tmp.data());  // created 0600: never readable by others, even briefly
  if (fd < 0) {
    return util::Error(fmt::format("cannot create a temporary file: {}", std::strerror(errno)), "", path);
  }
  auto fail = [&](std::string message) -> util::Result<void> {
    ::close(fd);
    ::unlink(tmp.c_str());
    return util::Error(std::move(message), "", path);
  };
  if (::fchmod(fd, static_cast<mode_t>(mode)) != 0) {
    return fail(fmt::format("cannot set permissions {:o}: {}", mode, std::strerror(errno)));
  }
  if (auto ok = write_all(fd, bytes); !ok) return fail(ok.error().message);
  if (::fsync(fd) != 0) return fail(fmt::format("flush failed: {}", std::strerror(errno)));
  if (::close(fd) != 0) {
    ::unlink(tmp.c_str());
    return util::Error(fmt::format("close failed: {}", std::strerror(errno)), "", path);
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    const int err = errno;
    ::unlink(tmp.c_str());
    return util::Error(fmt::format("cannot rename into place: {}", std::strerror(err)), "", path);
  }
  const int dir_fd = ::open(directory_of(path).c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd >= 0) {
    ::fsync(dir_fd);
    ::close(dir_fd);
  }
  return {};
}

}  // namespace dtraced::tls
