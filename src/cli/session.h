// dtraced::cli session: one verb's conversation with a collector.
//
// Owns: where (the --collector URL, plain or https), with which credential (--token-file) and
// which trust anchor (--ca-file), over one kept-alive connection (http::SyncClient), and how
// patient: every call rides out a busy collector (and, for a GET, one that does not answer) for
// up to --timeout-ms, or what retry_for sets (cli/retry.h says what is retried and why that is
// safe). Also the small helpers every client verb shares.
//
// Not thread-safe: one Session per verb, on main's thread.
#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <fmt/format.h>

#include "cli/client_verbs.h"
#include "cli/retry.h"
#include "http/client.h"
#include "protocol/messages.h"
#include "util/result.h"

namespace dtraced::cli {

// "12.3s", "4m05s", "2h03m".
std::string format_seconds(double s);

// The CA certificate(s) in `path`, checked to be usable; errors name the file.
util::Result<http::ClientTls> read_ca_file(const std::string& path);

// The value, or nullopt after printing why the collector's answer to `what` is not what was
// expected.
template <typename T>
std::optional<T> decode_or_report(const protocol::Decoded<T>& d, std::string_view what) {
  if (d.ok()) return d.value();
  fmt::print(stderr, "unexpected answer to {}: {}\n", what, d.error().front().to_string());
  return std::nullopt;
}

class Session {
 public:
  // False after printing what is wrong with the arguments (URL, CA file, token file).
  bool init(const ClientArgs& args);

  // How long a run of failures is retried, and the flag that set it (named when giving up).
  void retry_for(std::chrono::milliseconds budget, std::string flag);

  // Sends one request, again after each retryable failure (one line on stderr per wait) until it
  // succeeds or the retry budget is spent; on a final failure prints the reason and returns
  // nullopt.
  std::optional<http::Response> call(http::Verb verb, const std::string& target, const std::string& body = {},
                                     std::uint64_t max_body = protocol::kMaxJobListBytes);

 private:
  http::Url url_;
  std::string token_;
  std::unique_ptr<http::SyncClient> client_;  // set by init()
  RetryPolicy retry_{std::chrono::milliseconds(0), 0};
  std::string retry_flag_;
};

}  // namespace dtraced::cli
