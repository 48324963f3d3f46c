// dtraced::jsonio reader: the one strict, located reader of JSON values, shared by scene files,
// wire messages and config files so that the same mistake is worded the same way in all three.
//
// Owns: the rules and the words for reading a parsed value (parse.h) into plain structs:
//   - every problem is a util::Error{message, path, file}: `path` the JSON Pointer of the value at
//     fault (built lazily, path.h), `file` what the Reader was given ("" for a request body);
//   - problems are collected, not thrown: every check reports and carries on, so one pass names
//     every problem, up to a limit past which one last error counts the rest
//     ("N more problems not shown");
//   - shapes: objects, arrays (with a size limit), arrays of exactly n numbers, required keys;
//   - unknown keys are errors, worded `unknown key "X" (did you mean "Y"?)` when a known key is
//     within two edits or the caller's alias table maps X to a known key, otherwise
//     `unknown key "X"; known keys: a, b, c`;
//   - numbers: finite (a number that overflows a double is an error), -0 read as +0, ranges;
//     integers in [lo, hi] with |lo|, |hi| <= 2^53 (one implementation for signed and unsigned),
//     where an integral double (640.0, 1e3) counts, since JSON does not tell them apart;
//   - strings with a byte limit, booleans, and one of a fixed set of names.
//
// A Reader belongs to one reading: not thread-safe; readers share nothing.
#pragma once

#include <array>
#include <cassert>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/value.hpp>

#include "jsonio/parse.h"
#include "jsonio/path.h"
#include "util/result.h"

namespace dtraced::jsonio {

// The largest integer bound: every integer up to it is exact as a double, and a JavaScript
// client reads it exactly.
inline constexpr std::int64_t kMaxExactInteger = std::int64_t{1} << 53;

// A name other programs or users reach for, mapped to the key meant: spelling distance alone
// would never connect "center" to "loc".
struct KeyAlias {
  std::string_view alias;
  std::string_view meant;
};

enum class Need { kRequired, kOptional };

// The message for a key of an object that is not one of `known`.
std::string unknown_key_message(std::string_view key, std::span<const std::string_view> known,
                                std::span<const KeyAlias> aliases = {});

class Reader {
 public:
  // `file` labels every error ("" for none); past `max_errors` errors the rest are counted.
  explicit Reader(std::string file = {}, std::size_t max_errors = 100) : file_(std::move(file)), max_(max_errors) {}

  // ---- errors ---------------------------------------------------------------------------------
  void error(const Path& at, std::string message) {
    if (++count_ <= max_) errors_.push_back({std::move(message), at.str(), file_});
  }
  // For a path already spelled out (errors of a nested reading, moved under a prefix).
  void error(std::string path, std::string message) {
    if (++count_ <= max_) errors_.push_back({std::move(message), std::move(path), file_});
  }
  // Every error reported so far, shown or not: compare counts to learn whether a part was clean.
  std::size_t error_count() const { return count_; }
  bool failed() const { return count_ != 0; }
  const std::string& file() const { return file_; }
  // The errors, the count of those not shown appended as one more; the Reader starts afresh.
  util::Errors take_errors();
  // Appends `other`'s errors, shown and counted, as if reported here now (a part read apart, e.g.
  // while parsing, keeps its place in the order of the messages); `other` starts afresh.
  void absorb(Reader& other) {
    const std::size_t hidden = other.count_ - other.errors_.size();
    for (util::Error& e : other.errors_) error(std::move(e.path), std::move(e.message));
    count_ += hidden;
    other.errors_.clear();
    other.count_ = 0;
  }

  // ---- text -----------------------------------------------------------------------------------
  // `text` parsed by parse_strict, or nullopt after reporting why not: larger than `max_bytes`
  // ("{what} is N bytes, larger than the limit of M bytes") or a syntax error. Duplicate keys are
  // reported and do not stop the reading.
  std::optional<boost::json::value> parse(std::string_view text, std::string_view what, std::size_t max_bytes,
                                          std::size_t max_depth, boost::json::storage_ptr storage = {});

  // ---- shapes ---------------------------------------------------------------------------------
  // The checks on every field of a large document are inline; their error reports are not.
  const boost::json::object* object(const boost::json::value& v, const Path& at) {
    if (const boost::json::object* o = v.if_object()) return o;
    not_an_object(v, at);
    return nullptr;
  }
  const boost::json::array* array(const boost::json::value& v, const Path& at);
  // An array of at most `max_size` elements ("too many {what}: N (limit M)"); its elements are
  // not looked at when it has more: checking 10M+ of them would only bury the message.
  const boost::json::array* array(const boost::json::value& v, const Path& at, std::size_t max_size,
                                  std::string_view what);
  // An array of exactly `n` elements, described as "an array of {n} {what}".
  const boost::json::array* tuple(const boost::json::value& v, const Path& at, std::size_t n, std::string_view what) {
    const boost::json::array* a = v.if_array();
    if (a != nullptr && a->size() == n) return a;
    not_a_tuple(v, at, n, what);
    return nullptr;
  }
  // o[key], or nullptr (an error at at/key when `need` is kRequired).
  const boost::json::value* get(const boost::json::object& o, std::string_view key, const Path& at, Need need) {
    if (const boost::json::value* v = o.if_contains(key)) return v;
    if (need == Need::kRequired) error(at.key(key), "required key is missing");
    return nullptr;
  }
  // An error for each key of `o` not in `known` (unknown_key_message).
  void check_keys(const boost::json::object& o, const Path& at, std::span<const std::string_view> known,
                  std::span<const KeyAlias> aliases = {});

  // ---- scalars --------------------------------------------------------------------------------
  // A finite number; -0 becomes +0, so that nothing downstream (a digest) sees the sign of zero.
  std::optional<double> number(const boost::json::value& v, const Path& at) {
    double d = 0;
    if (const double* p = v.if_double()) {
      d = *p;
    } else if (const std::int64_t* i = v.if_int64()) {
      d = static_cast<double>(*i);
    } else if (const std::uint64_t* u = v.if_uint64()) {
      d = static_cast<double>(*u);
    } else {
      not_a_number(v, at);
      return std::nullopt;
    }
    if (!std::isfinite(d)) {
      not_a_number(v, at);
      return std::nullopt;
    }
    return d == 0 ? 0.0 : d;
  }
  std::optional<double> number(const boost::json::value& v, const Path& at, double lo, double hi) {
    const std::optional<double> d = number(v, at);
    return d && in_range(*d, at, lo, hi) ? d : std::nullopt;
  }
  // Range checks of a number already read: "must be in [lo, hi] (got d)", or with no upper bound
  // (hi = +inf or DBL_MAX) "must be >= lo (got d)"; "must be > 0 (got d)".
  bool in_range(double d, const Path& at, double lo, double hi) {
    if (d >= lo && d <= hi) return true;
    out_of_range(d, at, lo, hi);
    return false;
  }
  bool positive(double d, const Path& at) {
    if (d > 0) return true;
    not_positive(d, at);
    return false;
  }
  // An integer in [lo, hi] ("must be an integer in [lo, hi] (got x)"), |lo|, |hi| <= 2^53.
  std::optional<std::int64_t> integer(const boost::json::value& v, const Path& at, std::int64_t lo, std::int64_t hi);
  // A string of at most `max_bytes` bytes; the view lives as long as `v`.
  std::optional<std::string_view> string(const boost::json::value& v, const Path& at,
                                         std::size_t max_bytes = std::numeric_limits<std::size_t>::max());
  std::optional<bool> boolean(const boost::json::value& v, const Path& at);
  // The index in `names` of the string `v`: "expected a string (a, b or c), got X", or
  // `unknown {what} "x"; known {plural}: a, b, c`.
  std::optional<std::size_t> choice(const boost::json::value& v, const Path& at,
                                    std::span<const std::string_view> names, std::string_view what,
                                    std::string_view plural);

 private:
  void not_an_object(const boost::json::value& v, const Path& at);
  void not_a_tuple(const boost::json::value& v, const Path& at, std::size_t n, std::string_view what);
  void not_a_number(const boost::json::value& v, const Path& at);  // or one that overflows a double
  void out_of_range(double d, const Path& at, double lo, double hi);
  void not_positive(double d, const Path& at);

  std::string file_;
  std::size_t max_;
  std::size_t count_ = 0;
  util::Errors errors_;
};

// The members of one JSON object, read key by key into a struct. Each accessor reports a missing
// required key, a wrong type or a value out of range at the key's path, and leaves `out` alone
// then (or when an optional key is absent). Accessors return false when they reported an error.
class Fields {
 public:
  // Reports the keys of `o` that are not in `known` now.
  Fields(Reader& r, const boost::json::object& o, const Path& at, std::span<const std::string_view> known,
         std::span<const KeyAlias> aliases = {})
      : Fields(r, o, at) {
    r.check_keys(o, at, known, aliases);
  }
  // Checks no keys: the caller knows which keys apply only later (a scene object's type).
  Fields(Reader& r, const boost::json::object& o, const Path& at) : r_(r), o_(o), at_(at) {}

  Reader& reader() const { return r_; }
  const boost::json::object& object() const { return o_; }
  const Path& at() const { return at_; }
  Path path(std::string_view key) const { return at_.key(key); }
  bool has(std::string_view key) const { return o_.contains(key); }
  const boost::json::value* get(std::string_view key, Need need) { return r_.get(o_, key, at_, need); }

  // An integer in [lo, hi] into `out`, an integral type or a std::optional of one.
  template <typename T>
  bool integer(std::string_view key, T& out, std::int64_t lo, std::int64_t hi, Need need = Need::kRequired) {
    return read(key, out, need, integer_in<T>(lo, hi));
  }
  template <typename T>
  bool integer(std::string_view key, std::optional<T>& out, std::int64_t lo, std::int64_t hi,
               Need need = Need::kOptional) {
    return read(key, out, need, integer_in<T>(lo, hi));
  }
  // A finite number in [lo, hi] into `out`, a double or a std::optional<double>.
  bool number(std::string_view key, double& out, double lo, double hi, Need need = Need::kRequired) {
    return read(key, out, need, [&](const boost::json::value& v, const Path& p) { return r_.number(v, p, lo, hi); });
  }
  bool number(std::string_view key, std::optional<double>& out, double lo, double hi, Need need = Need::kOptional) {
    return read(key, out, need, [&](const boost::json::value& v, const Path& p) { return r_.number(v, p, lo, hi); });
  }
  bool string(std::string_view key, std::string& out, std::size_t max_bytes, Need need = Need::kRequired) {
    return read(key, out, need, [this, max_bytes](const boost::json::value& v, const Path& p) {
      const auto s = r_.string(v, p, max_bytes);
      return s ? std::optional<std::string>(*s) : std::nullopt;
    });
  }
  bool boolean(std::string_view key, bool& out, Need need = Need::kRequired) {
    return read(key, out, need, [this](const boost::json::value& v, const Path& p) { return r_.boolean(v, p); });
  }

  // Reads `key` with `read(value, path) -> std::optional<X>` (which reports its own errors) and
  // stores the result into `out`.
  template <typename T, typename Read>
  bool read(std::string_view key, T& out, Need need, Read read) {
    const boost::json::value* v = get(key, need);
    if (v == nullptr) return need == Need::kOptional;
    auto got = read(*v, path(key));
    if (!got) return false;
    out = static_cast<T>(std::move(*got));
    return true;
  }

 private:
  template <typename T>
  auto integer_in(std::int64_t lo, std::int64_t hi) {
    static_assert(std::is_integral_v<T>);
    assert(lo >= static_cast<std::int64_t>(std::numeric_limits<T>::min()));
    assert(static_cast<std::uint64_t>(hi) <= static_cast<std::uint64_t>(std::numeric_limits<T>::max()));
    return [this, lo, hi](const boost::json::value& v, const Path& p) {
      const auto i = r_.integer(v, p, lo, hi);
      return i ? std::optional<T>(static_cast<T>(*i)) : std::nullopt;
    };
  }
  Reader& r_;
  const boost::json::object& o_;
  Path at_;
};

// Key lists made of others: a message's own keys followed by a shared block's.
template <std::size_t N, std::size_t M>
constexpr std::array<std::string_view, N + M> join_keys(const std::array<std::string_view, N>& a,
                                                        const std::array<std::string_view, M>& b) {
  std::array<std::string_view, N + M> out{};
  for (std::size_t i = 0; i < N; ++i) out[i] = a[i];
  for (std::size_t i = 0; i < M; ++i) out[N + i] = b[i];
  return out;
}

}  // namespace dtraced::jsonio
