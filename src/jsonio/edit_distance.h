// dtraced::jsonio edit distance: the measure behind every did-you-mean, for unknown keys here
// (reader.h's unknown_key_message) and for unknown verbs and flags on the command line.
//
// A pure function: thread-safe.
#pragma once

#include <cstddef>
#include <string_view>

namespace dtraced::jsonio {

// Levenshtein distance between two names (insertions, deletions and substitutions of bytes).
std::size_t edit_distance(std::string_view a, std::string_view b);

}  // namespace dtraced::jsonio
