#include "cli/listen_address.h"

#include <charconv>
#include <system_error>

#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/address.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <fmt/format.h>

namespace dtraced::cli {

namespace {

namespace ip = boost::asio::ip;

constexpr const char* kFlag = "--listen";

// The address the name `host` stands for: its first IPv4 address, else its first IPv6 one.
util::Result<std::string> resolve_host(const std::string& host) {
  boost::asio::io_context io;
  ip::tcp::resolver resolver(io);
  boost::system::error_code ec;
  // Service "0" and numeric_service: only the host is looked up, never /etc/services.
  const ip::tcp::resolver::results_type results =
      resolver.resolve(host, "0", ip::tcp::resolver::numeric_service | ip::tcp::resolver::passive, ec);
  if (ec) return util::Error{fmt::format("cannot resolve the host name \"{}\": {}", host, ec.message()), kFlag};
  for (const auto& entry : results) {
    if (entry.endpoint().address().is_v4()) return entry.endpoint().address().to_string();
  }
  if (!results.empty()) return results.begin()->endpoint().address().to_string();
  return util::Error{fmt::format("the host name \"{}\" has no address", host), kFlag};
}

}  // namespace

util::Result<ListenAddress> parse_listen(const std::string& text) {
  const std::size_t colon = text.rfind(':');
  if (colon == std::string::npos || colon == 0) {
    return util::Error{fmt::format("expected HOST:PORT, got \"{}\"", text), kFlag};
  }
  ListenAddress out;
  std::string host = text.substr(0, colon);
  const bool bracketed = host.size() >= 2 && host.front() == '[' && host.back() == ']';
  if (bracketed) host = host.substr(1, host.size() - 2);
  const std::string p = text.substr(colon + 1);
  unsigned value = 0;
  const auto [end, ec] = std::from_chars(p.data(), p.data() + p.size(), value);
  if (p.empty() || ec != std::errc() || end != p.data() + p.size() || value > 65535) {
    return util::Error{fmt::format("bad port \"{}\" in \"{}\" (0-65535)", p, text), kFlag};
  }
  out.port = static_cast<std::uint16_t>(value);
  boost::system::error_code not_numeric;
  ip::make_address(host, not_numeric);
  if (!not_numeric) {
    out.host = host;
    return out;
  }
  // Names have no colons, and brackets hold addresses only: this is a mistyped address.
  if (bracketed || host.find(':') != std::string::npos) {
    return util::Error{fmt::format("\"{}\" is not an IP address (write IPv6 as [ADDRESS]:PORT)", host), kFlag};
  }
  util::Result<std::string> resolved = resolve_host(host);
  if (!resolved) return resolved.error();
  out.host = std::move(resolved).value();
  return out;
}

}  // namespace dtraced::cli
