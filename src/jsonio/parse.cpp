#include "jsonio/parse.h"

#include <algorithm>
#include <array>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <memory>
#include <system_error>
#include <utility>
#include <vector>

// basic_parser's member definitions live in this header; it must be included by exactly the
// translation units that instantiate basic_parser with their own handler (this one).
#include <boost/json/basic_parser_impl.hpp>
#include <boost/json/error.hpp>
#include <boost/json/monotonic_resource.hpp>
#include <boost/json/object.hpp>
#include <boost/json/string.hpp>
#include <boost/json/value_stack.hpp>
#include <boost/version.hpp>
#if defined(__SSE2__)
#include <emmintrin.h>
#endif
#include <fmt/format.h>

#include "jsonio/utf8.h"

namespace dtraced::jsonio {
namespace {

namespace json = boost::json;

// Keys of one object are compared linearly for duplicates. No object dtraced reads has more than
// a handful of keys; past this many the object is wrong anyway (every extra key is an unknown-key
// error later), so duplicate tracking stops instead of going quadratic on hostile input.
constexpr std::size_t kMaxTrackedKeys = 64;

bool boost_value_is_exact(const char* p, std::size_t n, double boost_value);

// The double of the number `text` whose Boost value is `boost_value`: Boost's where it is exact,
// else from_chars's. `text` must be readable 32 bytes past its start (boost_value_is_exact).
double padded_double(std::string_view text, double boost_value) {
  return boost_value_is_exact(text.data(), text.size(), boost_value) ? boost_value : precise_double(text, boost_value);
}

// Where the parser is inside the document, so an error can name a JSON Pointer.
struct Frame {
  bool is_array = false;
  std::size_t index = 0;  // array: index of the element being read
  bool has_key = false;   // object: a key was read and its value is being read
  // The key being read: the last of seen_text when it was new there (no copy), else `own_key`.
  bool key_is_last_seen = false;
  std::string own_key;
  // A frame of a recorded element: its key is the log's text that ends log_key_end bytes in
  // (no copy, and no duplicate check: see StrictParser::record_elements).
  bool key_in_log = false;
  std::size_t log_key_end = 0;
  std::size_t log_key_size = 0;
  // The keys read so far, end to end (no string apiece: a large scene has millions of objects).
  std::string seen_text;
  std::vector<std::size_t> seen_ends;  // where each ends in seen_text

  std::string_view key() const {
    if (!key_is_last_seen) return own_key;
    const std::size_t begin = seen_ends.size() > 1 ? seen_ends[seen_ends.size() - 2] : 0;
    return std::string_view(seen_text).substr(begin, seen_ends.back() - begin);
  }

  bool seen(std::string_view key) const {
    std::size_t begin = 0;
    for (const std::size_t end : seen_ends) {
      if (std::string_view(seen_text).substr(begin, end - begin) == key) return true;
      begin = end;
    }
    return false;
  }
};

// The basic_parser handler: builds the value with Boost's value_stack (as boost::json::parser
// does) while keeping a path stack. Returning true everywhere: no callback aborts parsing.
class StrictHandler {
 public:
  static constexpr std::size_t max_object_size = json::object::max_size();
  static constexpr std::size_t max_array_size = json::array::max_size();
  static constexpr std::size_t max_key_size = json::string::max_size();
  static constexpr std::size_t max_string_size = json::string::max_size();

  // The value stack's scratch space comes from the same storage as the value: with the
  // loader's arena, growing it for a 100k-element array costs no heap churn.
  StrictHandler(json::storage_ptr storage, std::size_t max_errors) : stack_(storage), max_errors_(max_errors) {
    stack_.reset(std::move(storage));
  }

  // See StrictParser::split_array.
  void split_array(std::string key, StrictParser::ElementSink sink) {
    split_key_ = std::move(key);
    sink_ = std::move(sink);
  }
  void record_elements(std::string key, EventLog* log, StrictParser::EventSink sink) {
    split_key_ = std::move(key);
    event_sink_ = std::move(sink);
    log_ = log;
  }
  void set_event_log(EventLog* log) { log_ = log; }
  // The end of the piece being parsed: the text of a number that ends 32 bytes or more before it
  // is read in place by boost_value_is_exact.
  void set_piece_end(const char* end) { piece_end_ = end; }
  bool split_seen() const { return split_seen_; }
  void set_element_storage(json::monotonic_resource* memory) { element_storage_ = memory; }

  bool on_document_begin(json::error_code&) { return true; }
  bool on_document_end(json::error_code&) { return true; }

  bool on_array_begin(json::error_code&) {
    begin_element();
    // The split array: a root object's member under the split key.
    if ((sink_ || event_sink_) && depth_ == 1 && !frames_[0].is_array && frames_[0].has_key &&
        frames_[0].key() == split_key_) {
      in_split_ = true;
      split_seen_ = true;
    }
    if (recording()) log_->add(EventLog::Kind::kArrayBegin);
    return open(/* is_array = */ true);
  }
  bool on_array_end(std::size_t n, json::error_code&) {
    if (in_split_ && !in_element_ && depth_ == kSplitDepth) {
      stack_.push_array(0);  // its elements went to the sink
      in_split_ = false;
    } else if (recording()) {
      log_->add(EventLog::Kind::kArrayEnd, n);
    } else {
      stack().push_array(n);
    }
    return close();
  }
  bool on_object_begin(json::error_code&) {
    begin_element();
    if (recording()) log_->add(EventLog::Kind::kObjectBegin);
    return open(/* is_array = */ false);
  }
  bool on_object_end(std::size_t n, json::error_code&) {
    if (recording()) {
      log_->add(EventLog::Kind::kObjectEnd, n);
    } else {
      stack().push_object(n);
    }
    return close();
  }

  bool on_string_part(json::string_view s, std::size_t, json::error_code&) {
    begin_element();
    if (recording()) {
      log_->add_part(view(s));
    } else {
      stack().push_chars(s);
    }
    return true;
  }
  bool on_string(json::string_view s, std::size_t, json::error_code&) {
    begin_element();
    if (recording()) {
      log_->add_text(EventLog::Kind::kString, view(s));
    } else {
      stack().push_string(s);
    }
    return value_done();
  }
  bool on_key_part(json::string_view s, std::size_t, json::error_code&) {
    if (recording()) {
      log_->add_part(view(s));
      return true;
    }
    stack().push_chars(s);
    key_part_.append(s.data(), s.size());
    return true;
  }
  bool on_key(json::string_view s, std::size_t, json::error_code&) {
    if (recording()) {
      const std::size_t size = log_->add_text(EventLog::Kind::kKey, view(s));
      Frame& f = frames_[depth_ - 1];
      f.has_key = true;
      f.key_in_log = true;
      f.log_key_end = log_->mark().text;
      f.log_key_size = size;
      return true;
    }
    stack().push_key(s);
    if (key_part_.empty()) {  // the whole key in one piece (nearly always): no copy
      key_read(view(s));
    } else {
      key_part_.append(s.data(), s.size());
      key_read(key_part_);
      key_part_.clear();
    }
    return true;
  }

  bool on_number_part(json::string_view s, json::error_code&) {
    number_part_.append(s.data(), s.size());
    return true;
  }
  bool on_int64(std::int64_t i, json::string_view, json::error_code&) {
    number_part_.clear();
    begin_element();
    if (recording()) {
      log_->add_int64(i);
    } else {
      stack().push_int64(i);
    }
    return value_done();
  }
  bool on_uint64(std::uint64_t u, json::string_view, json::error_code&) {
    number_part_.clear();
    begin_element();
    if (recording()) {
      log_->add_uint64(u);
    } else {
      stack().push_uint64(u);
    }
    return value_done();
  }
  bool on_double(double boost_value, json::string_view s, json::error_code&) {
    begin_element();
    if (recording() && log_->converts_doubles()) {
      log_->add_double_value(converted(s, boost_value));
    } else if (recording()) {
      // Converted by the consumer (precise_double), from the text.
      if (!number_part_.empty()) {
        log_->add_part(number_part_);
        number_part_.clear();
      }
      log_->add_text(EventLog::Kind::kDouble, view(s), boost_value);
    } else if (number_part_.empty()) {  // the whole number in one piece (nearly always): no copy
      stack().push_double(precise_double(std::string_view(s.data(), s.size()), boost_value));
    } else {
      number_part_.append(s.data(), s.size());
      stack().push_double(precise_double(number_part_, boost_value));
      number_part_.clear();
    }
    return value_done();
  }
  bool on_bool(bool b, json::error_code&) {
    begin_element();
    if (recording()) {
      log_->add_bool(b);
    } else {
      stack().push_bool(b);
    }
    return value_done();
  }
  bool on_null(json::error_code&) {
    begin_element();
    if (recording()) {
      log_->add(EventLog::Kind::kNull);
    } else {
      stack().push_null();
    }
    return value_done();
  }
  // Comments are disabled in parse_options; these only satisfy the handler concept.
  bool on_comment_part(json::string_view, json::error_code&) { return true; }
  bool on_comment(json::string_view, json::error_code&) { return true; }

  json::value release() { return stack_.release(); }
  util::Errors& errors() { return errors_; }
  const std::vector<std::size_t>& error_elements() const { return error_elements_; }
  std::optional<std::pair<EventLog::Mark, std::size_t>> open_element() const {
    if (!in_element_ || log_ == nullptr) return std::nullopt;
    return std::pair(element_begin_, element_index_);
  }

  // JSON Pointer of the value being read now (or of the container, between values).
  std::string current_path() const {
    std::string path;
    for (std::size_t i = 0; i < depth_; ++i) {
      const Frame& f = frames_[i];
      if (f.is_array) {
        path += fmt::format("/{}", f.index);
      } else if (f.has_key) {
        path += '/';
        path += printable(pointer_escape(f.key_in_log ? log_->text_before(f.log_key_end, f.log_key_size) : f.key()));
      }
    }
    return path;
  }

 private:
  static std::string_view view(json::string_view s) { return std::string_view(s.data(), s.size()); }
  // The double of the number whose text ends with `s` (after number_part_), as
  // EventLog::Cursor::double_value gives it for a recorded text; clears number_part_.
  double converted(json::string_view s, double boost_value) {
    if (number_part_.empty() && piece_end_ != nullptr && piece_end_ - s.data() >= 32) {
      return padded_double(view(s), boost_value);
    }
    number_part_.append(s.data(), s.size());
    // Copied with the padding the check reads.
    std::array<char, 64> padded{};
    double d = 0;
    if (number_part_.size() <= 31) {
      std::memcpy(padded.data(), number_part_.data(), number_part_.size());
      d = padded_double(std::string_view(padded.data(), number_part_.size()), boost_value);
    } else {
      d = precise_double(number_part_, boost_value);
    }
    number_part_.clear();
    return d;
  }
  // Whether the value being read is an element of the split array recorded as events.
  bool recording() const { return in_element_ && log_ != nullptr; }

  // Frames are reused rather than popped, so a large document does not reallocate key vectors
  // for every object.
  bool open(bool is_array) {
    if (depth_ == frames_.size()) frames_.emplace_back();
    Frame& f = frames_[depth_++];
    f.is_array = is_array;
    f.index = 0;
    f.has_key = false;
    f.key_is_last_seen = false;
    f.key_in_log = false;
    f.own_key.clear();
    f.seen_text.clear();
    f.seen_ends.clear();
    return true;
  }
  bool close() {
    --depth_;
    return value_done();
  }

  void key_read(std::string_view key) {
    Frame& f = frames_[depth_ - 1];
    f.has_key = true;
    if (f.seen_ends.size() < kMaxTrackedKeys && !f.seen(key)) {
      f.seen_text.append(key.data(), key.size());
      f.seen_ends.push_back(f.seen_text.size());
      f.key_is_last_seen = true;
      return;
    }
    f.own_key.assign(key.data(), key.size());
    f.key_is_last_seen = false;
    if (f.seen_ends.size() >= kMaxTrackedKeys) return;
    if (errors_.size() < max_errors_) {
      errors_.push_back({fmt::format("duplicate key {}", quoted(f.key())), current_path()});
      error_elements_.push_back(element_index_);
    }
  }

  // Depth (frames open) inside the split array: the root object's and the array's.
  static constexpr std::size_t kSplitDepth = 2;
  static constexpr std::size_t kElementBuffer = std::size_t(64) << 10;

  json::value_stack& stack() { return in_element_ ? element_stack_ : stack_; }

  // A value starts: if it is an element of the split array, it is built on its own stack (or
  // recorded, from the log's end on).
  void begin_element() {
    if (!in_split_ || in_element_ || depth_ != kSplitDepth) return;
    in_element_ = true;
    if (log_ != nullptr) {
      element_begin_ = log_->mark();
      return;
    }
    // From the concrete monotonic_resource type, so that the storage_ptr knows deallocation is a
    // no-op: the values' destructors then return at once instead of walking every element.
    element_stack_.reset(json::storage_ptr(element_storage_ != nullptr ? element_storage_ : &element_memory_));
  }

  // A value is complete: an element of the split array goes to the sink, and its memory is reused.
  void end_element() {
    if (!in_element_ || depth_ != kSplitDepth) return;
    in_element_ = false;
    if (log_ != nullptr) {
      event_sink_(element_index_++, *log_, element_begin_);
      return;
    }
    {
      json::value element = element_stack_.release();
      sink_(element_index_++, element);
    }
    if (element_storage_ == nullptr) element_memory_.release();
  }

  // A value (scalar or closed container) is complete: advance the enclosing container.
  bool value_done() {
    end_element();
    if (depth_ == 0) return true;
    Frame& f = frames_[depth_ - 1];
    if (f.is_array) {
      ++f.index;
    } else {
      f.has_key = false;
    }
    return true;
  }

  json::value_stack stack_;
  // The split array (StrictParser::split_array): its key, where its elements go, and the element
  // being built.
  std::string split_key_;
  StrictParser::ElementSink sink_;
  StrictParser::EventSink event_sink_;  // record_elements: the elements go here as events in log_
  EventLog* log_ = nullptr;
  const char* piece_end_ = nullptr;  // set_piece_end
  EventLog::Mark element_begin_;
  bool split_seen_ = false;
  bool in_split_ = false;
  bool in_element_ = false;
  std::size_t element_index_ = 0;
  // The first 64 KiB of every element come from this one buffer, reused (release() keeps it).
  std::unique_ptr<unsigned char[]> element_buffer_ = std::make_unique<unsigned char[]>(kElementBuffer);
  json::monotonic_resource element_memory_{element_buffer_.get(), kElementBuffer};
  json::monotonic_resource* element_storage_ = nullptr;  // the caller's (set_element_storage), else element_memory_
  json::value_stack element_stack_;
  std::vector<Frame> frames_;
  std::size_t depth_ = 0;
  std::string key_part_;
  std::string number_part_;
  util::Errors errors_;
  std::vector<std::size_t> error_elements_;  // per error: element_index_ then
  std::size_t max_errors_;
};

std::string describe_parse_error(const json::error_code& ec, std::size_t max_depth) {
  if (ec == json::error::too_deep) return fmt::format("nesting is deeper than the limit of {} levels", max_depth);
  if (ec == json::error::extra_data) return "unexpected data after the JSON document";
  if (ec == json::error::incomplete) return "unexpected end of input";
  return ec.message();
}

}  // namespace

namespace {

// Whether Boost's value `boost_value` of the JSON number `p` (n bytes, with p[0] to p[31]
// readable: a log's padded text, see EventLog, or a piece with 32 bytes left) is correctly
// rounded already. Boost 1.81 (basic_parser_impl.hpp: parse_number,
// dec_to_float) keeps the digits of the text in a 64-bit mantissa m, dropping digits only once m
// passes 2^53 - 1, and gives (double)m * 10^e, or (double)m / 10^-e for -22 <= e < 0, where e is
// the exponent written less the digits after the point. With m <= 2^53 and |e| <= 22 both
// operands are exact doubles (10^22 is the largest exact power of ten), so that one operation
// rounds the exact value once, correctly: from_chars's result to the bit.
//   m <= 2^53: at most 15 digits, or 16 with the first below 9 (< 9 * 10^15 < 2^53); leading
// zeros count as digits, which only makes the test stricter. Then no digit was dropped.
//   |e| <= 22: from Boost's value, not the text. With 1 <= m < 10^16, a value in [1e-6, 1e21)
// means e is in [-22, 21] (a smaller e gives at most 9.01e15 * 10^-23 < 1e-6, a larger one at
// least 1e22, or Inf; m = 0 gives 0, or NaN for an exponent past 308: rejected too).
// 2 in 3 of the doubles of a generated sphere scene pass (16 digits or fewer: the shortest form
// that reads back), and from_chars had taken a fifth of its load. The 'e' and the '.' are found
// with two 16-byte compares and the exponent is never read: a loop over the characters (its exits
// fall at lengths that vary from number to number) saved nothing (0.99 of the load's CPU), and
// reading the exponent's digits at the position found cost 3 % of it more than this. Other Boost
// versions convert differently: every number goes to from_chars there.
bool boost_value_is_exact(const char* p, std::size_t n, double boost_value) {
#if BOOST_VERSION == 108100 && defined(__SSE2__)
  const double magnitude = std::abs(boost_value);
  if (!(magnitude >= 1e-6 && magnitude < 1e21) || n > 31) return false;
  const __m128i lo = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p));
  const __m128i hi = _mm_loadu_si128(reinterpret_cast<const __m128i*>(p + 16));
  const auto find = [](__m128i a, __m128i b, __m128i c) {
    const auto low = static_cast<std::uint32_t>(_mm_movemask_epi8(_mm_cmpeq_epi8(a, c)));
    const auto high = static_cast<std::uint32_t>(_mm_movemask_epi8(_mm_cmpeq_epi8(b, c)));
    return low | high << 16;
  };
  const std::uint32_t in_text = (std::uint32_t{1} << n) - 1;
  const std::uint32_t dot = find(lo, hi, _mm_set1_epi8('.')) & in_text;
  // 'E' | 0x20 is 'e', and no other character of a number becomes 'e' so.
  const __m128i case_bit = _mm_set1_epi8(0x20);
  const std::uint32_t e = find(_mm_or_si128(lo, case_bit), _mm_or_si128(hi, case_bit), _mm_set1_epi8('e')) & in_text;
  const int sign = p[0] == '-';
  const int mark = e != 0 ? std::countr_zero(e) : static_cast<int>(n);  // where the exponent starts
  const int digits = mark - sign - (dot != 0);
  return digits < 16 || (digits == 16 && p[sign] <= '8');
#else
  (void)p;
  (void)n;
  (void)boost_value;
  return false;
#endif
}

}  // namespace

double EventLog::Cursor::text_double() const { return padded_double(text(), event_->d); }

double precise_double(std::string_view text, double boost_value) {
  // from_chars is correctly rounded; Boost 1.81's conversion is not (see the header).
  double d = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), d, std::chars_format::general);
  // On overflow/underflow from_chars leaves `d` alone; Boost's value (+-inf, or a value near
  // zero) is then the right one, and the reader reports the out-of-range number by path.
  if (ec != std::errc() || end != text.data() + text.size()) return boost_value;
  return d;
}

void EventLog::grow_events() { events_.resize(std::max(std::size_t(256), 2 * events_.size())); }

void EventLog::grow_text(std::size_t more) {
  text_.resize(std::max({std::size_t(4096), 2 * text_.size(), text_size_ + more + kTextPadding}));
}

json::value EventLog::build(Mark from, Mark to, json::storage_ptr storage, std::size_t* keys) const {
  // The value_stack the parser's handler builds with, fed the same events: the same value.
  json::value_stack stack(storage);
  stack.reset(std::move(storage));
  std::size_t key_count = 0;
  Cursor c(*this, from, to);
  while (c.next()) {
    const Event& e = c.event();
    switch (e.kind()) {
      case Kind::kObjectBegin:
      case Kind::kArrayBegin:
        break;
      case Kind::kObjectEnd:
        stack.push_object(e.size());
        break;
      case Kind::kArrayEnd:
        stack.push_array(e.size());
        break;
      case Kind::kKey:
        stack.push_key(c.text());
        ++key_count;
        break;
      case Kind::kString:
        stack.push_string(c.text());
        break;
      case Kind::kInt64:
        stack.push_int64(e.i);
        break;
      case Kind::kUint64:
        stack.push_uint64(e.u);
        break;
      case Kind::kDouble:
      case Kind::kDoubleValue:
        stack.push_double(c.double_value());
        break;
      case Kind::kBool:
        stack.push_bool(e.b);
        break;
      case Kind::kNull:
        stack.push_null();
        break;
    }
  }
  if (keys != nullptr) *keys = key_count;
  return stack.release();
}

bool EventLog::duplicate_keys(Mark from, Mark to, std::string_view path, std::size_t max_errors,
                              util::Errors& out) const {
  // The parser's Frame and key_read, on the events: the same keys tracked, the same paths.
  struct Level {
    bool is_array = false;
    std::size_t index = 0;
    bool has_key = false;
    std::string_view key;
    std::vector<std::string_view> seen;
  };
  std::vector<Level> levels;
  bool found = false;
  const auto value_done = [&levels] {
    if (levels.empty()) return;
    Level& l = levels.back();
    if (l.is_array) {
      ++l.index;
    } else {
      l.has_key = false;
    }
  };
  Cursor c(*this, from, to);
  while (c.next()) {
    switch (c.kind()) {
      case Kind::kObjectBegin:
      case Kind::kArrayBegin:
        levels.push_back({c.kind() == Kind::kArrayBegin, 0, false, {}, {}});
        break;
      case Kind::kObjectEnd:
      case Kind::kArrayEnd:
        levels.pop_back();
        value_done();
        break;
      case Kind::kKey: {
        Level& l = levels.back();
        l.has_key = true;
        l.key = c.text();
        if (l.seen.size() >= kMaxTrackedKeys) break;
        if (std::find(l.seen.begin(), l.seen.end(), l.key) == l.seen.end()) {
          l.seen.push_back(l.key);
          break;
        }
        found = true;
        if (out.size() >= max_errors) break;
        std::string at(path);
        for (const Level& up : levels) {
          if (up.is_array) {
            at += fmt::format("/{}", up.index);
          } else if (up.has_key) {
            at += '/';
            at += printable(pointer_escape(up.key));
          }
        }
        out.push_back({fmt::format("duplicate key {}", quoted(l.key)), std::move(at)});
        break;
      }
      default:
        value_done();
        break;
    }
  }
  return found;
}

Utf8Sequence utf8_at(std::string_view text, std::size_t i) {
  const auto c = static_cast<unsigned char>(text[i]);
  if (c < 0x80) return {1, c};
  std::size_t n = 0;
  unsigned lo = 0x80, hi = 0xBF;  // allowed range of the second byte
  char32_t cp = 0;
  if (c >= 0xC2 && c <= 0xDF) {
    n = 1;
    cp = c & 0x1F;
  } else if (c >= 0xE0 && c <= 0xEF) {
    n = 2;
    cp = c & 0x0F;
    if (c == 0xE0) lo = 0xA0;
    if (c == 0xED) hi = 0x9F;
  } else if (c >= 0xF0 && c <= 0xF4) {
    n = 3;
    cp = c & 0x07;
    if (c == 0xF0) lo = 0x90;
    if (c == 0xF4) hi = 0x8F;
  } else {
    return {};
  }
  if (i + n >= text.size()) return {};
  for (std::size_t k = 1; k <= n; ++k) {
    const auto b = static_cast<unsigned char>(text[i + k]);
    if (k == 1 ? (b < lo || b > hi) : (b < 0x80 || b > 0xBF)) return {};
    cp = (cp << 6) | (b & 0x3F);
  }
  return {n + 1, cp};
}

std::string pointer_escape(std::string_view token) {
  std::string out;
  out.reserve(token.size());
  for (const char c : token) {
    if (c == '~') {
      out += "~0";
    } else if (c == '/') {
      out += "~1";
    } else {
      out += c;
    }
  }
  return out;
}

namespace {

// Whether code point `cp` is shown as an escape (see printable() in the header).
bool must_escape(char32_t cp) {
  return cp < 0x20 || (cp >= 0x7F && cp <= 0x9F) || cp == 0x200E || cp == 0x200F || cp == 0x2028 || cp == 0x2029 ||
         (cp >= 0x202A && cp <= 0x202E) || (cp >= 0x2066 && cp <= 0x2069);
}

void append_printable(std::string& out, std::string_view text, bool escape_quote) {
  for (std::size_t i = 0; i < text.size();) {
    const auto [n, cp] = utf8_at(text, i);
    if (n == 0) {
      out += fmt::format("\\x{:02x}", static_cast<unsigned char>(text[i]));
      ++i;
      continue;
    }
    if (cp == '\\' || (escape_quote && cp == '"')) {
      out += '\\';
      out += static_cast<char>(cp);
    } else if (cp == '\n') {
      out += "\\n";
    } else if (cp == '\r') {
      out += "\\r";
    } else if (cp == '\t') {
      out += "\\t";
    } else if (must_escape(cp)) {
      out += fmt::format("\\u{:04x}", static_cast<std::uint32_t>(cp));
    } else {
      out.append(text.substr(i, n));
    }
    i += n;
  }
}

}  // namespace

std::string printable(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  append_printable(out, text, /*escape_quote=*/false);
  return out;
}

std::string quoted(std::string_view text, std::size_t max_bytes) {
  std::size_t keep = text.size();
  if (keep > max_bytes) {
    keep = 0;
    while (keep < text.size()) {
      const std::size_t n = std::max<std::size_t>(1, utf8_at(text, keep).length);
      if (keep + n > max_bytes) break;
      keep += n;
    }
  }
  std::string out = "\"";
  append_printable(out, text.substr(0, keep), /*escape_quote=*/true);
  out += keep < text.size() ? "...\"" : "\"";
  return out;
}

struct StrictParser::Impl {
  Impl(std::size_t max_depth_, std::size_t max_errors, json::storage_ptr storage)
      : max_depth(max_depth_), parser(options(max_depth_), std::move(storage), max_errors) {}
  static json::parse_options options(std::size_t max_depth) {
    json::parse_options o;
    o.max_depth = max_depth;  // the other options already default to strict JSON
    return o;
  }
  // The syntax error `ec` found `consumed` bytes into `piece`.
  void fail(std::string_view piece, std::size_t consumed, const json::error_code& ec) {
    const std::string_view before = piece.substr(0, std::min(consumed, piece.size()));
    const std::size_t newlines = static_cast<std::size_t>(std::count(before.begin(), before.end(), '\n'));
    const std::size_t last = before.rfind('\n');
    const std::size_t start = last == std::string_view::npos ? line_start : offset + last + 1;
    auto& handler = parser.handler();
    handler.errors().push_back(
        {fmt::format("invalid JSON at line {}, column {} (byte {}): {}", line + newlines, offset + consumed - start + 1,
                     offset + consumed, describe_parse_error(ec, max_depth)),
         handler.current_path()});
    failed = true;
  }

  std::size_t max_depth;
  json::basic_parser<StrictHandler> parser;
  std::size_t offset = 0;      // bytes of the pieces before this one
  std::size_t line = 1;        // line at `offset`
  std::size_t line_start = 0;  // offset of that line's first byte
  bool failed = false;
};

StrictParser::StrictParser(std::size_t max_depth, std::size_t max_errors, json::storage_ptr storage)
    : impl_(std::make_unique<Impl>(max_depth, max_errors, std::move(storage))) {}

StrictParser::~StrictParser() = default;

void StrictParser::split_array(std::string root_key, ElementSink sink) {
  impl_->parser.handler().split_array(std::move(root_key), std::move(sink));
}

bool StrictParser::split_seen() const { return impl_->parser.handler().split_seen(); }

void StrictParser::record_elements(std::string root_key, EventLog* log, EventSink sink) {
  impl_->parser.handler().record_elements(std::move(root_key), log, std::move(sink));
}

void StrictParser::set_event_log(EventLog* log) { impl_->parser.handler().set_event_log(log); }

const std::vector<std::size_t>& StrictParser::error_elements() const {
  return impl_->parser.handler().error_elements();
}

std::optional<std::pair<EventLog::Mark, std::size_t>> StrictParser::open_element() const {
  if (!impl_->failed) return std::nullopt;
  return impl_->parser.handler().open_element();
}

void StrictParser::set_element_storage(boost::json::monotonic_resource* memory) {
  impl_->parser.handler().set_element_storage(memory);
}

bool StrictParser::write(std::string_view piece) {
  Impl& im = *impl_;
  if (im.failed) return false;
  json::error_code ec;
  im.parser.handler().set_piece_end(piece.data() + piece.size());
  const std::size_t consumed = im.parser.write_some(/* more = */ true, piece.data(), piece.size(), ec);
  if (!ec && consumed != piece.size()) ec = json::error::extra_data;
  if (ec) {
    im.fail(piece, consumed, ec);
    return false;
  }
  // Found forwards, by memchr: rfind goes back a byte at a time, and std::count widens every byte,
  // which through a 1 MiB piece without a newline (a scene written on one line) took 8 % and then
  // 6 % of a large scene's parsing thread.
  std::size_t last = std::string_view::npos;
  for (std::size_t at = piece.find('\n'); at != std::string_view::npos; at = piece.find('\n', at + 1)) {
    ++im.line;
    last = at;
  }
  if (last != std::string_view::npos) im.line_start = im.offset + last + 1;
  im.offset += piece.size();
  return true;
}

Document StrictParser::finish() {
  Impl& im = *impl_;
  auto& handler = im.parser.handler();
  if (!im.failed) {
    json::error_code ec;
    im.parser.write_some(/* more = */ false, nullptr, 0, ec);
    if (ec) im.fail({}, 0, ec);
  }
  if (im.failed) return Document{json::value(), /* parsed = */ false, std::move(handler.errors())};
  return Document{handler.release(), /* parsed = */ true, std::move(handler.errors())};
}

Document parse_strict(std::string_view text, std::size_t max_depth, std::size_t max_errors, json::storage_ptr storage) {
  json::parse_options options;
  options.max_depth = max_depth;  // the other options already default to strict JSON

  json::basic_parser<StrictHandler> parser(options, std::move(storage), max_errors);
  json::error_code ec;
  const std::size_t consumed = parser.write_some(/* more = */ false, text.data(), text.size(), ec);
  if (!ec && consumed != text.size()) ec = json::error::extra_data;

  if (ec) {
    // Line and column count from 1; the column counts bytes, which is what editors show for
    // ASCII and close enough otherwise.
    const std::string_view before = text.substr(0, std::min(consumed, text.size()));
    const std::size_t line = 1 + static_cast<std::size_t>(std::count(before.begin(), before.end(), '\n'));
    const std::size_t line_start = before.rfind('\n') == std::string_view::npos ? 0 : before.rfind('\n') + 1;
    const std::size_t column = consumed - line_start + 1;
    auto& handler = parser.handler();
    // The syntax error is pushed past the error limit if need be: it is the one that matters.
    handler.errors().push_back({fmt::format("invalid JSON at line {}, column {} (byte {}): {}", line, column, consumed,
                                            describe_parse_error(ec, max_depth)),
                                handler.current_path()});
    return Document{json::value(), /* parsed = */ false, std::move(handler.errors())};
  }
  // Constructed, not assigned: assigning into a value with the default storage would deep-copy
  // the whole tree out of the caller's arena.
  return Document{parser.handler().release(), /* parsed = */ true, std::move(parser.handler().errors())};
}

std::string_view kind_name(const json::value& v) {
  switch (v.kind()) {
    case json::kind::object:
      return "an object";
    case json::kind::array:
      return "an array";
    case json::kind::string:
      return "a string";
    case json::kind::bool_:
      return "a boolean";
    case json::kind::null:
      return "null";
    default:
      return "a number";
  }
}

json::value exact_number(double d, json::storage_ptr storage) {
  constexpr double kExactIntegers = 9007199254740992.0;  // 2^53
  if (d == std::floor(d) && std::abs(d) <= kExactIntegers) {
    return json::value(static_cast<std::int64_t>(d), std::move(storage));
  }
  return json::value(d, std::move(storage));
}

}  // namespace dtraced::jsonio
