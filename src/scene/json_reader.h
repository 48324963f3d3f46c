// dtraced::scene strict JSON reading, the first half of scene loading (load.h is the second).
//
// Owns: turning text into a boost::json::value under the rules a scene file needs and that
// boost::json::parse alone (Boost 1.81) does not give:
//   - doubles are converted with std::from_chars, so they are correctly rounded. Boost 1.81's
//     own conversion is off by an ulp for about one double in five, which would break the
//     "canonical JSON reloads to the same bits" promise that scene digests rest on;
//   - duplicate keys are reported (Boost keeps the last one silently);
//   - a syntax error is located by line, column, byte offset and the JSON Pointer of the value
//     being read when it happened;
//   - nesting depth is bounded through parse_options::max_depth, never a global.
// It is still Boost.JSON's parser (basic_parser) that reads the text; only the handler that
// builds the value is ours.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <boost/json/storage_ptr.hpp>
#include <boost/json/value.hpp>

namespace dtraced::scene {

// One problem found while reading JSON text; `path` is a JSON Pointer ("" is the document).
struct JsonIssue {
  std::string path;
  std::string message;
};

struct JsonDocument {
  boost::json::value value;  // null when !parsed
  bool parsed = false;       // false after a syntax error: `value` is unusable
  // Syntax error (at most one, parsing stops there) and duplicate keys (all of them, up to
  // `max_issues`). Duplicate keys do not stop parsing; the last occurrence is kept in `value`.
  std::vector<JsonIssue> issues;
};

// Parses `text` as strict RFC 8259 JSON (no comments, no trailing commas, valid UTF-8, nothing
// but whitespace after the document). The value's memory comes from `storage`.
JsonDocument read_json_strict(std::string_view text, std::size_t max_depth, std::size_t max_issues,
                              boost::json::storage_ptr storage = {});

// Escapes one reference token of a JSON Pointer (RFC 6901): '~' -> "~0", '/' -> "~1".
std::string json_pointer_escape(std::string_view token);

// "an object", "an array", "a string", "a boolean", "null" or "a number", for error messages.
std::string_view json_kind_name(const boost::json::value& v);

// The value of a JSON number as a finite double, or nullopt with `error` set ("expected a number,
// got a string", "number is out of range (overflows a double)"). Shared by every strict reader so
// scene files and wire messages treat numbers alike; range checks stay with the caller.
std::optional<double> json_finite_number(const boost::json::value& v, std::string& error);

}  // namespace dtraced::scene
