// Test helpers for decoding job submissions: a submission body around a scene, and
// "path: message" of the first error of a failed decode.
#pragma once

#include <string>
#include <string_view>

#include <catch2/catch.hpp>

namespace dtraced::testing {

// {"scene": SCENE, EXTRA}: a job submission of `scene` (JSON text) with the keys in `extra`.
inline std::string submit_body(std::string_view scene, std::string_view extra) {
  return "{\"scene\": " + std::string(scene) + ", " + std::string(extra) + "}";
}

// The first error of a failed decode (a submission, stored settings, any result whose error is a
// list of path-and-message errors) as "path: message".
template <typename Decoded>
std::string first_error(const Decoded& d) {
  REQUIRE_FALSE(d.ok());
  return d.error().front().path + ": " + d.error().front().message;
}

}  // namespace dtraced::testing
