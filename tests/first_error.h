// Test helper: "path: message" of the first error of a failed decode (a submission, stored
// settings, any result whose error is a list of path-and-message errors).
#pragma once

#include <string>

#include <catch2/catch.hpp>

namespace dtraced::testing {

template <typename Decoded>
std::string first_error(const Decoded& d) {
  REQUIRE_FALSE(d.ok());
  return d.error().front().path + ": " + d.error().front().message;
}

}  // namespace dtraced::testing
