#include "cli/tls_flags.h"

#include <boost/asio/ip/address.hpp>
#include <fmt/format.h>

namespace dtraced::cli {

bool is_loopback_address(std::string_view address) {
  boost::system::error_code ec;
  const auto parsed = boost::asio::ip::make_address(std::string(address), ec);
  return !ec && parsed.is_loopback();
}

util::Result<bool> resolve_tls(std::string_view mode, std::string_view listen_address, bool allow_plain_http) {
  const bool loopback = is_loopback_address(listen_address);
  if (mode == "on") return true;
  if (mode == "auto") return !loopback;
  if (mode != "off") return util::Error(fmt::format("'{}' is not auto, on or off", mode), "--tls");
  if (!loopback && !allow_plain_http) {
    return util::Error(fmt::format("plain HTTP on {} (not a loopback address) would send tokens and pixels in clear; "
                                   "use TLS (--tls auto or on), or add --allow-plain-http if the network in between "
                                   "is trusted (a TLS proxy in front, a private link)",
                                   listen_address),
                       "--tls");
  }
  return false;
}

}  // namespace dtraced::cli
