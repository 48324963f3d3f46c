// dtraced::jsonio paths: the JSON Pointer (RFC 6901) of a value being read, built only when an
// error needs it. It is built for display: a key's control characters are escaped (printable()
// in parse.h), so a pointer never carries a raw newline or terminal escape into a message.
//
// Reading a scene of 10M objects must not allocate a path string per field, so a Path is a link
// to its parent plus one key or index, and str() walks the chain only for an error message. The
// price is a lifetime rule: a Path refers to its parent, so keep a chain in one expression
// (`at.key("material").key("ior")` passed straight to a call) or in named locals whose parents
// outlive them. Copying a Path copies the link, not the parent.
//
// Values on the stack: thread-compatible.
#pragma once

#include <cstddef>
#include <string>
#include <string_view>

#include "jsonio/parse.h"

namespace dtraced::jsonio {

class Path {
 public:
  Path() = default;  // the document root, ""

  Path key(std::string_view k) const& { return Path(this, k, 0, /* is_index = */ false); }
  Path index(std::size_t i) const& { return Path(this, {}, i, /* is_index = */ true); }
  Path key(std::string_view k) const&& = delete;
  Path index(std::size_t i) const&& = delete;
  bool is_root() const { return parent_ == nullptr; }

  std::string str() const {
    if (parent_ == nullptr) return {};
    std::string s = parent_->str();
    s += '/';
    s += is_index_ ? std::to_string(index_) : printable(pointer_escape(key_));
    return s;
  }

 private:
  Path(const Path* parent, std::string_view key, std::size_t index, bool is_index)
      : parent_(parent), key_(key), index_(index), is_index_(is_index) {}

  const Path* parent_ = nullptr;
  std::string_view key_;
  std::size_t index_ = 0;
  bool is_index_ = false;
};

}  // namespace dtraced::jsonio
