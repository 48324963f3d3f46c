#include "http/tls_server.h"

#include <array>
#include <string_view>
#include <utility>

#include <boost/asio/buffer.hpp>
#include <fmt/format.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>

#include "tls/material.h"

namespace dtraced::http {
namespace {

namespace ssl = boost::asio::ssl;

// TLS 1.2's suites: forward secrecy and AEAD only. TLS 1.3's are OpenSSL's defaults (all both).
constexpr const char* kTls12Ciphers = "ECDHE+AESGCM:ECDHE+CHACHA20";
// Resumed sessions must belong to this application (OpenSSL refuses resumption with client
// verification on and no session id context).
constexpr std::string_view kSessionIdContext = "dtraced";
constexpr int kMaxVerifyDepth = 4;

// OpenSSL's queued reasons, joined, or the error code's message; the queue is left empty.
std::string context_failure_reason(const boost::system::error_code& ec = {}) {
  const bool queued = ERR_peek_error() != 0;
  std::string out = tls::openssl_reason();
  if (!queued && ec) out = ec.message();
  return out;
}

// The key in `pem`, or null. An encrypted key is refused (no password callback can prompt on a
// terminal nobody watches).
EVP_PKEY* read_private_key(const std::string& pem) {
  BIO* bio = BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size()));
  if (bio == nullptr) return nullptr;
  auto no_password = [](char*, int, int, void*) { return -1; };
  EVP_PKEY* key = PEM_read_bio_PrivateKey(bio, nullptr, no_password, nullptr);
  BIO_free(bio);
  return key;
}

// Adds every certificate of `pem` to the names sent in the CertificateRequest; false if none.
bool add_client_ca_names(SSL_CTX* native, const std::string& pem) {
  BIO* bio = BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size()));
  if (bio == nullptr) return false;
  int added = 0;
  while (X509* cert = PEM_read_bio_X509(bio, nullptr, nullptr, nullptr)) {
    if (SSL_CTX_add_client_CA(native, cert) == 1) ++added;
    X509_free(cert);
  }
  BIO_free(bio);
  ERR_clear_error();  // the read that ended the loop queued "no start line"
  return added > 0;
}

}  // namespace

util::Result<std::shared_ptr<ssl::context>> make_server_tls_context(const ServerTlsConfig& config) {
  ERR_clear_error();
  auto ctx = std::make_shared<ssl::context>(ssl::context::tls_server);
  SSL_CTX* native = ctx->native_handle();
  if (SSL_CTX_set_min_proto_version(native, TLS1_2_VERSION) != 1) {
    return util::Error(fmt::format("TLS: cannot require TLS 1.2 or later: {}", context_failure_reason()));
  }
  SSL_CTX_set_options(native, SSL_OP_NO_RENEGOTIATION | SSL_OP_NO_COMPRESSION | SSL_OP_CIPHER_SERVER_PREFERENCE);
  if (SSL_CTX_set_cipher_list(native, kTls12Ciphers) != 1) {
    return util::Error(fmt::format("TLS: cannot set the TLS 1.2 cipher list: {}", context_failure_reason()));
  }
  boost::system::error_code ec;
  if (config.cert_chain_pem.empty()) return util::Error("TLS: the server certificate PEM is empty");
  ctx->use_certificate_chain(boost::asio::buffer(config.cert_chain_pem), ec);
  if (ec)
    return util::Error(fmt::format("TLS: the server certificate PEM is not usable: {}", context_failure_reason(ec)));
  if (config.key_pem.empty()) return util::Error("TLS: the server key PEM is empty");
  EVP_PKEY* key = read_private_key(config.key_pem);
  if (key == nullptr) {
    return util::Error(fmt::format("TLS: the server key PEM is not usable (an encrypted key is not supported): {}",
                                   context_failure_reason()));
  }
  const bool matches = SSL_CTX_use_PrivateKey(native, key) == 1 && SSL_CTX_check_private_key(native) == 1;
  EVP_PKEY_free(key);
  if (!matches) {
    return util::Error(
        fmt::format("TLS: the server key does not match the server certificate: {}", context_failure_reason()));
  }

  if (!config.client_ca_pem.empty()) {
    ctx->add_certificate_authority(boost::asio::buffer(config.client_ca_pem), ec);
    if (ec || !add_client_ca_names(native, config.client_ca_pem)) {
      return util::Error(fmt::format("TLS: the client CA PEM is not usable: {}", context_failure_reason(ec)));
    }
    SSL_CTX_set_verify(native, SSL_VERIFY_PEER | SSL_VERIFY_CLIENT_ONCE, nullptr);
    SSL_CTX_set_verify_depth(native, kMaxVerifyDepth);
  }
  if (SSL_CTX_set_session_id_context(native, reinterpret_cast<const unsigned char*>(kSessionIdContext.data()),
                                     static_cast<unsigned int>(kSessionIdContext.size())) != 1) {
    return util::Error(fmt::format("TLS: cannot set the session id context: {}", context_failure_reason()));
  }
  return ctx;
}

}  // namespace dtraced::http
