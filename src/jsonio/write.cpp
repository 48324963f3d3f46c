#include "jsonio/write.h"

#include <charconv>
#include <cmath>
#include <cstddef>
#include <iterator>
#include <system_error>
#include <vector>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/string.hpp>
#include <fmt/format.h>

namespace dtraced::jsonio {
namespace {

namespace json = boost::json;

// Below and above these magnitudes fmt's shortest form (with an exponent) is kept; in between,
// plain decimals. fmt's own switch to an exponent happens at 1e-5, earlier than people expect.
constexpr double kPlainMin = 1e-6;
constexpr double kPlainMax = 1e16;

void append_string(std::string& out, json::string_view s) { out += json::serialize(s); }

void append_scalar(std::string& out, const json::value& v) {
  switch (v.kind()) {
    case json::kind::null:
      out += "null";
      break;
    case json::kind::bool_:
      out += v.get_bool() ? "true" : "false";
      break;
    case json::kind::int64:
      fmt::format_to(std::back_inserter(out), "{}", v.get_int64());
      break;
    case json::kind::uint64:
      fmt::format_to(std::back_inserter(out), "{}", v.get_uint64());
      break;
    case json::kind::double_:
      append_number(out, v.get_double());
      break;
    case json::kind::string:
      append_string(out, v.get_string());
      break;
    case json::kind::array:
    case json::kind::object:
      break;  // containers are walked by to_text
  }
}

// One open container on the explicit stack: which one, and how far through it we are.
struct Frame {
  const json::value* container;
  std::size_t next;
};

}  // namespace

void append_number(std::string& out, double d) {
  if (!std::isfinite(d)) {
    out += "null";
    return;
  }
  if (d == 0) {
    out += std::signbit(d) ? "-0.0" : "0";
    return;
  }
  const double magnitude = std::fabs(d);
  if (magnitude < kPlainMin || magnitude >= kPlainMax) {
    fmt::format_to(std::back_inserter(out), "{}", d);  // shortest round trip, e.g. "1e+20"
    return;
  }
  // The shortest plain decimal that reads back to `d` (the standard requires round trip and the
  // fewest characters). The longest is "-0.000001" followed by 17 significant digits.
  char buf[64];
  const auto [end, ec] = std::to_chars(buf, buf + sizeof buf, d, std::chars_format::fixed);
  if (ec == std::errc()) {
    out.append(buf, end);
  } else {
    fmt::format_to(std::back_inserter(out), "{}", d);  // not reached: buf is large enough
  }
}

std::string to_text(const json::value& root) {
  std::string out;
  std::vector<Frame> stack;
  const json::value* v = &root;
  while (true) {
    // Open `v`: write a scalar whole, or start a container and descend into it.
    if (v != nullptr) {
      if (v->is_array()) {
        out += '[';
        stack.push_back({v, 0});
      } else if (v->is_object()) {
        out += '{';
        stack.push_back({v, 0});
      } else {
        append_scalar(out, *v);
      }
      v = nullptr;
    }
    if (stack.empty()) return out;
    // Next element of the innermost open container, or close it.
    Frame& top = stack.back();
    if (const json::array* a = top.container->if_array()) {
      if (top.next == a->size()) {
        out += ']';
        stack.pop_back();
        continue;
      }
      if (top.next > 0) out += ',';
      v = &(*a)[top.next++];
    } else {
      const json::object& o = top.container->get_object();
      if (top.next == o.size()) {
        out += '}';
        stack.pop_back();
        continue;
      }
      if (top.next > 0) out += ',';
      const json::key_value_pair& kv = *(o.begin() + static_cast<std::ptrdiff_t>(top.next++));
      append_string(out, kv.key());
      out += ':';
      v = &kv.value();
    }
  }
}

}  // namespace dtraced::jsonio
