#include "cli/enroll_verbs.h"

#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <ctime>
#include <filesystem>
#include <optional>
#include <utility>

#include <boost/beast/http/field.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <fmt/chrono.h>
#include <fmt/format.h>

#include "cli/session.h"
#include "http/client.h"
#include "protocol/credential_messages.h"
#include "tls/join_code.h"
#include "tls/material.h"
#include "util/file.h"

namespace dtraced::cli {

namespace {

constexpr int kExitOk = 0;
constexpr int kExitFailed = 1;
constexpr int kExitUsage = 2;
constexpr std::uint64_t kMaxCaAnswerBytes = 1 << 20;
constexpr std::uint64_t kMaxMessageAnswerBytes = 64 * 1024;

// The collector's message in an error answer ({"error": ...}), else the status line.
std::string refusal_text(const http::Response& res) {
  auto body = protocol::decode_error_body(res.body());
  if (body.ok()) return fmt::format("HTTP {}: {}", res.result_int(), body.value().error);
  return fmt::format("HTTP {}", res.result_int());
}

std::string host_name() {
  std::array<char, 256> buffer{};
  if (gethostname(buffer.data(), buffer.size() - 1) != 0) return "worker";
  std::string name(buffer.data());
  // The part before the first dot, in the characters a credential name takes.
  name = name.substr(0, name.find('.'));
  for (char& c : name) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_') c = '-';
  }
  return name.empty() ? std::string("worker") : name;
}

struct EnrollmentFiles {
  std::string token, ca, config;
};

EnrollmentFiles files_of(const EnrollArgs& a) {
  const std::filesystem::path dir(a.dir);
  return {(dir / fmt::format("worker-{}.token", a.instance)).string(),
          (dir / fmt::format("worker-{}-ca.pem", a.instance)).string(),
          (dir / fmt::format("worker-{}.json", a.instance)).string()};
}

// The worker's config file (the keys are its flags, config/worker.json).
std::string worker_config(const std::string& collector, const std::string& ca_file, const std::string& name) {
  boost::json::object o;
  o["collector"] = collector;
  if (!ca_file.empty()) o["ca_file"] = ca_file;
  o["name"] = name;
  // One key a line, as people edit it.
  std::string pretty = "{\n";
  bool first = true;
  for (const auto& kv : o) {
    if (!first) pretty += ",\n";
    first = false;
    pretty += fmt::format("  \"{}\": {}", std::string_view(kv.key()), boost::json::serialize(kv.value()));
  }
  pretty += "\n}\n";
  return pretty;
}

}  // namespace

util::Result<std::uint32_t> parse_duration_seconds(const std::string& text, std::uint32_t max_seconds) {
  if (text.empty()) return util::Error("empty duration: give e.g. 90s, 30m, 1h or 7d");
  std::uint64_t unit = 1;
  std::string_view digits(text);
  switch (text.back()) {
    case 's':
      unit = 1;
      digits.remove_suffix(1);
      break;
    case 'm':
      unit = 60;
      digits.remove_suffix(1);
      break;
    case 'h':
      unit = 3600;
      digits.remove_suffix(1);
      break;
    case 'd':
      unit = 86400;
      digits.remove_suffix(1);
      break;
    default:
      break;
  }
  std::uint64_t value = 0;
  const auto [end, ec] = std::from_chars(digits.data(), digits.data() + digits.size(), value);
  if (digits.empty() || ec != std::errc() || end != digits.data() + digits.size()) {
    return util::Error(fmt::format("'{}' is not a duration: give e.g. 90s, 30m, 1h or 7d", text));
  }
  if (value == 0 || value > max_seconds / unit) {
    return util::Error(fmt::format("'{}' is outside 1 s to {} s", text, max_seconds));
  }
  return static_cast<std::uint32_t>(value * unit);
}

bool valid_instance_name(const std::string& name) {
  if (name.empty() || name.size() > 64 || name.front() == '.' || name.front() == '-') return false;
  return std::all_of(name.begin(), name.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' || c == '.';
  });
}

int run_enroll_code(const ClientArgs& client, const EnrollCodeArgs& args) {
  auto seconds = parse_duration_seconds(args.expires, protocol::kMaxEnrollCodeSeconds);
  if (!seconds) {
    fmt::print(stderr, "--expires: {}\n", seconds.error().message);
    return kExitUsage;
  }
  Session session;
  if (!session.init(client)) return kExitUsage;
  protocol::EnrollCodeRequest request;
  request.expires_s = *seconds;
  if (!args.name.empty()) request.name = args.name;
  auto resp = session.call(http::Verb::post, "/v1/enroll-codes", protocol::encode(request), kMaxMessageAnswerBytes);
  if (!resp) return kExitFailed;
  auto code = decode_or_report(protocol::decode_enroll_code(resp->body()), "POST /v1/enroll-codes");
  if (!code) return kExitFailed;
  fmt::print("{}\n", code->code);
  if (isatty(STDOUT_FILENO) != 0) {
    fmt::print(stderr,
               "one use, valid for {} s; on the new worker host run:\n  dtraced enroll --collector {} --code {}\n",
               *seconds, client.collector, code->code);
  }
  return kExitOk;
}

int run_enroll(const EnrollArgs& a) {
  auto code = tls::parse_join_code(a.code);
  if (!code) {
    fmt::print(stderr, "--code: {}\n", code.error().message);
    return kExitUsage;
  }
  auto url = http::parse_base_url(a.collector);
  if (!url) {
    fmt::print(stderr, "--collector: {}\n", url.error().message);
    return kExitUsage;
  }
  if (!valid_instance_name(a.instance)) {
    fmt::print(stderr, "--instance: '{}' must be 1-64 letters, digits, '-', '_' or '.'\n", a.instance);
    return kExitUsage;
  }
  const std::string name = a.name.empty() ? host_name() : a.name;
  const EnrollmentFiles files = files_of(a);
  if (!a.force && std::filesystem::exists(files.token)) {
    fmt::print(stderr, "{} exists: this host is already enrolled as instance '{}' (--force replaces it)\n", files.token,
               a.instance);
    return kExitUsage;
  }

  http::ClientOptions options;
  options.timeouts.read = options.timeouts.write = std::chrono::milliseconds(a.timeout_ms);
  std::string ca_pem;
  if (url->tls) {
    http::ClientTls tls;
    if (!a.ca_file.empty()) {
      auto given = read_ca_file(a.ca_file);
      if (!given) {
        fmt::print(stderr, "--ca-file: {}\n", given.error().to_string());
        return kExitUsage;
      }
      tls = std::move(given).value();
    } else if (code->ca) {
      tls.ca_fingerprint = *code->ca;
      tls.ca_source = "the join code's CA fingerprint";
    } else {
      fmt::print(stderr,
                 "--code: this join code carries no CA fingerprint (the collector uses its own certificate without "
                 "--tls-ca): give --ca-file with the CA its certificate chains to\n");
      return kExitUsage;
    }
    options.tls = std::move(tls);
  } else if (code->ca) {
    fmt::print(stderr, "--collector: the join code is for a collector with TLS: use https://{}\n", url->host_header());
    return kExitUsage;
  } else {
    fmt::print(stderr, "warning: {} is plain HTTP: the worker's token will travel in clear\n", url->to_string());
  }
  http::SyncClient client(std::move(options));

  // The CA the collector's chain verified against: kept as the worker's trust anchor, and
  // checked against the code once more.
  if (url->tls) {
    http::ClientResult r = client.request(*url, http::make_request(http::Verb::get, "/v1/ca"), kMaxCaAnswerBytes);
    if (!r.ok()) {
      if (r.error == http::ClientError::kTls && code->ca && a.ca_file.empty()) {
        fmt::print(stderr,
                   "{}: the collector's certificate does not match the join code's CA (fingerprint {}): {}\n"
                   "Check the collector URL; a code is only good for the collector that made it.\n",
                   url->to_string(), tls::fingerprint_hex(*code->ca), r.message);
      } else {
        fmt::print(stderr, "{}\n", r.message);
      }
      return kExitFailed;
    }
    if (r.response.result() != http::Status::ok) {
      fmt::print(stderr, "GET /v1/ca: {}\n", refusal_text(r.response));
      return kExitFailed;
    }
    ca_pem = r.response.body();
    auto fingerprint = tls::fingerprint_of_pem(ca_pem);
    if (!fingerprint || (code->ca && *fingerprint != *code->ca)) {
      fmt::print(stderr, "{}: the CA the collector serves does not match the join code's fingerprint {}\n",
                 url->to_string(), code->ca ? tls::fingerprint_hex(*code->ca) : std::string("-"));
      return kExitFailed;
    }
  }

  protocol::EnrollRequest request;
  request.code = a.code;
  request.name = name;
  http::Request req =
      http::make_request(http::Verb::post, "/v1/enroll", protocol::encode(request), http::kJsonContentType);
  http::ClientResult r = client.request(*url, std::move(req), kMaxMessageAnswerBytes);
  if (!r.ok()) {
    fmt::print(stderr, "{}\n", r.message);
    return kExitFailed;
  }
  if (r.response.result() != http::Status::created) {
    fmt::print(stderr, "the collector refused the enrollment: {}\n", refusal_text(r.response));
    return kExitFailed;
  }
  auto issued = decode_or_report(protocol::decode_credential_issued(r.response.body()), "POST /v1/enroll");
  if (!issued) return kExitFailed;

  std::error_code ec;
  std::filesystem::create_directories(a.dir, ec);
  if (ec) {
    fmt::print(stderr, "--dir {}: {}\n", a.dir, ec.message());
    return kExitFailed;
  }
  // The token first and root-only; the CA and the config are public.
  const std::string ca_file = url->tls ? files.ca : std::string();
  if (auto w = tls::write_private_file(files.token, issued->token + "\n", 0600); !w) {
    fmt::print(stderr, "{}\n", w.error().to_string());
    return kExitFailed;
  }
  if (url->tls) {
    if (auto w = tls::write_private_file(files.ca, ca_pem, 0644); !w) {
      fmt::print(stderr, "{}\n", w.error().to_string());
      return kExitFailed;
    }
  }
  if (auto w = tls::write_private_file(files.config, worker_config(url->to_string(), ca_file, issued->name), 0644);
      !w) {
    fmt::print(stderr, "{}\n", w.error().to_string());
    return kExitFailed;
  }
  fmt::print("enrolled as worker '{}' of {}\n", issued->name, url->to_string());
  fmt::print("  token   {} (0600)\n", files.token);
  if (url->tls) fmt::print("  CA      {}\n", files.ca);
  fmt::print("  config  {}\n", files.config);
  fmt::print("start it with:\n  systemctl enable --now dtraced-worker@{}\n", a.instance);
  return kExitOk;
}

int run_revoke(const ClientArgs& client, const std::string& name) {
  Session session;
  if (!session.init(client)) return kExitUsage;
  auto resp =
      session.call(http::Verb::post, fmt::format("/v1/credentials/{}/revoke", name), "{}", kMaxMessageAnswerBytes);
  if (!resp) return kExitFailed;
  auto revoked =
      decode_or_report(protocol::decode_credential_revoked(resp->body()), "POST /v1/credentials/NAME/revoke");
  if (!revoked) return kExitFailed;
  fmt::print("revoked {} ({}){}\n", revoked->name, revoked->role,
             revoked->leases_released > 0
                 ? fmt::format("; {} leased tile(s) offered to other workers at once", revoked->leases_released)
                 : std::string());
  return kExitOk;
}

int run_credentials_add(const ClientArgs& client, const CredentialAddArgs& args) {
  Session session;
  if (!session.init(client)) return kExitUsage;
  protocol::CredentialRequest request{args.name, args.role};
  auto resp = session.call(http::Verb::post, "/v1/credentials", protocol::encode(request), kMaxMessageAnswerBytes);
  if (!resp) return kExitFailed;
  auto issued = decode_or_report(protocol::decode_credential_issued(resp->body()), "POST /v1/credentials");
  if (!issued) return kExitFailed;
  if (args.output.empty()) {
    fmt::print("{}\n", issued->token);
    return kExitOk;
  }
  if (auto w = tls::write_private_file(args.output, issued->token + "\n", 0600); !w) {
    fmt::print(stderr, "{}\n", w.error().to_string());
    return kExitFailed;
  }
  fmt::print(stderr, "{} ({}): token in {}\n", issued->name, issued->role, args.output);
  return kExitOk;
}

int run_credentials_list(const ClientArgs& client, bool json) {
  Session session;
  if (!session.init(client)) return kExitUsage;
  auto resp = session.call(http::Verb::get, "/v1/credentials", {}, protocol::kMaxCredentialListBytes);
  if (!resp) return kExitFailed;
  if (json) {
    fmt::print("{}\n", resp->body());
    return kExitOk;
  }
  auto list = decode_or_report(protocol::decode_credential_list(resp->body()), "GET /v1/credentials");
  if (!list) return kExitFailed;
  const auto when = [](std::int64_t unix_seconds) {
    return fmt::format("{:%Y-%m-%d %H:%M}", fmt::gmtime(static_cast<std::time_t>(unix_seconds)));
  };
  std::size_t width = 4;
  for (const auto& c : list->credentials) width = std::max(width, c.name.size());
  fmt::print("{:<{}}  {:<8} {:<16}  {}\n", "name", width, "role", "created (UTC)", "revoked (UTC)");
  for (const auto& c : list->credentials) {
    fmt::print("{:<{}}  {:<8} {:<16}  {}\n", c.name, width, c.role, when(c.created_unix),
               c.revoked_unix ? when(*c.revoked_unix) : std::string("-"));
  }
  return kExitOk;
}

}  // namespace dtraced::cli
