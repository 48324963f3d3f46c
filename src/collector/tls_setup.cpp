#include "collector/tls_setup.h"

#include <utility>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "http/tls_server.h"
#include "util/file.h"

namespace dtraced::collector {

namespace {

// A CA certificate file is a few KiB; a bundle of them well under this.
constexpr std::uint64_t kMaxPemBytes = 1 << 20;

util::Result<TlsSetup> with_context(TlsSetup setup, const tls::KeyPair& server, std::string client_ca_pem) {
  http::ServerTlsConfig config;
  config.cert_chain_pem = server.cert_pem;
  config.key_pem = server.key_pem;
  config.client_ca_pem = std::move(client_ca_pem);
  auto context = http::make_server_tls_context(config);
  if (!context) return std::move(context).error();
  setup.context = std::move(context).value();
  return setup;
}

util::Result<TlsSetup> operator_certificate(const TlsSettings& s) {
  if (s.key_file.empty()) return util::Error("--tls-cert needs --tls-key (the certificate's private key)");
  auto pair = tls::load_key_pair(s.cert_file, s.key_file);
  if (!pair) return std::move(pair).error();
  TlsSetup setup;
  if (!s.ca_file.empty()) {
    auto ca = util::read_file_limited(s.ca_file, kMaxPemBytes);
    if (!ca) return util::Error(ca.error().message, "--tls-ca", s.ca_file);
    auto fingerprint = tls::fingerprint_of_pem(*ca);
    if (!fingerprint) return util::Error(fingerprint.error().message, "--tls-ca", s.ca_file);
    setup.ca_pem = *ca;
    setup.ca_fingerprint = *fingerprint;
  }
  setup.description = fmt::format("TLS with {} (CA {})", s.cert_file, s.ca_file.empty() ? "not given" : s.ca_file);
  const std::string client_ca = setup.ca_pem;
  return with_context(std::move(setup), *pair, client_ca);
}

}  // namespace

util::Result<TlsSetup> prepare_tls(const TlsSettings& s, const std::string& state_dir,
                                   const std::string& listen_address, std::int64_t now_unix) {
  if (!s.cert_file.empty()) return operator_certificate(s);
  if (!s.key_file.empty()) return util::Error("--tls-key needs --tls-cert (the certificate it belongs to)");
  auto ca = tls::load_or_create_authority(state_dir, now_unix);
  if (!ca) return std::move(ca).error();
  const tls::CertSpec spec = tls::server_cert_spec(listen_address, s.names, now_unix);
  auto server = tls::issue(*ca, spec);
  if (!server) return util::Error(fmt::format("issuing the server certificate: {}", server.error().message));
  auto fingerprint = tls::fingerprint_of_pem(ca->cert_pem);
  if (!fingerprint)
    return util::Error(fmt::format("the private CA in {}/tls: {}", state_dir, fingerprint.error().message));
  TlsSetup setup;
  setup.ca_pem = ca->cert_pem;
  setup.ca_fingerprint = *fingerprint;
  std::vector<std::string> names = spec.dns_names;
  names.insert(names.end(), spec.ip_addresses.begin(), spec.ip_addresses.end());
  setup.description = fmt::format("TLS with the private CA in {}/tls (fingerprint {}), server certificate for {}",
                                  state_dir, tls::fingerprint_hex(*fingerprint), fmt::join(names, ", "));
  // The server presents its certificate and the CA's, so a client holding the CA can check the chain.
  tls::KeyPair chain = std::move(server).value();
  chain.cert_pem += ca->cert_pem;
  return with_context(std::move(setup), chain, ca->cert_pem);
}

}  // namespace dtraced::collector
