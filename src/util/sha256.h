// dtraced::util SHA-256 through OpenSSL's libcrypto. Stateless: thread-safe.
#pragma once

#include <string>
#include <string_view>

namespace dtraced::util {

// Lower-case hex digest (64 characters) of `bytes`.
std::string sha256_hex(std::string_view bytes);

}  // namespace dtraced::util
