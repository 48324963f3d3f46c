// dtraced::util results: the one way every module reports an expected failure.
//
// Expected failures (a bad scene, an unreadable file, a malformed request body, a busy database,
// an invalid option) come back as a Result: a value or an error. Invariants are asserted;
// exceptions are for programming errors and memory exhaustion, and are translated only at the
// edges (the HTTP router, the CLI's main, a coroutine's completion handler).
//
// An Error is located: the file it came from, the JSON Pointer (or option name) of the value at
// fault, and what is wrong, so that a message names the file, the field and the problem. A
// reader that reports every problem in one pass returns Result<T, Errors>.
//
// Thread safety: plain value types.
#pragma once

#include <cassert>
#include <string>
#include <utility>
#include <variant>
#include <vector>

namespace dtraced::util {

struct Error {
  Error() = default;
  // Not explicit: `errors.push_back({message, path})` and `return Error{message}` read well.
  Error(std::string message_, std::string path_ = {}, std::string file_ = {})  // NOLINT(google-explicit-constructor)
      : message(std::move(message_)), path(std::move(path_)), file(std::move(file_)) {}

  std::string message;
  // JSON Pointer of the offending value ("/scene_objects/3/radius"), or an option name
  // ("--tile-size", "state_dir"); "" when no single value is at fault.
  std::string path;
  // The file the input came from; "" for a request body, a flag or a database call whose
  // message already names its file.
  std::string file;

  // "FILE: PATH: MESSAGE", leaving out the parts that are empty.
  std::string to_string() const {
    std::string out;
    for (const std::string* part : {&file, &path}) {
      if (part->empty()) continue;
      out += *part;
      out += ": ";
    }
    return out + message;
  }
  bool operator==(const Error&) const = default;
};

// Every problem a reader found, the most useful first; never empty inside a failed Result.
using Errors = std::vector<Error>;

// One line per error, each Error::to_string.
inline std::string to_string(const Errors& errors) {
  std::string out;
  for (const Error& e : errors) {
    if (!out.empty()) out += '\n';
    out += e.to_string();
  }
  return out;
}

template <typename T, typename E = Error>
class [[nodiscard]] Result {
 public:
  // Implicit both ways, so that a function can `return value;` or `return Error{...};`.
  Result(T value) : v_(std::in_place_index<0>, std::move(value)) {}  // NOLINT(google-explicit-constructor)
  Result(E error) : v_(std::in_place_index<1>, std::move(error)) {}  // NOLINT(google-explicit-constructor)

  bool ok() const { return v_.index() == 0; }
  explicit operator bool() const { return ok(); }

  T& value() & {
    assert(ok());
    return std::get<0>(v_);
  }
  const T& value() const& {
    assert(ok());
    return std::get<0>(v_);
  }
  T&& value() && {
    assert(ok());
    return std::get<0>(std::move(v_));
  }
  T* operator->() { return &value(); }
  const T* operator->() const { return &value(); }
  T& operator*() & { return value(); }
  const T& operator*() const& { return value(); }

  const E& error() const& {
    assert(!ok());
    return std::get<1>(v_);
  }
  E&& error() && {
    assert(!ok());
    return std::get<1>(std::move(v_));
  }

 private:
  std::variant<T, E> v_;
};

template <typename E>
class [[nodiscard]] Result<void, E> {
 public:
  Result() = default;
  Result(E error) : error_(std::move(error)), ok_(false) {}  // NOLINT(google-explicit-constructor)

  bool ok() const { return ok_; }
  explicit operator bool() const { return ok_; }
  const E& error() const& {
    assert(!ok_);
    return error_;
  }
  E&& error() && {
    assert(!ok_);
    return std::move(error_);
  }

 private:
  E error_{};
  bool ok_ = true;
};

using Status = Result<void>;

}  // namespace dtraced::util
