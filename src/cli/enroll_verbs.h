// dtraced::cli enrollment and credential verbs: how hosts and people get their own credentials
// from a collector (docs/security.md).
//
//   dtraced enroll-code --expires 1h [--name N]   (client role) prints a one-time join code
//   dtraced enroll --collector https://HOST:PORT --code CODE [--name N] [--instance I] [--dir D]
//       on a new worker host: checks the collector against the CA fingerprint the code carries,
//       redeems the code for the worker's own token, stores token, CA and config where the
//       systemd unit dtraced-worker@I reads them, and prints the systemctl command left to run
//   dtraced workers revoke NAME                   (client role) the worker's next request fails
//   dtraced credentials add --role R NAME         (client role) a viewer, client or worker token
//   dtraced credentials list                      (client role) names, roles, when revoked
//
// Results on stdout, diagnostics on stderr; each function returns the exit code (0 ok, 1 the
// collector refused or could not be reached, 2 a usage error).
#pragma once

#include <cstdint>
#include <string>

#include "cli/client_verbs.h"
#include "util/result.h"

namespace dtraced::cli {

struct EnrollCodeArgs {
  std::string expires = "1h";  // a duration: 90s, 30m, 1h, 7d (or plain seconds)
  std::string name;            // the name the enrolled worker gets (default: the one it asks for)
};
int run_enroll_code(const ClientArgs& client, const EnrollCodeArgs& args);

struct EnrollArgs {
  std::string collector;          // https://HOST:PORT (http:// only for a collector without TLS)
  std::string code;               // from enroll-code
  std::string name;               // asked for; default: this host's name
  std::string instance = "farm";  // the systemd instance: dtraced-worker@INSTANCE
  std::string dir = "/etc/dtraced";
  std::string ca_file;  // only for a code without a CA fingerprint
  bool force = false;   // replace an existing enrollment of this instance
  std::uint32_t timeout_ms = 30000;
};
int run_enroll(const EnrollArgs& args);

int run_revoke(const ClientArgs& client, const std::string& name);

struct CredentialAddArgs {
  std::string name;
  std::string role;    // viewer, client or worker
  std::string output;  // write the token to this file (0600) instead of stdout
};
int run_credentials_add(const ClientArgs& client, const CredentialAddArgs& args);
int run_credentials_list(const ClientArgs& client, bool json);

// "90s", "30m", "1h", "7d" or a number of seconds, in [1, max_seconds]; the error says why not.
util::Result<std::uint32_t> parse_duration_seconds(const std::string& text, std::uint32_t max_seconds);

// Whether `name` may name a systemd instance and the files of an enrollment: 1-64 of
// [A-Za-z0-9_.-], not starting with a dot or a dash.
bool valid_instance_name(const std::string& name);

}  // namespace dtraced::cli
