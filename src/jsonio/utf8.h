// dtraced::jsonio UTF-8: decoding one sequence, for what must check or escape text byte by byte
// (printable() in parse.h, the scene loader's check of OBJ files).
//
// Pure functions: thread-safe.
#pragma once

#include <cstddef>
#include <string_view>

namespace dtraced::jsonio {

struct Utf8Sequence {
  std::size_t length = 0;  // 0: text[i] does not start a valid sequence
  char32_t code_point = 0;
};

// The UTF-8 sequence at text[i] (i < text.size()) under RFC 3629: no overlong forms, no
// surrogates, nothing above U+10FFFF, not cut short by the end of `text`.
Utf8Sequence utf8_at(std::string_view text, std::size_t i);

}  // namespace dtraced::jsonio
