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
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

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

// The double parse_strict gives for the JSON number `text` that Boost converted to `boost_value`:
// std::from_chars's, correctly rounded, or Boost's where from_chars has none (out of range).
double precise_double(std::string_view text, double boost_value);

// The parse events of a split array's elements, recorded in order instead of built into values
// (StrictParser::record_elements): a consumer can read an element of a shape it knows straight
// from the events, and build the value (build) of any other, the value parse_strict would have
// built. Keys and strings are whole (their parts joined); a number keeps Boost's value, and a
// double its text too, so that precise_double converts it on the consumer's thread (kDouble), or,
// in a log made with convert_doubles, the parser converts it as it reads it and keeps no text
// (kDoubleValue): for a consumer on the parser's own thread, which would convert it there anyway.
class EventLog {
 public:
  explicit EventLog(bool convert_doubles = false) : convert_doubles_(convert_doubles) {}
  bool converts_doubles() const { return convert_doubles_; }
  enum class Kind : std::uint8_t {
    kObjectBegin,
    kObjectEnd,  // size(): the object's key count
    kArrayBegin,
    kArrayEnd,  // size(): the array's element count
    kKey,       // size(): its text's length, as for kString and kDouble
    kString,
    kInt64,
    kUint64,
    kDouble,
    kBool,
    kNull,
    kDoubleValue,  // a double converted already (a log made with convert_doubles): no text
  };
  struct Event {
    std::uint64_t kind_size = 0;  // the kind in the low 8 bits, the size above
    union {
      double d;
      std::int64_t i;
      std::uint64_t u;
      bool b;
    };
    Kind kind() const { return static_cast<Kind>(kind_size & 0xff); }
    std::uint64_t size() const { return kind_size >> 8; }
  };
  // A place in the log: an element starts at one and ends at the next (or at the log's end).
  struct Mark {
    std::size_t event = 0;
    std::size_t text = 0;
  };

  // The events from one mark to another, in order; text() is the current event's text (a key,
  // a string or a double's digits), empty for the others.
  class Cursor {
   public:
    Cursor(const EventLog& log, Mark from, Mark to) : log_(log), at_(from), end_(to.event) {}
    // The next event, or false at the end.
    bool next() {
      if (at_.event == end_) return false;
      at_.text += text_size_;
      event_ = &log_.events_[at_.event++];
      const Kind k = event_->kind();
      text_size_ = k == Kind::kKey || k == Kind::kString || k == Kind::kDouble ? event_->size() : 0;
      return true;
    }
    // The next event, when it is of kind `k`.
    bool next(Kind k) { return next() && event_->kind() == k; }
    bool done() const { return at_.event == end_; }
    const Event& event() const { return *event_; }
    Kind kind() const { return event_->kind(); }
    std::string_view text() const { return std::string_view(log_.text_.data() + at_.text, text_size_); }
    // A kDouble or kDoubleValue event's double: precise_double of its text and Boost's value, to
    // the bit. A kDoubleValue was converted so when it was recorded; of a kDouble, Boost's value
    // is kept where it is provably correctly rounded already (parse.cpp: few enough digits, a
    // value in [1e-6, 1e21)), which the log's padded texts let it see quickly.
    double double_value() const { return event_->kind() == Kind::kDoubleValue ? event_->d : text_double(); }

   private:
    double text_double() const;  // double_value of a kDouble
    const EventLog& log_;
    Mark at_;
    std::size_t end_;
    const Event* event_ = nullptr;
    std::size_t text_size_ = 0;
  };

  Mark mark() const { return {event_count_, text_size_}; }
  bool empty() const { return event_count_ == 0; }
  // Forgets every event; keeps the memory.
  void clear() {
    event_count_ = 0;
    text_size_ = 0;
    pending_ = 0;
  }
  // The value of the events from `from` to `to` (one whole value), on `storage`; `keys` (if not
  // null) gets the number of keys in the events. The value keeps the last of duplicate keys, so
  // it holds fewer keys than that exactly when the events have a duplicate key.
  boost::json::value build(Mark from, Mark to, boost::json::storage_ptr storage = {},
                           std::size_t* keys = nullptr) const;
  // The duplicate keys in the events from `from` to `to` (one value, or the start of one that a
  // syntax error cut short), reported as StrictParser reports those of a document: "duplicate key
  // ..." at the key's JSON Pointer, which here starts with `path` (the value's own), appended to
  // `out` while it holds fewer than `max_errors`. Returns whether there was one.
  bool duplicate_keys(Mark from, Mark to, std::string_view path, std::size_t max_errors, util::Errors& out) const;
  // The `size` bytes of text that end `end` bytes into the log (a recorded key: StrictParser's
  // path of a syntax error).
  std::string_view text_before(std::size_t end, std::size_t size) const {
    return std::string_view(text_.data() + end - size, size);
  }

  // Recording (the parser's handler).
  void add(Kind k, std::uint64_t size = 0) { push(k, size); }
  void add_int64(std::int64_t i) { push(Kind::kInt64, 0).i = i; }
  void add_uint64(std::uint64_t u) { push(Kind::kUint64, 0).u = u; }
  // A double converted already (kDoubleValue).
  void add_double_value(double d) { push(Kind::kDoubleValue, 0).d = d; }
  void add_bool(bool b) { push(Kind::kBool, 0).b = b; }
  // A part of the next key's, string's or double's text.
  void add_part(std::string_view part) {
    if (text_.size() - text_size_ < part.size() + kTextPadding) grow_text(part.size());
    std::memcpy(text_.data() + text_size_, part.data(), part.size());
    text_size_ += part.size();
    pending_ += part.size();
  }
  // A key, string or double whose text ends with `last` (after the parts added before); returns
  // the size of its whole text.
  std::size_t add_text(Kind k, std::string_view last, double d = 0) {
    add_part(last);
    const std::size_t size = pending_;
    push(k, size).d = d;
    pending_ = 0;
    return size;
  }

 private:
  // The next event, its payload 0 until the caller sets it. Written in place: vector's
  // emplace_back stayed a call, which with a sphere's 35 events took 8 % of a large load.
  Event& push(Kind k, std::uint64_t size) {
    if (event_count_ == events_.size()) grow_events();
    Event& e = events_[event_count_++];
    e.kind_size = (size << 8) | static_cast<std::uint64_t>(k);
    e.u = 0;
    return e;
  }
  void grow_events();
  void grow_text(std::size_t more);
  // Readable bytes kept after the texts: Cursor::double_value reads a text in two 16-byte blocks.
  static constexpr std::size_t kTextPadding = 32;

  // The events: the first event_count_ of events_ (whose size is its capacity).
  std::vector<Event> events_;
  std::size_t event_count_ = 0;
  bool convert_doubles_ = false;
  // The texts, end to end: the first text_size_ bytes of text_ (whose size is its capacity, so
  // that an append is one memcpy, not std::string's out-of-line append).
  std::vector<char> text_;
  std::size_t text_size_ = 0;
  std::size_t pending_ = 0;  // bytes of text added as parts of the next event
};

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

  // Called with each element of the split array as its events in `log`, from `begin` to the log's
  // end (record_elements).
  using EventSink = std::function<void(std::size_t index, const EventLog& log, EventLog::Mark begin)>;

  // Elements of the array under `root_key` of the root object go to `sink`, not into the document.
  // Call before the first write.
  void split_array(std::string root_key, ElementSink sink);
  // The same, but the elements are recorded into `log` (the caller's, alive while the parser
  // writes to it; the sink may clear it, or give another with set_event_log, after an element)
  // and handed over as events: no value is built for them. The same errors as split_array but
  // one kind: duplicate keys inside an element are left to the consumer, which knows most
  // elements have none (a sphere read from the events has each key once) and checks the others
  // with EventLog::duplicate_keys, off the parsing thread; it puts them among the parser's own
  // errors by error_elements(), and finds those of an element a syntax error cut short from
  // open_element(). Call before the first write.
  void record_elements(std::string root_key, EventLog* log, EventSink sink);
  void set_event_log(EventLog* log);
  // For each error of the document (finish()) but a syntax error: how many elements of the split
  // array had begun before it, so that a consumer's errors of element i go before the parser's
  // errors with a count above i, and after the others.
  const std::vector<std::size_t>& error_elements() const;
  // After a syntax error inside an element being recorded: where it began in the log being
  // written then (it runs to that log's end) and its index. Nullopt otherwise.
  std::optional<std::pair<EventLog::Mark, std::size_t>> open_element() const;
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
