#include "jsonio/reader.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <vector>

#include <boost/json/string.hpp>
#include <fmt/format.h>

#include "jsonio/edit_distance.h"

namespace dtraced::jsonio {
namespace {

namespace json = boost::json;

// A string longer than this is not quoted back in a message about a name it should have been.
constexpr std::size_t kMaxQuotedBytes = 64;

}  // namespace

std::size_t edit_distance(std::string_view a, std::string_view b) {
  std::vector<std::size_t> row(b.size() + 1);
  for (std::size_t j = 0; j <= b.size(); ++j) row[j] = j;
  for (std::size_t i = 1; i <= a.size(); ++i) {
    std::size_t diagonal = row[0];
    row[0] = i;
    for (std::size_t j = 1; j <= b.size(); ++j) {
      const std::size_t up = row[j];
      row[j] = std::min({row[j] + 1, row[j - 1] + 1, diagonal + (a[i - 1] == b[j - 1] ? 0 : 1)});
      diagonal = up;
    }
  }
  return row[b.size()];
}

namespace {

bool contains(std::span<const std::string_view> names, std::string_view name) {
  return std::find(names.begin(), names.end(), name) != names.end();
}

// "a, b or c".
std::string or_list(std::span<const std::string_view> names) {
  std::string out;
  for (std::size_t i = 0; i < names.size(); ++i) {
    if (i > 0) out += i + 1 == names.size() ? " or " : ", ";
    out += names[i];
  }
  return out;
}

}  // namespace

std::string unknown_key_message(std::string_view key, std::span<const std::string_view> known,
                                std::span<const KeyAlias> aliases) {
  for (const KeyAlias& a : aliases) {
    if (key == a.alias && contains(known, a.meant)) {
      return fmt::format("unknown key {} (did you mean \"{}\"?)", quoted(key), a.meant);
    }
  }
  std::string_view best;
  std::size_t best_distance = std::numeric_limits<std::size_t>::max();
  for (const std::string_view k : known) {
    const std::size_t d = edit_distance(key, k);
    if (d < best_distance) {
      best_distance = d;
      best = k;
    }
  }
  // Two edits catch transpositions ("raduis") and British spellings ("colour") without
  // suggesting "loc" for "foo".
  if (best_distance <= 2 && best_distance < key.size()) {
    return fmt::format("unknown key {} (did you mean \"{}\"?)", quoted(key), best);
  }
  return fmt::format("unknown key {}; known keys: {}", quoted(key), fmt::join(known, ", "));
}

util::Errors Reader::take_errors() {
  if (count_ > errors_.size()) {
    errors_.push_back({fmt::format("{} more problems not shown", count_ - errors_.size()), "", file_});
  }
  count_ = 0;
  return std::move(errors_);
}

std::optional<json::value> Reader::parse(std::string_view text, std::string_view what, std::size_t max_bytes,
                                         std::size_t max_depth, json::storage_ptr storage) {
  if (text.size() > max_bytes) {
    error(Path(), fmt::format("{} is {} bytes, larger than the limit of {} bytes", what, text.size(), max_bytes));
    return std::nullopt;
  }
  // One place is kept for the syntax error, which matters more than any duplicate key before it.
  Document doc = parse_strict(text, max_depth, max_ > count_ ? max_ - count_ - 1 : 0, std::move(storage));
  for (util::Error& e : doc.errors) error(std::move(e.path), std::move(e.message));
  if (!doc.parsed) return std::nullopt;
  return std::move(doc.value);
}

void Reader::not_an_object(const json::value& v, const Path& at) {
  if (at.is_root()) {
    error(at, fmt::format("expected a JSON object at the top level, got {}", kind_name(v)));
  } else {
    error(at, fmt::format("expected an object, got {}", kind_name(v)));
  }
}

const json::array* Reader::array(const json::value& v, const Path& at) {
  if (const json::array* a = v.if_array()) return a;
  error(at, fmt::format("expected an array, got {}", kind_name(v)));
  return nullptr;
}

const json::array* Reader::array(const json::value& v, const Path& at, std::size_t max_size, std::string_view what) {
  const json::array* a = array(v, at);
  if (a != nullptr && a->size() > max_size) {
    error(at, fmt::format("too many {}: {} (limit {})", what, a->size(), max_size));
    return nullptr;
  }
  return a;
}

void Reader::not_a_tuple(const json::value& v, const Path& at, std::size_t n, std::string_view what) {
  const json::array* a = v.if_array();
  if (a == nullptr) {
    error(at, fmt::format("expected an array of {} {}, got {}", n, what, kind_name(v)));
  } else {
    error(at,
          fmt::format("expected an array of {} {}, got {} element{}", n, what, a->size(), a->size() == 1 ? "" : "s"));
  }
}

void Reader::check_keys(const json::object& o, const Path& at, std::span<const std::string_view> known,
                        std::span<const KeyAlias> aliases) {
  for (const auto& member : o) {
    const std::string_view key = member.key();
    if (!contains(known, key)) error(at.key(key), unknown_key_message(key, known, aliases));
  }
}

void Reader::not_a_number(const json::value& v, const Path& at) {
  if (v.is_number()) {
    error(at, "number is out of range (overflows a double)");
  } else {
    error(at, fmt::format("expected a number, got {}", kind_name(v)));
  }
}

void Reader::out_of_range(double d, const Path& at, double lo, double hi) {
  if (hi >= DBL_MAX) {
    error(at, fmt::format("must be >= {} (got {})", lo, d));
  } else {
    error(at, fmt::format("must be in [{}, {}] (got {})", lo, hi, d));
  }
}

void Reader::not_positive(double d, const Path& at) { error(at, fmt::format("must be > 0 (got {})", d)); }

std::optional<std::int64_t> Reader::integer(const json::value& v, const Path& at, std::int64_t lo, std::int64_t hi) {
  assert(lo <= hi && hi <= kMaxExactInteger && lo >= -kMaxExactInteger);
  const auto out_of_range = [&](auto got) {
    error(at, fmt::format("must be an integer in [{}, {}] (got {})", lo, hi, got));
    return std::nullopt;
  };
  switch (v.kind()) {
    case json::kind::int64: {
      const std::int64_t i = v.get_int64();
      if (i < lo || i > hi) return out_of_range(i);
      return i;
    }
    case json::kind::uint64:  // only values above INT64_MAX arrive as uint64: always too large
      return out_of_range(v.get_uint64());
    case json::kind::double_: {
      const double d = v.get_double();
      if (!std::isfinite(d)) {
        error(at, "number is out of range (overflows a double)");
        return std::nullopt;
      }
      if (d != std::floor(d)) {
        error(at, fmt::format("must be an integer (got {})", d));
        return std::nullopt;
      }
      // Compared in double before converting: a value beyond int64 must never reach the
      // conversion (undefined behaviour). Every bound is at most 2^53, so exact as a double.
      if (d < static_cast<double>(lo) || d > static_cast<double>(hi)) return out_of_range(d);
      return static_cast<std::int64_t>(d);
    }
    default:
      error(at, fmt::format("expected an integer, got {}", kind_name(v)));
      return std::nullopt;
  }
}

std::optional<std::string_view> Reader::string(const json::value& v, const Path& at, std::size_t max_bytes) {
  const json::string* s = v.if_string();
  if (s == nullptr) {
    error(at, fmt::format("expected a string, got {}", kind_name(v)));
    return std::nullopt;
  }
  if (s->size() > max_bytes) {
    error(at, fmt::format("string is {} bytes, longer than the limit of {}", s->size(), max_bytes));
    return std::nullopt;
  }
  return std::string_view(s->data(), s->size());
}

std::optional<bool> Reader::boolean(const json::value& v, const Path& at) {
  if (v.is_bool()) return v.get_bool();
  error(at, fmt::format("expected true or false, got {}", kind_name(v)));
  return std::nullopt;
}

std::optional<std::size_t> Reader::choice(const json::value& v, const Path& at, std::span<const std::string_view> names,
                                          std::string_view what, std::string_view plural) {
  const json::string* s = v.if_string();
  if (s == nullptr) {
    error(at, fmt::format("expected a string ({}), got {}", or_list(names), kind_name(v)));
    return std::nullopt;
  }
  const std::string_view text(s->data(), s->size());
  const auto it = std::find(names.begin(), names.end(), text);
  if (it != names.end()) return static_cast<std::size_t>(it - names.begin());
  const std::string shown =
      text.size() <= kMaxQuotedBytes ? quoted(text) : fmt::format("(a string of {} bytes)", text.size());
  error(at, fmt::format("unknown {} {}; known {}: {}", what, shown, plural, fmt::join(names, ", ")));
  return std::nullopt;
}

}  // namespace dtraced::jsonio
