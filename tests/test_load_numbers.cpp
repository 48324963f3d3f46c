// The strict parser's doubles (jsonio/parse.h): Boost 1.81 converts every number itself and is
// off by an ulp for about one double in five, so the parser converts the number's text again with
// std::from_chars, from Boost's own view of the text when the number came in one piece and from a
// copy when it was split across the pieces of a text. Both give from_chars' bits on many numbers.
#include <bit>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "jsonio/parse.h"

namespace {

namespace jsonio = dtraced::jsonio;

std::uint64_t from_chars_bits(const std::string& s) {
  double d = 0;
  const auto [end, ec] = std::from_chars(s.data(), s.data() + s.size(), d);
  REQUIRE(ec == std::errc());
  REQUIRE(end == s.data() + s.size());
  return std::bit_cast<std::uint64_t>(d);
}

// Numbers of every kind a scene holds: short decimals, random doubles at every precision, the
// shortest text of random doubles (the canonical form's), and the edges of the exact range.
std::vector<std::string> many_numbers() {
  std::vector<std::string> out = {"0.1",
                                  "2.675",
                                  "1.0000000000000002",
                                  "123.456",
                                  "-7.25e-3",
                                  "9007199254740993",
                                  "1e23",
                                  "-0.0",
                                  "4.9e-324",
                                  "1.7976931348623157e308",
                                  "0.30000000000000004"};
  std::mt19937_64 rng(16);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  std::uniform_int_distribution<int> exponent(-30, 30);
  for (int i = 0; i < 20000; ++i) {
    const double v = unit(rng) * std::pow(10.0, exponent(rng));
    out.push_back(fmt::format("{:.{}g}", v, 1 + i % 17));
    out.push_back(fmt::format("{:.{}E}", v, i % 17));
    out.push_back(fmt::format("{}", v));
    const double any = std::bit_cast<double>(rng());
    if (std::isfinite(any)) out.push_back(fmt::format("{}", any));
  }
  return out;
}

std::string array_of(const std::vector<std::string>& numbers) {
  std::string text = "[";
  for (std::size_t i = 0; i < numbers.size(); ++i) text += (i ? "," : "") + numbers[i];
  return text + "]";
}

void check_doubles(const jsonio::Document& doc, const std::vector<std::string>& numbers) {
  REQUIRE(doc.parsed);
  REQUIRE(doc.errors.empty());
  const auto& a = doc.value.as_array();
  REQUIRE(a.size() == numbers.size());
  for (std::size_t i = 0; i < numbers.size(); ++i) {
    INFO(numbers[i]);
    // Integral texts are read as integers; every other one is a double of from_chars' bits.
    if (!a[i].is_double()) continue;
    REQUIRE(std::bit_cast<std::uint64_t>(a[i].as_double()) == from_chars_bits(numbers[i]));
  }
}

}  // namespace

TEST_CASE("the strict parser's doubles are from_chars', in one piece", "[load][number]") {
  const std::vector<std::string> numbers = many_numbers();
  check_doubles(jsonio::parse_strict(array_of(numbers), 8, 8), numbers);
}

TEST_CASE("the strict parser's doubles are from_chars', split across pieces", "[load][number]") {
  const std::vector<std::string> numbers = many_numbers();
  const std::string text = array_of(numbers);
  for (const std::size_t piece : {1, 3, 7, 4096}) {
    INFO("pieces of " << piece);
    jsonio::StrictParser parser(8, 8);
    for (std::size_t i = 0; i < text.size(); i += piece) REQUIRE(parser.write(std::string_view(text).substr(i, piece)));
    check_doubles(parser.finish(), numbers);
  }
}
