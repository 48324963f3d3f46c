// dtraced::store results: a value or an error message, for expected failures (a bad database
// file, a constraint violation, a full disk). The store never throws for those; an exception out
// of it means a programming error or memory exhaustion.
//
// Thread safety: plain value types.
#pragma once

#include <cassert>
#include <string>
#include <utility>
#include <variant>

namespace dtraced::store {

// A human-readable message that names the database file and, for SQLite failures, carries
// sqlite3_errmsg and the extended result code.
struct Error {
  std::string message;
};

template <typename T>
class [[nodiscard]] Result {
 public:
  Result(T value) : v_(std::in_place_index<0>, std::move(value)) {}  // NOLINT: implicit by design
  Result(Error error) : v_(std::in_place_index<1>, std::move(error)) {}

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
  const std::string& error() const {
    assert(!ok());
    return std::get<1>(v_).message;
  }

 private:
  std::variant<T, Error> v_;
};

template <>
class [[nodiscard]] Result<void> {
 public:
  Result() = default;
  Result(Error error) : error_(std::move(error.message)), ok_(false) {}

  bool ok() const { return ok_; }
  explicit operator bool() const { return ok_; }
  const std::string& error() const {
    assert(!ok_);
    return error_;
  }

 private:
  std::string error_;
  bool ok_ = true;
};

using Status = Result<void>;

}  // namespace dtraced::store
