// Tests for dtraced::jsonio::to_text, the one writer of JSON for people and the wire: doubles as
// plain shortest decimals that read back (through parse_strict) to the same bits, integers in
// full, strings escaped, containers nested, and never a token that is not JSON.

#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/string.hpp>
#include <boost/json/value.hpp>
#include <catch2/catch.hpp>

#include "jsonio/parse.h"
#include "jsonio/write.h"

namespace {

namespace json = boost::json;
namespace jsonio = dtraced::jsonio;

json::value reparse(const std::string& text) {
  jsonio::Document doc = jsonio::parse_strict(text, 64, 10);
  INFO(text);
  REQUIRE(doc.parsed);
  REQUIRE(doc.errors.empty());
  return std::move(doc.value);
}

// The double a number reads back as, whichever kind the parser gave it.
double as_double(const json::value& v) {
  REQUIRE(v.is_number());
  return v.to_number<double>();
}

}  // namespace

TEST_CASE("an object with one double is written as plain compact JSON", "[jsonio][write]") {
  CHECK(jsonio::to_text(json::object{{"a", 1.5}}) == R"({"a":1.5})");
  CHECK(jsonio::to_text(json::value(0.25)) == "0.25");
  CHECK(jsonio::to_text(json::value(120.0)) == "120");
  CHECK(jsonio::to_text(json::value(-2.5)) == "-2.5");
  CHECK(jsonio::to_text(json::value(21.333333333333332)) == "21.333333333333332");
}

TEST_CASE("doubles between 1e-6 and 1e16 are written without an exponent", "[jsonio][write]") {
  CHECK(jsonio::to_text(json::value(1e-6)) == "0.000001");
  CHECK(jsonio::to_text(json::value(1e-5)) == "0.00001");
  CHECK(jsonio::to_text(json::value(1e15)) == "1000000000000000");
  CHECK(jsonio::to_text(json::value(9999999999999998.0)) == "9999999999999998");
  CHECK(jsonio::to_text(json::value(0.1)) == "0.1");
}

TEST_CASE("tiny and huge doubles keep an exponent that is valid JSON", "[jsonio][write]") {
  CHECK(jsonio::to_text(json::value(1e16)) == "1e+16");
  CHECK(jsonio::to_text(json::value(1e20)) == "1e+20");
  CHECK(jsonio::to_text(json::value(1e-7)) == "1e-07");
  CHECK(jsonio::to_text(json::value(-1e300)) == "-1e+300");
  CHECK(jsonio::to_text(json::value(5e-324)) == "5e-324");
}

TEST_CASE("zero is written as 0 and negative zero keeps its sign", "[jsonio][write]") {
  CHECK(jsonio::to_text(json::value(0.0)) == "0");
  CHECK(jsonio::to_text(json::value(-0.0)) == "-0.0");
  const double back = as_double(reparse(jsonio::to_text(json::value(-0.0))));
  CHECK(back == 0.0);
  CHECK(std::signbit(back));
}

TEST_CASE("non-finite doubles are written as null, never as a token that is not JSON", "[jsonio][write]") {
  const json::object o{{"inf", std::numeric_limits<double>::infinity()},
                       {"ninf", -std::numeric_limits<double>::infinity()},
                       {"nan", std::numeric_limits<double>::quiet_NaN()}};
  CHECK(jsonio::to_text(o) == R"({"inf":null,"ninf":null,"nan":null})");
}

TEST_CASE("every double written reads back to the same bits", "[jsonio][write]") {
  std::vector<double> values = {0.1,
                                0.2,
                                0.3,
                                1.0 / 3.0,
                                2.0 / 3.0,
                                1e-7,
                                1e-6,
                                9.999999999999999e-7,
                                1e-5,
                                123456.789,
                                1e15,
                                9007199254740992.0,  // 2^53
                                9007199254740994.0,
                                1e16,
                                1.7976931348623157e308,
                                1e300,
                                -1e300,
                                2.2250738585072014e-308,  // smallest normal
                                2.2250738585072009e-308,  // largest denormal
                                4.9406564584124654e-324,  // smallest denormal
                                -4.9406564584124654e-324,
                                std::numeric_limits<double>::epsilon(),
                                1.0 + std::numeric_limits<double>::epsilon(),
                                std::nextafter(1e16, 0.0),
                                std::nextafter(1e-6, 0.0),
                                std::nextafter(1e-6, 1.0)};
  // A spread of magnitudes, with awkward mantissas.
  for (int e = -320; e <= 308; e += 7) values.push_back(1.2345678901234567 * std::pow(10.0, e));
  for (double d : values) {
    const std::string text = jsonio::to_text(json::value(d));
    INFO(text);
    CHECK(text.find_first_of("EIN") == std::string::npos);  // no Boost exponent, Infinity or NaN
    CHECK(std::bit_cast<std::uint64_t>(as_double(reparse(text))) == std::bit_cast<std::uint64_t>(d));
  }
}

TEST_CASE("integers are written in full, from int64 min to uint64 max", "[jsonio][write]") {
  const std::int64_t lo = std::numeric_limits<std::int64_t>::min();
  const std::uint64_t hi = std::numeric_limits<std::uint64_t>::max();
  CHECK(jsonio::to_text(json::value(lo)) == "-9223372036854775808");
  CHECK(jsonio::to_text(json::value(hi)) == "18446744073709551615");
  CHECK(reparse(jsonio::to_text(json::value(lo))) == json::value(lo));
  CHECK(reparse(jsonio::to_text(json::value(hi))) == json::value(hi));
  for (std::int64_t i : {std::int64_t(0), std::int64_t(-1), std::int64_t(1) << 53, -(std::int64_t(1) << 53)}) {
    CHECK(reparse(jsonio::to_text(json::value(i))) == json::value(i));
  }
}

TEST_CASE("strings with control characters, quotes and unicode are escaped and read back", "[jsonio][write]") {
  const std::string s =
      std::string("tab\tnl\nquote\"back\\slash\x01nul") + '\0' + "end \xC3\xA9\xE2\x82\xAC\xF0\x9F\x98\x80";
  const std::string text = jsonio::to_text(json::value(json::string(s)));
  CHECK(text.find('\n') == std::string::npos);
  CHECK(text.find('\t') == std::string::npos);
  CHECK(text.find('\x01') == std::string::npos);
  CHECK(text.find(std::string(1, '\0')) == std::string::npos);
  const json::value back = reparse(text);
  REQUIRE(back.is_string());
  CHECK(std::string(back.get_string()) == s);
  // Keys are escaped the same way.
  CHECK(jsonio::to_text(json::object{{"a\"b", 1}}) == R"({"a\"b":1})");
}

TEST_CASE("nested arrays and objects are written in order and read back equal", "[jsonio][write]") {
  const json::value v = json::object{{"jobs", json::array{json::object{{"id", 1}, {"eta_s", 2.5}, {"x", nullptr}},
                                                          json::object{{"id", 2}, {"ok", true}, {"no", false}}}},
                                     {"empty_a", json::array{}},
                                     {"empty_o", json::object{}},
                                     {"deep", json::array{json::array{json::array{1.25, "s"}}}}};
  const std::string text = jsonio::to_text(v);
  CHECK(text == R"({"jobs":[{"id":1,"eta_s":2.5,"x":null},{"id":2,"ok":true,"no":false}],"empty_a":[],"empty_o":{},)"
                R"("deep":[[[1.25,"s"]]]})");
  CHECK(reparse(text) == v);
}

TEST_CASE("a value nested far deeper than any reader allows is written without recursion", "[jsonio][write]") {
  json::value v = json::array{};
  for (int i = 0; i < 20000; ++i) v = json::array{std::move(v)};
  const std::string text = jsonio::to_text(v);
  CHECK(text.size() == 2 * 20001);
  CHECK(text.front() == '[');
  CHECK(text.back() == ']');
}
