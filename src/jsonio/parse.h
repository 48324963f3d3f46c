// dtraced::jsonio strict parsing: JSON text into a boost::json::value under the rules every
// reader of dtraced needs (scene files, wire messages, config files) and that boost::json::parse
// alone (Boost 1.81) does not give:
//   - doubles are converted with std::from_chars, so they are correctly rounded. Boost 1.81's
//     own conversion is off by an ulp for about one double in five, which would break the
//     "canonical JSON reloads to the same bits" promise that scene digests rest on;
//   - duplicate keys are reported (Boost keeps the last one silently): which of two values a
//     writer meant is anyone's guess;
//   - a syntax error is located by line, column, byte offset and the JSON Pointer of the value
//     being read when it happened;
//   - nesting depth is bounded through parse_options::max_depth, never a global.
// It is still Boost.JSON's parser (basic_parser) that reads the text; only the handler that
// builds the value is ours. reader.h reads the value that comes out.
//
// Stateless functions: thread-safe.
#pragma once

#include <cstddef>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include <boost/json/memory_resource.hpp>
#include <boost/json/monotonic_resource.hpp>
#include <boost/json/storage_ptr.hpp>
#include <boost/json/value.hpp>

#include "util/result.h"

namespace dtraced::jsonio {

struct Document {
  boost::json::value value;  // null when !parsed
  bool parsed = false;       // false after a syntax error: `value` is unusable
  // The syntax error (at most one: parsing stops there) and duplicate keys (all of them, up to
  // `max_errors`), each with `path` the JSON Pointer of the value at fault and `file` empty.
  // Duplicate keys do not stop parsing; the last occurrence is kept in `value`.
  util::Errors errors;
};

// Parses `text` as strict RFC 8259 JSON (no comments, no trailing commas, valid UTF-8, nothing
// but whitespace after the document), at most `max_depth` levels deep. The value's memory comes
// from `storage`.
Document parse_strict(std::string_view text, std::size_t max_depth, std::size_t max_errors,
                      boost::json::storage_ptr storage = {});

// parse_strict for text that arrives in pieces (a large file read a block at a time), with one
// more feature for documents too large to hold as a tree: the elements of one array just below the
// root object (e.g. "scene_objects") can be handed to a callback one at a time, as each completes,
// instead of being kept; the document then holds an empty array under that key. Same rules, same
// errors (a syntax error's line, column and byte count from the start of the whole text) as
// parse_strict. One parser per document; not thread-safe.
class StrictParser {
 public:
  // Called with each element of the split array and its index. The sink may move the value out
  // when its memory is the caller's (set_element_storage); otherwise it lives only for the call.
  using ElementSink = std::function<void(std::size_t index, boost::json::value& element)>;

  StrictParser(std::size_t max_depth, std::size_t max_errors, boost::json::storage_ptr storage = {});
  ~StrictParser();
  StrictParser(const StrictParser&) = delete;
  StrictParser& operator=(const StrictParser&) = delete;

  // Elements of the array under `root_key` of the root object go to `sink`, not into the document.
  // Call before the first write.
  void split_array(std::string root_key, ElementSink sink);
  // Where the next elements of the split array are built (null: the parser's own memory, reused
  // element after element). The caller owns `memory` and keeps it alive as long as the values
  // built on it; it may change it at any time, also from within the sink (then it applies from
  // the next element on).
  // A monotonic resource (its deallocation is a no-op, so destroying the values built on it costs
  // nothing: Boost.JSON skips walking them).
  void set_element_storage(boost::json::monotonic_resource* memory);
  // Whether an array under the split key was met (and its elements went to the sink).
  bool split_seen() const;
  // The next piece of the text. Returns false once the text has a syntax error (then stop
  // writing: finish() reports it).
  bool write(std::string_view piece);
  // The end of the text: the document, or the syntax error.
  Document finish();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Escapes one reference token of a JSON Pointer (RFC 6901): '~' -> "~0", '/' -> "~1".
std::string pointer_escape(std::string_view token);

// `text` made safe to print in a message, a log line or on a terminal. A scene's keys and
// strings are echoed in errors, and raw they could end a line and forge the next one, or carry
// a terminal escape sequence. So, JSON-style: a backslash becomes "\\" (so that every escape
// in the output means one), \n \r \t stay short, and the other C0 controls, DEL, the C1
// controls (U+0080..U+009F, some terminals obey U+009B as CSI), the line and paragraph
// separators U+2028/U+2029 and the bidirectional controls (U+200E, U+200F, U+202A..U+202E,
// U+2066..U+2069, which reorder what a reader sees) become \uXXXX. A byte that does not start
// valid UTF-8 becomes \xNN. Everything else, including other non-ASCII text, is kept.
std::string printable(std::string_view text);

// `text` in double quotes for a message: printable(), with '"' escaped as well, and at most
// `max_bytes` of `text` (longer ones are cut at a character boundary and marked with "...").
std::string quoted(std::string_view text, std::size_t max_bytes = 200);

// "an object", "an array", "a string", "a boolean", "null" or "a number", for error messages.
std::string_view kind_name(const boost::json::value& v);

// `d` as a JSON value that prints exactly: integral values within 2^53 as integers ("640", not
// Boost's "6.4E2"; they convert back to the identical double), others by Boost's Ryu, the
// shortest digits that read back (correctly rounded, as parse_strict reads them) to the same
// double. -0 prints as 0: every reader here turns -0 into +0 anyway.
boost::json::value exact_number(double d, boost::json::storage_ptr storage = {});

}  // namespace dtraced::jsonio
