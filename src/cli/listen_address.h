// dtraced::cli --listen: the collector's listening address as given on the command line.
//
// "HOST:PORT", where HOST is an IPv4 address, a bracketed IPv6 address ("[::1]:7878") or a host
// name ("localhost:0"). A name is resolved once, at start, with Asio's resolver (the system's
// getaddrinfo): the collector binds one address, its first IPv4 one, else its first IPv6 one,
// so that "localhost" means 127.0.0.1 on hosts whose IPv6 is off.
//
// Stateless; resolving blocks the calling thread (main's, before any loop runs): thread-safe.
#pragma once

#include <cstdint>
#include <string>

#include "util/result.h"

namespace dtraced::cli {

struct ListenAddress {
  std::string host;  // a numeric IPv4 or IPv6 address, never a name
  std::uint16_t port = 0;
};

// The address `text` asks for, its host resolved; an Error whose path is "--listen" and whose
// message quotes what was wrong (a missing port, a bad port, a name that does not resolve).
util::Result<ListenAddress> parse_listen(const std::string& text);

}  // namespace dtraced::cli
