// dtraced::jsonio writer: the one way dtraced turns a boost::json::value into text for people
// and for the wire (collector answers, `status --json`, `list --json`, `workers --json`).
//
// Owns: number formatting. boost::json::serialize (Boost 1.81) writes every double in its own
// exponent form ("1.5E0", "2.5E-1"), which jq users and people reading `status --json` dislike,
// and writes non-finite doubles as `Infinity` and `NaN`, which are not JSON. Here a double is
// written as the shortest decimal that reads back to the same double (correctly rounded, as
// parse_strict reads it):
//   - plain when 1e-6 <= |d| < 1e16 ("1.5", "0.25", "120", "0.000001"): an integral double
//     prints without a fraction, so it reads back as an integer of the same value (JSON does
//     not tell them apart, and reader.h accepts an integer wherever it wants a double);
//   - with an exponent outside that range, where plain would be absurd ("1e+20", "5e-324");
//   - zero as "0", and -0 as "-0.0" so that its sign survives a round trip;
//   - a non-finite double (which no encoder should produce) as `null`, so the text is always
//     JSON and a reader that wants a number names the field instead of failing on a syntax error.
// Strings are escaped by Boost.JSON; integers are written in full (int64 and uint64).
// Nesting is walked with an explicit stack, so a deep value cannot overflow the call stack.
//
// Stateless functions: thread-safe.
#pragma once

#include <string>

#include <boost/json/value.hpp>

namespace dtraced::jsonio {

// `v` as compact JSON text (no whitespace), objects in their stored key order.
std::string to_text(const boost::json::value& v);

// Appends `d` as written by to_text (see the rules above).
void append_number(std::string& out, double d);

}  // namespace dtraced::jsonio
