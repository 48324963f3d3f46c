// dtraced::http TLS for the server: the OpenSSL context an HTTPS Server is given.
//
// Owns: the server's TLS policy in one place. TLS 1.2 and 1.3 only; for TLS 1.2 the ECDHE
// suites with AES-GCM or ChaCha20-Poly1305 only (TLS 1.3's suites are all ECDHE and AEAD); no
// compression; no renegotiation of either kind; no encrypted keys (no password prompt can hang a
// daemon). With a client CA, the server asks every client for a certificate without requiring
// one (SSL_VERIFY_PEER without FAIL_IF_NO_PEER_CERT): a client that presents one the CA did not
// sign, or one outside its validity, fails the handshake; one that presents none is let in.
//
// Thread safety: make_server_tls_context is a free function; the context it returns is shared
// read-only by the connections of one Server (OpenSSL allows that across threads).
#pragma once

#include <memory>
#include <string>

#include <boost/asio/ssl/context.hpp>

#include "util/result.h"

namespace dtraced::http {

struct ServerTlsConfig {
  std::string cert_chain_pem;  // the server's certificate, then any intermediates
  std::string key_pem;         // its private key, unencrypted
  std::string client_ca_pem;   // empty: no client certificates asked for
};

// The context for Server's `tls` parameter. Errors say which PEM is wrong and how, with
// OpenSSL's reason.
util::Result<std::shared_ptr<boost::asio::ssl::context>> make_server_tls_context(const ServerTlsConfig& config);

}  // namespace dtraced::http
