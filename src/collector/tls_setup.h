// dtraced::collector TLS set-up: what the collector's HTTPS listener presents and trusts.
//
// Owns: turning the TLS settings (flags and config file) into the server's ssl::context and into
// what the collector tells enrolling workers (the CA certificate they must trust and its
// fingerprint, which join codes carry). Two sources of certificates:
//   - by default a private CA kept in <state_dir>/tls (created on first start, key 0600; the CA
//     key never leaves the collector) issues a fresh server certificate at every start for the
//     names the collector answers to: localhost, 127.0.0.1, ::1, the host name, the listen
//     address (every interface's address for a wildcard) and each --tls-name;
//   - or the operator's own certificate and key (--tls-cert, --tls-key), with --tls-ca naming the
//     CA that workers should trust (without it join codes carry no fingerprint, and enrolling
//     workers need --ca-file).
// Either way a client certificate, if one is presented, must chain to that CA (or the handshake
// fails); nobody needs one.
//
// Blocking file I/O and key generation: called once at start-up, before the loop runs.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <boost/asio/ssl/context.hpp>

#include "tls/material.h"
#include "util/result.h"

namespace dtraced::collector {

struct TlsSettings {
  bool enabled = false;            // the CLI resolves --tls auto|on|off (auto: on unless loopback)
  std::string cert_file;           // operator-provided server certificate (chain), PEM; empty: the private CA
  std::string key_file;            // its private key, PEM
  std::string ca_file;             // operator-provided: the CA workers must trust, PEM (optional)
  std::vector<std::string> names;  // extra names for the private CA's server certificate (--tls-name)
};

struct TlsSetup {
  std::shared_ptr<boost::asio::ssl::context> context;
  std::string ca_pem;  // what GET /v1/ca serves; empty when unknown
  std::optional<tls::Fingerprint> ca_fingerprint;
  std::string description;  // one line for the start-up log
};

// Reads or creates the material and builds the server context. Errors name the file or the
// setting and the problem.
util::Result<TlsSetup> prepare_tls(const TlsSettings& settings, const std::string& state_dir,
                                   const std::string& listen_address, std::int64_t now_unix);

}  // namespace dtraced::collector
