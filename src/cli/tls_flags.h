// dtraced::cli TLS flags: whether a collector listens with TLS, decided from --tls, the listen
// address and --allow-plain-http.
//
//   --tls on     always TLS;
//   --tls off    plain HTTP: fine on a loopback address (127.0.0.0/8, ::1), refused on any other
//                unless --allow-plain-http says the network in between is trusted;
//   --tls auto   (the default) TLS unless the address is loopback.
//
// Pure functions: thread-safe.
#pragma once

#include <string_view>

#include "util/result.h"

namespace dtraced::cli {

// Whether `address` (an IPv4 or IPv6 address, as --listen gives it) is a loopback address.
bool is_loopback_address(std::string_view address);

// Whether the collector listens with TLS; an error (naming --tls) for plain HTTP off loopback
// without allow_plain_http, or an unknown mode.
util::Result<bool> resolve_tls(std::string_view mode, std::string_view listen_address, bool allow_plain_http);

}  // namespace dtraced::cli
