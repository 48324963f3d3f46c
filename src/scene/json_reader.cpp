#include "scene/json_reader.h"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <system_error>
#include <utility>

// basic_parser's member definitions live in this header; it must be included by exactly the
// translation units that instantiate basic_parser with their own handler (this one).
#include <boost/json/basic_parser_impl.hpp>
#include <boost/json/error.hpp>
#include <boost/json/object.hpp>
#include <boost/json/string.hpp>
#include <boost/json/value_stack.hpp>
#include <fmt/format.h>

namespace dtraced::scene {
namespace {

namespace json = boost::json;

// Keys of one object are compared linearly for duplicates. No scene object has more than a
// handful of keys; past this many the object is wrong anyway (every extra key is an unknown-key
// error later), so duplicate tracking stops instead of going quadratic on hostile input.
constexpr std::size_t kMaxTrackedKeys = 64;

// Where the parser is inside the document, so an error can name a JSON Pointer.
struct Frame {
  bool is_array = false;
  std::size_t index = 0;  // array: index of the element being read
  bool has_key = false;   // object: a key was read and its value is being read
  std::string key;
  std::vector<std::string> seen_keys;
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
  StrictHandler(json::storage_ptr storage, std::size_t max_issues) : stack_(storage), max_issues_(max_issues) {
    stack_.reset(std::move(storage));
  }

  bool on_document_begin(json::error_code&) { return true; }
  bool on_document_end(json::error_code&) { return true; }

  bool on_array_begin(json::error_code&) {
    push_frame(/* is_array = */ true);
    return true;
  }
  bool on_array_end(std::size_t n, json::error_code&) {
    stack_.push_array(n);
    --depth_;
    value_done();
    return true;
  }
  bool on_object_begin(json::error_code&) {
    push_frame(/* is_array = */ false);
    return true;
  }
  bool on_object_end(std::size_t n, json::error_code&) {
    stack_.push_object(n);
    --depth_;
    value_done();
    return true;
  }

  bool on_string_part(json::string_view s, std::size_t, json::error_code&) {
    stack_.push_chars(s);
    return true;
  }
  bool on_string(json::string_view s, std::size_t, json::error_code&) {
    stack_.push_string(s);
    value_done();
    return true;
  }
  bool on_key_part(json::string_view s, std::size_t, json::error_code&) {
    stack_.push_chars(s);
    key_part_.append(s.data(), s.size());
    return true;
  }
  bool on_key(json::string_view s, std::size_t, json::error_code&) {
    stack_.push_key(s);
    key_part_.append(s.data(), s.size());
    key_read(std::move(key_part_));
    key_part_.clear();
    return true;
  }

  bool on_number_part(json::string_view s, json::error_code&) {
    number_part_.append(s.data(), s.size());
    return true;
  }
  bool on_int64(std::int64_t i, json::string_view, json::error_code&) {
    number_part_.clear();
    stack_.push_int64(i);
    value_done();
    return true;
  }
  bool on_uint64(std::uint64_t u, json::string_view, json::error_code&) {
    number_part_.clear();
    stack_.push_uint64(u);
    value_done();
    return true;
  }
  bool on_double(double boost_value, json::string_view s, json::error_code&) {
    number_part_.append(s.data(), s.size());
    stack_.push_double(precise_double(number_part_, boost_value));
    number_part_.clear();
    value_done();
    return true;
  }
  bool on_bool(bool b, json::error_code&) {
    stack_.push_bool(b);
    value_done();
    return true;
  }
  bool on_null(json::error_code&) {
    stack_.push_null();
    value_done();
    return true;
  }
  // Comments are disabled in parse_options; these only satisfy the handler concept.
  bool on_comment_part(json::string_view, json::error_code&) { return true; }
  bool on_comment(json::string_view, json::error_code&) { return true; }

  json::value release() { return stack_.release(); }
  std::vector<JsonIssue>& issues() { return issues_; }

  // JSON Pointer of the value being read now (or of the container, between values).
  std::string current_path() const {
    std::string path;
    for (std::size_t i = 0; i < depth_; ++i) {
      const Frame& f = frames_[i];
      if (f.is_array) {
        path += fmt::format("/{}", f.index);
      } else if (f.has_key) {
        path += '/';
        path += json_pointer_escape(f.key);
      }
    }
    return path;
  }

  void add_issue(std::string path, std::string message) {
    if (issues_.size() < max_issues_) issues_.push_back({std::move(path), std::move(message)});
  }

 private:
  // from_chars is correctly rounded; Boost 1.81's conversion is not (see the header).
  static double precise_double(const std::string& text, double boost_value) {
    double d = 0;
    const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), d, std::chars_format::general);
    // On overflow/underflow from_chars leaves `d` alone; Boost's value (+-inf, or a value near
    // zero) is then the right one, and validation reports the out-of-range number by path.
    if (ec != std::errc() || end != text.data() + text.size()) return boost_value;
    return d;
  }

  // Frames are reused rather than popped, so a large document does not reallocate key vectors
  // for every object.
  void push_frame(bool is_array) {
    if (depth_ == frames_.size()) frames_.emplace_back();
    Frame& f = frames_[depth_++];
    f.is_array = is_array;
    f.index = 0;
    f.has_key = false;
    f.key.clear();
    f.seen_keys.clear();
  }

  void key_read(std::string key) {
    Frame& f = frames_[depth_ - 1];
    f.key = std::move(key);
    f.has_key = true;
    if (f.seen_keys.size() >= kMaxTrackedKeys) return;
    if (std::find(f.seen_keys.begin(), f.seen_keys.end(), f.key) != f.seen_keys.end()) {
      add_issue(current_path(), fmt::format("duplicate key \"{}\"", f.key));
    } else {
      f.seen_keys.push_back(f.key);
    }
  }

  // A value (scalar or closed container) is complete: advance the enclosing container.
  void value_done() {
    if (depth_ == 0) return;
    Frame& f = frames_[depth_ - 1];
    if (f.is_array) {
      ++f.index;
    } else {
      f.has_key = false;
    }
  }

  json::value_stack stack_;
  std::vector<Frame> frames_;
  std::size_t depth_ = 0;
  std::string key_part_;
  std::string number_part_;
  std::vector<JsonIssue> issues_;
  std::size_t max_issues_;
};

std::string describe_parse_error(const json::error_code& ec, std::size_t max_depth) {
  if (ec == json::error::too_deep) return fmt::format("nesting is deeper than the limit of {} levels", max_depth);
  if (ec == json::error::extra_data) return "unexpected data after the JSON document";
  if (ec == json::error::incomplete) return "unexpected end of input";
  return ec.message();
}

}  // namespace

std::string json_pointer_escape(std::string_view token) {
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

JsonDocument read_json_strict(std::string_view text, std::size_t max_depth, std::size_t max_issues,
                              json::storage_ptr storage) {
  json::parse_options options;
  options.max_depth = max_depth;  // the other options already default to strict JSON

  json::basic_parser<StrictHandler> parser(options, std::move(storage), max_issues);
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
    // The syntax error is pushed past the issue limit if need be: it is the one that matters.
    handler.issues().push_back(
        {handler.current_path(), fmt::format("invalid JSON at line {}, column {} (byte {}): {}", line, column, consumed,
                                             describe_parse_error(ec, max_depth))});
    return JsonDocument{json::value(), /* parsed = */ false, std::move(handler.issues())};
  }
  // Constructed, not assigned: assigning into a value with the default storage would deep-copy
  // the whole tree out of the caller's arena.
  return JsonDocument{parser.handler().release(), /* parsed = */ true, std::move(parser.handler().issues())};
}

std::string_view json_kind_name(const boost::json::value& v) {
  switch (v.kind()) {
    case boost::json::kind::object:
      return "an object";
    case boost::json::kind::array:
      return "an array";
    case boost::json::kind::string:
      return "a string";
    case boost::json::kind::bool_:
      return "a boolean";
    case boost::json::kind::null:
      return "null";
    default:
      return "a number";
  }
}

std::optional<double> json_finite_number(const boost::json::value& v, std::string& error) {
  double d = 0;
  switch (v.kind()) {
    case boost::json::kind::double_:
      d = v.get_double();
      break;
    case boost::json::kind::int64:
      d = static_cast<double>(v.get_int64());
      break;
    case boost::json::kind::uint64:
      d = static_cast<double>(v.get_uint64());
      break;
    default:
      error = fmt::format("expected a number, got {}", json_kind_name(v));
      return std::nullopt;
  }
  if (!std::isfinite(d)) {
    error = "number is out of range (overflows a double)";
    return std::nullopt;
  }
  return d;
}

}  // namespace dtraced::scene
