// dtraced::protocol codec, internal: the reading and writing that the message codecs of
// messages.cpp and job_messages.cpp share. Not for other modules: they call messages.h.
//
// Every decoder is one call of decode_object: the body parsed under its size and depth limits,
// its top level an object with a known set of keys, each key read by jsonio (reader.h), and
// either the message or every error found.
//
// Stateless functions: thread-safe.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/value.hpp>

#include "jsonio/reader.h"
#include "jsonio/write.h"  // jsonio::to_text, the one writer of every encode()
#include "protocol/messages.h"

namespace dtraced::protocol::detail {

using jsonio::Fields;
using jsonio::Need;
using jsonio::Path;
using jsonio::Reader;

// Decodes `text`: at most `max_bytes` and `max_depth` levels, a top-level object whose keys are
// among `keys`, read by `read(Fields&, T&)`. The message, or every error of the body.
template <typename T, typename Read>
Decoded<T> decode_object(std::string_view text, std::size_t max_bytes, std::size_t max_depth,
                         std::span<const std::string_view> keys, Read read) {
  Reader r({}, kMaxDecodeErrors);
  const std::optional<boost::json::value> body = r.parse(text, "body", max_bytes, max_depth);
  const Path root;
  const boost::json::object* o = body ? r.object(*body, root) : nullptr;
  if (o == nullptr) return r.take_errors();
  Fields f(r, *o, root, keys);
  T message{};
  read(f, message);
  if (r.failed()) return r.take_errors();
  return message;
}

// The object's required array `key` of at most `max_items` objects, each with keys among `keys`
// and read by `read(Fields&, T&)`, appended to `out` when it read without error.
template <typename T, typename Read>
void read_object_array(Fields& f, std::string_view key, std::size_t max_items, std::span<const std::string_view> keys,
                       std::vector<T>& out, Read read) {
  Reader& r = f.reader();
  const boost::json::value* v = f.get(key, Need::kRequired);
  const Path at = f.path(key);
  const boost::json::array* a = v != nullptr ? r.array(*v, at, max_items, key) : nullptr;
  if (a == nullptr) return;
  out.reserve(a->size());
  for (std::size_t i = 0; i < a->size(); ++i) {
    const Path element_at = at.index(i);
    const boost::json::object* o = r.object((*a)[i], element_at);
    if (o == nullptr) continue;
    const std::size_t before = r.error_count();
    Fields element(r, *o, element_at, keys);
    T item{};
    read(element, item);
    if (r.error_count() == before) out.push_back(std::move(item));
  }
}

// A lease reply's members ({"lease": ...} or {"retry_after_ms": ...}) into `m`, and the keys it
// may have: POST /v1/lease's answer, and the "next" lease of an upload's answer.
void read_lease_reply(Fields& f, LeaseReply& m);
inline constexpr std::array<std::string_view, 2> kLeaseReplyKeys = {"lease", "retry_after_ms"};
// The object's required "digest": is_digest.
void read_digest(Fields& f, std::string& out);
// The object's "output": a file name (check_output_name).
void read_output(Fields& f, std::string& out, Need need);
// The object's optional "png_bit_depth" (8 or 16) into `out`; false after an error.
bool read_bit_depth(Fields& f, std::uint32_t& out);
// The object's optional "crop", {"x", "y", "width", "height"} (not empty), into `out`; false
// after an error.
bool read_crop(Fields& f, std::optional<scene::TileRect>& out);
// Whether `crop` (read at f.path("crop")) lies inside a width x height image; the error names
// the member that reaches outside.
void check_crop_inside(Fields& f, const scene::TileRect& crop, std::uint32_t width, std::uint32_t height);
// {"x", "y", "width", "height"}: how a submission and stored settings write a crop.
boost::json::object crop_object(const scene::TileRect& crop);

}  // namespace dtraced::protocol::detail
