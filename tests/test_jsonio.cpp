// Tests for dtraced::jsonio: the strict parse (duplicate keys, depth limit, located syntax errors,
// correctly rounded doubles) and the located reader (shapes, keys with did-you-mean, integers up to
// 2^53, numbers, strings, the error cap, lazy JSON Pointers), which scenes, wire messages and
// config files share.
#include <array>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstdint>
#include <limits>
#include <optional>
#include <random>
#include <string>
#include <string_view>
#include <vector>

#include <boost/json/serialize.hpp>
#include <catch2/catch.hpp>

#include "jsonio/parse.h"
#include "jsonio/path.h"
#include "jsonio/reader.h"
#include "jsonio/utf8.h"

namespace {

namespace json = boost::json;
namespace jsonio = dtraced::jsonio;
using jsonio::Fields;
using jsonio::Need;
using jsonio::Path;
using jsonio::Reader;

json::value parse_ok(std::string_view text) {
  jsonio::Document doc = jsonio::parse_strict(text, 16, 10);
  INFO(text);
  REQUIRE(doc.parsed);
  REQUIRE(doc.errors.empty());
  return std::move(doc.value);
}

// The one error a reading reported, as "PATH: MESSAGE".
std::string only_error(Reader& r) {
  const dtraced::util::Errors errors = r.take_errors();
  REQUIRE(errors.size() == 1);
  return errors[0].to_string();
}

constexpr std::array<std::string_view, 4> kKnown = {"radius", "color", "loc", "material"};

}  // namespace

// ---- parse ---------------------------------------------------------------------------------

TEST_CASE("duplicate keys are reported at their path, and parsing goes on", "[jsonio][parse]") {
  const jsonio::Document doc = jsonio::parse_strict(R"({"a": {"b": 1, "b": 2}, "c": [{"d": 1, "d": 1}]})", 16, 10);
  REQUIRE(doc.parsed);
  REQUIRE(doc.errors.size() == 2);
  CHECK(doc.errors[0].to_string() == "/a/b: duplicate key \"b\"");
  CHECK(doc.errors[1].to_string() == "/c/0/d: duplicate key \"d\"");
  // The last occurrence is the one kept.
  CHECK(doc.value.at("a").at("b").as_int64() == 2);
}

TEST_CASE("nesting is bounded by the depth limit, located where it is crossed", "[jsonio][parse]") {
  CHECK(jsonio::parse_strict("[[[1]]]", 3, 10).parsed);
  const jsonio::Document doc = jsonio::parse_strict(R"({"a": [[1]]})", 2, 10);
  CHECK_FALSE(doc.parsed);
  REQUIRE(doc.errors.size() == 1);
  CHECK(doc.errors[0].path == "/a/0");
  CHECK(doc.errors[0].message.find("nesting is deeper than the limit of 2 levels") != std::string::npos);
}

TEST_CASE("a syntax error names its line, column, byte and path", "[jsonio][parse]") {
  const jsonio::Document doc = jsonio::parse_strict("{\n  \"a\": [1,, 2]\n}", 16, 10);
  CHECK_FALSE(doc.parsed);
  CHECK(doc.value.is_null());
  REQUIRE(doc.errors.size() == 1);
  CHECK(doc.errors[0].path == "/a/1");
  CHECK(doc.errors[0].message.starts_with("invalid JSON at line 2, column 11 (byte 12): "));

  CHECK(jsonio::parse_strict("", 16, 10).errors.at(0).message.ends_with("unexpected end of input"));
  CHECK(
      jsonio::parse_strict("{} []", 16, 10).errors.at(0).message.ends_with("unexpected data after the JSON document"));
  CHECK_FALSE(jsonio::parse_strict("{\"a\": 1,}", 16, 10).parsed);         // no trailing commas
  CHECK_FALSE(jsonio::parse_strict("{\"a\": 1 /* x */}", 16, 10).parsed);  // no comments
  CHECK_FALSE(jsonio::parse_strict("\"\xff\"", 16, 10).parsed);            // UTF-8 only
}

TEST_CASE("doubles are read correctly rounded: the shortest text of any double reads back to its bits",
          "[jsonio][parse]") {
  // Fixed seed: the same 20000 doubles every run, finite ones of every exponent.
  std::mt19937_64 bits(20240601);
  int checked = 0;
  while (checked < 20000) {
    const double d = std::bit_cast<double>(bits());
    if (!std::isfinite(d)) continue;
    char text[64];
    const auto end = std::to_chars(text, text + sizeof text, d).ptr;
    const json::value v = parse_ok(std::string_view(text, static_cast<std::size_t>(end - text)));
    // Integral values may be printed without an exponent, and then read as integers.
    const double back = v.is_double()  ? v.get_double()
                        : v.is_int64() ? static_cast<double>(v.get_int64())
                                       : static_cast<double>(v.get_uint64());
    INFO(std::string_view(text, static_cast<std::size_t>(end - text)));
    REQUIRE(std::bit_cast<std::uint64_t>(back) == std::bit_cast<std::uint64_t>(d));
    ++checked;
  }
  // Decimal fractions that round to the nearest double, and the extremes.
  CHECK(parse_ok("0.30000000000000004").get_double() == 0.1 + 0.2);
  CHECK(parse_ok("2.2250738585072014e-308").get_double() == std::numeric_limits<double>::min());
  CHECK(parse_ok("1.7976931348623157e308").get_double() == std::numeric_limits<double>::max());
  CHECK(parse_ok("4.9e-324").get_double() == std::numeric_limits<double>::denorm_min());
}

TEST_CASE("a recorded double of any shape near where Boost's own value stops being exact reads as from_chars",
          "[jsonio][parse][stream]") {
  // EventLog::Cursor::double_value keeps Boost's value where it is provably correctly rounded
  // (at most 16 digits, 16 only below 9 * 10^15, a value in [1e-6, 1e21)) and asks from_chars
  // otherwise. Texts of 1 to 19 digits, with and without a point, leading zeros, signs, 'e' and
  // 'E', exponents of -30 to 30 with and without '+', so that both sides of each bound are met
  // many times; each is recorded as an element and read back both ways (the cursor, and build()
  // as the fallback reader does). Fixed seed: the same texts every run.
  std::mt19937_64 random(20261205);
  const auto pick = [&random](int lo, int hi) { return std::uniform_int_distribution<int>(lo, hi)(random); };
  std::vector<std::string> texts = {"9.007199254740993E15",
                                    "9007199254740993.0",
                                    "9007199254740991.5",
                                    "8.999999999999999E-22",
                                    "1.234567890123457E-7",
                                    "9.999999999999999E22",
                                    "1.5E-23",
                                    "4.9E-22",
                                    "-0.0",
                                    "0.000000000000000001",
                                    "1E-0",
                                    "0E400",
                                    "-0.0e-400",
                                    "9.99999999999999E20",
                                    "1E21",
                                    "1E-6",
                                    "9.99999999999999E-7"};
  while (texts.size() < 100000) {
    std::string text;
    if (pick(0, 1) == 1) text += '-';
    const int digits = pick(1, 19);
    const int point = pick(0, 2) == 0 ? 0 : pick(1, digits);  // digits before the point (0: none)
    const bool zero_first = point == 1 && pick(0, 3) == 0;    // "0.000ddd" (JSON allows no other leading 0)
    for (int i = 0; i < digits; ++i) {
      if (i == point && point > 0 && point < digits) text += '.';
      // Many 9s first, so that 16 digits above 9 * 10^15 and above 2^53 are met.
      char c = static_cast<char>('0' + pick(0, 9));
      if (i == 0) c = zero_first ? '0' : pick(0, 2) == 0 ? '9' : static_cast<char>('1' + pick(0, 8));
      text += c;
    }
    if ((point == 0 || point == digits) && pick(0, 1) == 0) text += ".5";
    if (pick(0, 3) != 0) {
      text += pick(0, 1) == 0 ? 'E' : 'e';
      const int e = pick(-30, 30);
      if (e >= 0 && pick(0, 1) == 0) text += '+';
      text += std::to_string(e);
    }
    texts.push_back(std::move(text));
  }
  std::string document = "{\"items\": [";
  for (std::size_t i = 0; i < texts.size(); ++i) document += (i == 0 ? "" : ", ") + texts[i];
  document += "]}";
  // Both kinds of log: texts converted by the consumer (kDouble), and doubles converted by the
  // parser as it reads them (kDoubleValue), in place or, near a piece's end or cut by it, copied.
  for (const bool convert : {false, true}) {
    INFO("convert_doubles " << convert);
    jsonio::EventLog log(convert);
    jsonio::StrictParser parser(64, 10);
    std::size_t doubles = 0, mismatches = 0;
    parser.record_elements("items", &log, [&](std::size_t i, const jsonio::EventLog& l, jsonio::EventLog::Mark begin) {
      jsonio::EventLog::Cursor c(l, begin, l.mark());
      REQUIRE(c.next());
      if (c.kind() == jsonio::EventLog::Kind::kDouble || c.kind() == jsonio::EventLog::Kind::kDoubleValue) {
        CHECK((c.kind() == jsonio::EventLog::Kind::kDoubleValue) == convert);
        double expected = 0;
        const std::string& t = texts[i];
        const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), expected);
        REQUIRE(ec == std::errc());
        REQUIRE(end == t.data() + t.size());
        const json::value built = l.build(begin, l.mark());
        const auto bits = std::bit_cast<std::uint64_t>(expected);
        if (std::bit_cast<std::uint64_t>(c.double_value()) != bits ||
            std::bit_cast<std::uint64_t>(built.as_double()) != bits) {
          UNSCOPED_INFO(t);
          ++mismatches;
        }
        ++doubles;
      }
      log.clear();
    });
    // In pieces, so that some texts arrive in parts.
    for (std::size_t at = 0; at < document.size(); at += 4093) {
      if (!parser.write(std::string_view(document).substr(at, 4093))) break;
    }
    const jsonio::Document doc = parser.finish();
    INFO((doc.errors.empty() ? std::string() : doc.errors[0].message));
    REQUIRE(doc.parsed);
    CHECK(doubles > 50000);
    CHECK(mismatches == 0);
  }
}

TEST_CASE("exact_number writes integral values as integers and others so they read back exactly", "[jsonio][write]") {
  CHECK(json::serialize(jsonio::exact_number(640.0)) == "640");
  CHECK(json::serialize(jsonio::exact_number(-0.0)) == "0");
  CHECK(json::serialize(jsonio::exact_number(9007199254740992.0)) == "9007199254740992");
  CHECK(jsonio::exact_number(18014398509481984.0).is_double());  // 2^54: beyond exact integers
  for (const double d : {0.1, 1e-300, 12.345678901234567, -3.5e20}) {
    const json::value back = parse_ok(json::serialize(jsonio::exact_number(d)));
    CHECK(std::bit_cast<std::uint64_t>(back.get_double()) == std::bit_cast<std::uint64_t>(d));
  }
}

// ---- reader: errors and paths --------------------------------------------------------------

TEST_CASE("paths are JSON Pointers, escaped, and built only from live parents", "[jsonio][path]") {
  const Path root;
  CHECK(root.str().empty());
  CHECK(root.is_root());
  const Path a = root.key("a/b");
  const Path list = a.index(3);
  CHECK(list.key("~x").str() == "/a~1b/3/~0x");
  CHECK(jsonio::pointer_escape("~/") == "~0~1");
  // A copy refers to the same parent: it names the same value.
  const Path copy = list;
  CHECK(copy.str() == "/a~1b/3");
  CHECK_FALSE(copy.is_root());
}

TEST_CASE("every error carries its file and path, and past the cap the rest are counted", "[jsonio][errors]") {
  Reader r("f.json", 3);
  const Path root;
  for (int i = 0; i < 5; ++i) r.error(root.index(static_cast<std::size_t>(i)), "bad");
  CHECK(r.error_count() == 5);
  CHECK(r.failed());
  const dtraced::util::Errors errors = r.take_errors();
  REQUIRE(errors.size() == 4);
  CHECK(errors[0].to_string() == "f.json: /0: bad");
  CHECK(errors[2].to_string() == "f.json: /2: bad");
  CHECK(errors[3].to_string() == "f.json: 2 more problems not shown");
  // Taking the errors starts afresh.
  CHECK_FALSE(r.failed());
  CHECK(r.take_errors().empty());
}

TEST_CASE("a reader's parse reports the size limit, syntax errors and duplicate keys", "[jsonio][errors]") {
  Reader r("", 10);
  CHECK_FALSE(r.parse("[1, 2]", "body", 5, 8));
  CHECK(only_error(r) == "body is 6 bytes, larger than the limit of 5 bytes");

  const auto dup = r.parse(R"({"a": 1, "a": 2})", "body", 100, 8);
  REQUIRE(dup);
  CHECK(only_error(r) == "/a: duplicate key \"a\"");

  // Duplicate keys fill the cap, but the syntax error after them is still shown.
  Reader capped("", 2);
  CHECK_FALSE(capped.parse(R"({"a": 1, "a": 2, "a": 3, "b": })", "body", 100, 8));
  const dtraced::util::Errors errors = capped.take_errors();
  REQUIRE_FALSE(errors.empty());
  CHECK(errors[0].message == "duplicate key \"a\"");
  CHECK(errors[1].message.starts_with("invalid JSON"));
}

// ---- reader: shapes and keys ---------------------------------------------------------------

TEST_CASE("unknown keys get a did-you-mean within two edits or by alias, else the known keys", "[jsonio][keys]") {
  CHECK(jsonio::unknown_key_message("raduis", kKnown) == "unknown key \"raduis\" (did you mean \"radius\"?)");
  CHECK(jsonio::unknown_key_message("colour", kKnown) == "unknown key \"colour\" (did you mean \"color\"?)");
  CHECK(jsonio::unknown_key_message("frobnicate", kKnown) ==
        "unknown key \"frobnicate\"; known keys: radius, color, loc, material");
  // One edit away, but the whole key: "x" is not a misspelling of "loc"... nor of anything.
  CHECK(jsonio::unknown_key_message("x", std::array<std::string_view, 1>{"y"}).find("known keys: y") !=
        std::string::npos);
  // The caller's aliases: only towards a key that is known here.
  const std::array<jsonio::KeyAlias, 2> aliases = {{{"center", "loc"}, {"spp", "samples"}}};
  CHECK(jsonio::unknown_key_message("center", kKnown, aliases) == "unknown key \"center\" (did you mean \"loc\"?)");
  CHECK(jsonio::unknown_key_message("spp", kKnown, aliases).find("known keys") != std::string::npos);

  Reader r;
  const json::value v = parse_ok(R"({"loc": 1, "raduis": 2})");
  const Path root;
  r.check_keys(v.as_object(), root.key("sphere"), kKnown);
  CHECK(only_error(r) == "/sphere/raduis: unknown key \"raduis\" (did you mean \"radius\"?)");
}

TEST_CASE("shapes: objects, arrays with a limit, tuples, required keys", "[jsonio][shapes]") {
  Reader r;
  const Path root;
  CHECK(r.object(parse_ok("[]"), root) == nullptr);
  CHECK(only_error(r) == "expected a JSON object at the top level, got an array");
  CHECK(r.object(parse_ok("3"), root.key("camera")) == nullptr);
  CHECK(only_error(r) == "/camera: expected an object, got a number");

  CHECK(r.array(parse_ok("[1, 2, 3]"), root.key("lights"), 2, "lights") == nullptr);
  CHECK(only_error(r) == "/lights: too many lights: 3 (limit 2)");
  CHECK(r.array(parse_ok("[1, 2]"), root.key("lights"), 2, "lights") != nullptr);
  CHECK(r.array(parse_ok("null"), root.key("lights")) == nullptr);
  CHECK(only_error(r) == "/lights: expected an array, got null");

  CHECK(r.tuple(parse_ok("[1]"), root.key("loc"), 3, "numbers") == nullptr);
  CHECK(only_error(r) == "/loc: expected an array of 3 numbers, got 1 element");
  CHECK(r.tuple(parse_ok("[1, 2]"), root.key("loc"), 3, "numbers") == nullptr);
  CHECK(only_error(r) == "/loc: expected an array of 3 numbers, got 2 elements");
  CHECK(r.tuple(parse_ok("\"x\""), root.key("loc"), 3, "numbers") == nullptr);
  CHECK(only_error(r) == "/loc: expected an array of 3 numbers, got a string");

  const json::value o = parse_ok(R"({"a": 1})");
  CHECK(r.get(o.as_object(), "a", root, Need::kRequired) != nullptr);
  CHECK(r.get(o.as_object(), "b", root, Need::kOptional) == nullptr);
  CHECK_FALSE(r.failed());
  CHECK(r.get(o.as_object(), "b", root, Need::kRequired) == nullptr);
  CHECK(only_error(r) == "/b: required key is missing");
}

// ---- reader: scalars -----------------------------------------------------------------------

TEST_CASE("integers: bounds up to 2^53 either side, integral doubles accepted", "[jsonio][numbers]") {
  constexpr std::int64_t k53 = jsonio::kMaxExactInteger;
  Reader r;
  const Path root;
  const Path at = root.key("n");
  CHECK(r.integer(parse_ok("9007199254740992"), at, 0, k53) == k53);
  CHECK(r.integer(parse_ok("-9007199254740992"), at, -k53, 0) == -k53);
  CHECK(r.integer(parse_ok("9007199254740992.0"), at, 0, k53) == k53);
  CHECK(r.integer(parse_ok("1e3"), at, 0, 1000) == 1000);
  CHECK(r.integer(parse_ok("-0.0"), at, 0, 10) == 0);
  CHECK_FALSE(r.failed());

  CHECK_FALSE(r.integer(parse_ok("9007199254740992"), at, 0, k53 - 1));
  CHECK(only_error(r) == "/n: must be an integer in [0, 9007199254740991] (got 9007199254740992)");
  CHECK_FALSE(r.integer(parse_ok("18446744073709551615"), at, 0, k53));  // a uint64: beyond every bound
  CHECK(only_error(r) == "/n: must be an integer in [0, 9007199254740992] (got 18446744073709551615)");
  CHECK_FALSE(r.integer(parse_ok("1e300"), at, -k53, k53));  // never converted: no overflow
  CHECK(only_error(r).find("must be an integer in [") != std::string::npos);
  CHECK_FALSE(r.integer(parse_ok("-1"), at, 0, 5));
  CHECK(only_error(r) == "/n: must be an integer in [0, 5] (got -1)");
  CHECK_FALSE(r.integer(parse_ok("2.5"), at, 0, 5));
  CHECK(only_error(r) == "/n: must be an integer (got 2.5)");
  CHECK_FALSE(r.integer(parse_ok("1e400"), at, 0, 5));
  CHECK(only_error(r) == "/n: number is out of range (overflows a double)");
  CHECK_FALSE(r.integer(parse_ok("\"3\""), at, 0, 5));
  CHECK(only_error(r) == "/n: expected an integer, got a string");
}

TEST_CASE("numbers: finite, -0 read as +0, ranges worded alike", "[jsonio][numbers]") {
  Reader r;
  const Path root;
  const Path at = root.key("x");
  const std::optional<double> zero = r.number(parse_ok("-0.0"), at);
  REQUIRE(zero);
  CHECK_FALSE(std::signbit(*zero));
  CHECK(r.number(parse_ok("18446744073709551615"), at) == 18446744073709551615.0);
  CHECK_FALSE(r.failed());

  CHECK_FALSE(r.number(parse_ok("-1e400"), at));
  CHECK(only_error(r) == "/x: number is out of range (overflows a double)");
  CHECK_FALSE(r.number(parse_ok("null"), at));
  CHECK(only_error(r) == "/x: expected a number, got null");
  CHECK_FALSE(r.number(parse_ok("1.5"), at, 0, 1));
  CHECK(only_error(r) == "/x: must be in [0, 1] (got 1.5)");
  CHECK_FALSE(r.number(parse_ok("-2"), at, 0, std::numeric_limits<double>::max()));
  CHECK(only_error(r) == "/x: must be >= 0 (got -2)");
  CHECK_FALSE(r.positive(0.0, at));
  CHECK(only_error(r) == "/x: must be > 0 (got 0)");
}

TEST_CASE("strings with a byte limit, booleans, and one of a set of names", "[jsonio][strings]") {
  Reader r;
  const Path root;
  const Path at = root.key("s");
  CHECK(r.string(parse_ok("\"abc\""), at, 3) == std::string_view("abc"));
  CHECK_FALSE(r.string(parse_ok("\"abcd\""), at, 3));
  CHECK(only_error(r) == "/s: string is 4 bytes, longer than the limit of 3");
  CHECK_FALSE(r.string(parse_ok("[]"), at));
  CHECK(only_error(r) == "/s: expected a string, got an array");

  CHECK(r.boolean(parse_ok("false"), at) == false);
  CHECK_FALSE(r.boolean(parse_ok("0"), at));
  CHECK(only_error(r) == "/s: expected true or false, got a number");

  constexpr std::array<std::string_view, 3> kStates = {"queued", "rendering", "done"};
  CHECK(r.choice(parse_ok("\"done\""), at, kStates, "state", "states") == 2u);
  CHECK_FALSE(r.choice(parse_ok("\"paused\""), at, kStates, "state", "states"));
  CHECK(only_error(r) == "/s: unknown state \"paused\"; known states: queued, rendering, done");
  CHECK_FALSE(r.choice(parse_ok("3"), at, kStates, "state", "states"));
  CHECK(only_error(r) == "/s: expected a string (queued, rendering or done), got a number");
  // A long string is not quoted back.
  CHECK_FALSE(r.choice(json::value(std::string(100, 'x')), at, kStates, "state", "states"));
  CHECK(only_error(r) == "/s: unknown state (a string of 100 bytes); known states: queued, rendering, done");
}

TEST_CASE("fields: required and optional keys, values kept when absent or wrong", "[jsonio][fields]") {
  constexpr std::array<std::string_view, 5> kKeys = {"id", "name", "ratio", "limit", "on"};
  const json::value v = parse_ok(R"({"id": 7, "name": "w", "ratio": 2, "extra": 1})");
  Reader r("c.json");
  const Path root;
  Fields f(r, v.as_object(), root.key("job"), kKeys);
  CHECK(only_error(r) == "c.json: /job/extra: unknown key \"extra\"; known keys: id, name, ratio, limit, on");

  std::uint32_t id = 0;
  CHECK(f.integer("id", id, 1, 10));
  CHECK(id == 7);
  std::string name;
  CHECK(f.string("name", name, 8));
  CHECK(name == "w");
  double ratio = 0.5;
  CHECK_FALSE(f.number("ratio", ratio, 0, 1));
  CHECK(ratio == 0.5);  // left alone
  CHECK(only_error(r) == "c.json: /job/ratio: must be in [0, 1] (got 2)");

  std::optional<std::uint32_t> limit;
  CHECK(f.integer("limit", limit, 0, 5));  // absent and optional: fine, still unset
  CHECK_FALSE(limit);
  bool on = true;
  CHECK_FALSE(f.boolean("on", on));
  CHECK(on);
  CHECK(only_error(r) == "c.json: /job/on: required key is missing");
  CHECK(f.path("name").str() == "/job/name");
}

// ---- what a message echoes of a document --------------------------------------------------------

TEST_CASE("control characters in keys and strings are escaped in every message and pointer", "[jsonio][escape]") {
  // A scene whose key carries a newline and a forged log line, and an ANSI escape (clear screen).
  const std::string forged = "ra\ndtraced: info: job 7 done\x1b[2J";
  const std::string escaped = "ra\\ndtraced: info: job 7 done\\u001b[2J";
  const auto no_raw_controls = [](const std::string& s) {
    INFO(s);
    for (const char c : s) CHECK(static_cast<unsigned char>(c) >= 0x20);
    CHECK(s.find('\x7f') == std::string::npos);
  };

  SECTION("an unknown key, at its pointer and in its message") {
    Reader r("s.json");
    const json::value v = parse_ok(R"({"ra\ndtraced: info: job 7 done\u001b[2J": 1})");
    const Path root;
    r.check_keys(v.as_object(), root.key("sphere"), kKnown);
    const std::string e = only_error(r);
    no_raw_controls(e);
    CHECK(e ==
          "s.json: /sphere/" + escaped + ": unknown key \"" + escaped + "\"; known keys: radius, color, loc, material");
  }
  SECTION("a duplicate key, from the parser") {
    const jsonio::Document doc = jsonio::parse_strict(R"({"a\tb\r": 1, "a\tb\r": 2})", 16, 10);
    REQUIRE(doc.errors.size() == 1);
    CHECK(doc.errors[0].to_string() == "/a\\tb\\r: duplicate key \"a\\tb\\r\"");
  }
  SECTION("a syntax error under such a key") {
    const jsonio::Document doc = jsonio::parse_strict("{\"a\\u0007\": [1, }", 16, 10);
    REQUIRE(doc.errors.size() == 1);
    no_raw_controls(doc.errors[0].to_string());
    CHECK(doc.errors[0].path == "/a\\u0007/1");
  }
  SECTION("a string value that is not one of the names") {
    Reader r;
    constexpr std::array<std::string_view, 1> kTypes = {"sphere"};
    const Path root;
    CHECK_FALSE(r.choice(json::value(forged), root.key("type"), kTypes, "type", "types"));
    CHECK(only_error(r) == "/type: unknown type \"" + escaped + "\"; known types: sphere");
  }
  SECTION("a path built by hand") {
    const Path root;
    CHECK(root.key(forged).str() == "/" + escaped);
  }
}

TEST_CASE("printable escapes C0, DEL, C1, separators and bidi controls, keeps other text, marks bad bytes",
          "[jsonio][escape]") {
  using jsonio::printable;
  CHECK(printable("plain text, café, 東京") == "plain text, café, 東京");
  CHECK(printable(std::string_view("a\0b", 3)) == "a\\u0000b");
  CHECK(printable("\x01\x1f\x7f") == "\\u0001\\u001f\\u007f");
  CHECK(printable("\n\r\t") == "\\n\\r\\t");
  CHECK(printable("back\\slash") == "back\\\\slash");  // so that "\n" in the output is always an escape
  CHECK(printable("\xc2\x9b"
                  "31m") == "\\u009b31m");  // C1 CSI
  CHECK(printable("\xe2\x80\xa8\xe2\x80\xa9") == "\\u2028\\u2029");
  CHECK(printable("\xe2\x80\xae"
                  "evil\xe2\x81\xa6") == "\\u202eevil\\u2066");
  CHECK(printable("\xff"
                  "a\xc3") == "\\xffa\\xc3");  // not UTF-8: shown as bytes
  CHECK(printable("say \"hi\"") == "say \"hi\"");
  CHECK(jsonio::quoted("say \"hi\"\n") == "\"say \\\"hi\\\"\\n\"");
  // Long text is cut at a character boundary, never inside one.
  CHECK(jsonio::quoted("ééé", 5) == "\"éé...\"");
  CHECK(jsonio::quoted(std::string(300, 'x')).size() == 200 + 5);
}

TEST_CASE("utf8_at decodes RFC 3629 sequences and refuses overlong, surrogate, too large and cut ones",
          "[jsonio][escape]") {
  using jsonio::utf8_at;
  CHECK(utf8_at("a", 0).length == 1);
  CHECK(utf8_at("\xc3\xa9", 0).length == 2);
  CHECK(utf8_at("\xc3\xa9", 0).code_point == U'\u00e9');
  CHECK(utf8_at("\xe6\x9d\xb1", 0).code_point == U'\u6771');
  CHECK(utf8_at("\xf4\x8f\xbf\xbf", 0).code_point == U'\U0010ffff');
  for (const std::string_view bad : {"\xc0\x80", "\xc1\xbf", "\xe0\x80\x80", "\xed\xa0\x80", "\xf4\x90\x80\x80",
                                     "\xf5\x80\x80\x80", "\x80", "\xe6\x9d", "\xc3"}) {
    INFO(jsonio::printable(bad));
    CHECK(utf8_at(bad, 0).length == 0);
  }
}

TEST_CASE("StrictParser: pieces of any size, a split array handed over element by element", "[jsonio][stream]") {
  const std::string text =
      "{\"a\": 1,\n \"items\": [{\"x\": [1, 2.5]}, 7, \"s\\u00e9\", [], null, {\"y\": {\"z\": true}}],\n"
      " \"b\": {\"items\": [1]}, \"c\": [0.1]}";
  const jsonio::Document whole = jsonio::parse_strict(text, 64, 10);
  REQUIRE(whole.parsed);
  for (const std::size_t piece : {std::size_t(1), std::size_t(3), std::size_t(7), text.size()}) {
    INFO("piece " << piece);
    jsonio::StrictParser parser(64, 10);
    std::vector<std::pair<std::size_t, std::string>> got;
    parser.split_array("items", [&](std::size_t i, json::value& v) { got.push_back({i, json::serialize(v)}); });
    for (std::size_t at = 0; at < text.size(); at += piece)
      REQUIRE(parser.write(std::string_view(text).substr(at, piece)));
    const jsonio::Document doc = parser.finish();
    REQUIRE(doc.parsed);
    CHECK(parser.split_seen());
    REQUIRE(got.size() == 6);
    const json::array& items = whole.value.at("items").as_array();
    for (std::size_t i = 0; i < got.size(); ++i) {
      CHECK(got[i].first == i);
      CHECK(got[i].second == json::serialize(items[i]));
    }
    // The split array is empty in the document; everything else (a nested "items" too) is kept.
    CHECK(doc.value.at("items").as_array().empty());
    CHECK(json::serialize(doc.value.at("b")) == json::serialize(whole.value.at("b")));
    CHECK(doc.value.at("c") == whole.value.at("c"));
    CHECK(doc.value.at("a") == whole.value.at("a"));
  }
}

TEST_CASE("StrictParser: recorded elements build the values split_array hands over, with the same errors",
          "[jsonio][stream]") {
  // Strings with escapes and numbers that cross pieces arrive in parts; a duplicate key inside an
  // element and one outside; every kind of value, nested, and as a whole element.
  const std::string text =
      "{\"a\": 1,\n \"items\": [{\"x\": [1, 2.5, -0.0, 1e-400, 18446744073709551615, -9223372036854775808],"
      " \"k\\u00e9y\": \"s\\n\\u00e9 long enough to be cut\", \"d\": {}, \"d\": 2}, 7, 0.1, \"s\\u00e9\", [], null,"
      " {\"y\": {\"z\": true, \"w\": false}}, 3.14159265358979323846e-300, [[[]]]],\n"
      " \"b\": {\"items\": [1], \"b\": 2, \"b\": 3}, \"c\": [0.1]}";
  const jsonio::Document whole = jsonio::parse_strict(text, 64, 10);
  REQUIRE(whole.parsed);
  REQUIRE(whole.errors.size() == 2);  // "d" in the first element, "b" in "b"
  const json::array& items = whole.value.at("items").as_array();
  for (const std::size_t piece : {std::size_t(1), std::size_t(3), std::size_t(7), text.size()}) {
    INFO("piece " << piece);
    jsonio::EventLog log;
    jsonio::StrictParser parser(64, 10);
    std::vector<std::pair<std::size_t, json::value>> got;
    dtraced::util::Errors duplicates;  // the elements' (the parser leaves them to the consumer), and of which
    std::vector<std::size_t> duplicate_elements;
    parser.record_elements("items", &log, [&](std::size_t i, const jsonio::EventLog& l, jsonio::EventLog::Mark begin) {
      CHECK(&l == &log);
      std::size_t keys = 0;
      got.push_back({i, l.build(begin, l.mark(), {}, &keys)});
      // The value keeps one of a duplicate key: fewer keys than the events have.
      if (i == 0) CHECK((keys == 4 && got.back().second.as_object().size() == 3));
      CHECK(l.duplicate_keys(begin, l.mark(), "/items/" + std::to_string(i), 10, duplicates) == (i == 0));
      duplicate_elements.resize(duplicates.size(), i);
      if (i % 2 == 0) log.clear();  // the sink may clear the log
    });
    for (std::size_t at = 0; at < text.size(); at += piece)
      REQUIRE(parser.write(std::string_view(text).substr(at, piece)));
    const jsonio::Document doc = parser.finish();
    REQUIRE(doc.parsed);
    CHECK(parser.split_seen());
    REQUIRE(got.size() == items.size());
    for (std::size_t i = 0; i < got.size(); ++i) {
      CHECK(got[i].first == i);
      CHECK(json::serialize(got[i].second) == json::serialize(items[i]));
    }
    // Doubles to the bit (serialize would not tell -0 from a value that prints alike).
    const json::array& x = got[0].second.at("x").as_array();
    CHECK(std::bit_cast<std::uint64_t>(x[2].as_double()) == std::bit_cast<std::uint64_t>(-0.0));
    CHECK(x[3] == items[0].at("x").as_array()[3]);
    CHECK(got[2].second.as_double() == 0.1);
    CHECK(got[7].second.as_double() == items[7].as_double());
    CHECK(doc.value.at("items").as_array().empty());
    CHECK(json::serialize(doc.value.at("b")) == json::serialize(whole.value.at("b")));
    // The parser's own ("b", after every element) and the elements', in the document's order.
    REQUIRE(doc.errors.size() == 1);
    REQUIRE(parser.error_elements() == std::vector<std::size_t>{items.size()});
    REQUIRE(duplicate_elements == std::vector<std::size_t>{0});
    CHECK(duplicates[0].message == whole.errors[0].message);
    CHECK(duplicates[0].path == whole.errors[0].path);
    CHECK(doc.errors[0].message == whole.errors[1].message);
    CHECK(doc.errors[0].path == whole.errors[1].path);
    CHECK_FALSE(parser.open_element());
  }
  SECTION("an element cut short by a syntax error: its duplicate keys, then the error at its path") {
    const std::string cut = "{\"items\": [1, {\"a\": {\"b\": 1, \"b\": [2, 3]}, \"a\": 4, \"c\": [5,, 6]}]}";
    const jsonio::Document cut_whole = jsonio::parse_strict(cut, 64, 10);
    REQUIRE(cut_whole.errors.size() == 3);  // "b", "a", the syntax error
    for (const std::size_t piece : {std::size_t(1), std::size_t(4), cut.size()}) {
      INFO("piece " << piece);
      jsonio::EventLog log;
      jsonio::StrictParser parser(64, 10);
      std::size_t elements = 0;
      parser.record_elements("items", &log, [&](std::size_t, const jsonio::EventLog&, jsonio::EventLog::Mark) {
        ++elements;
        log.clear();
      });
      for (std::size_t at = 0; at < cut.size(); at += piece) {
        if (!parser.write(std::string_view(cut).substr(at, piece))) break;
      }
      const jsonio::Document doc = parser.finish();
      REQUIRE_FALSE(doc.parsed);
      CHECK(elements == 1);
      CHECK(parser.error_elements().empty());
      const auto open = parser.open_element();
      REQUIRE(open);
      CHECK(open->second == 1);
      dtraced::util::Errors errors;
      CHECK(log.duplicate_keys(open->first, log.mark(), "/items/1", 10, errors));
      REQUIRE(doc.errors.size() == 1);
      errors.push_back(doc.errors[0]);
      REQUIRE(errors.size() == cut_whole.errors.size());
      for (std::size_t i = 0; i < errors.size(); ++i) {
        CHECK(errors[i].message == cut_whole.errors[i].message);
        CHECK(errors[i].path == cut_whole.errors[i].path);
      }
      // At most as many as asked for.
      dtraced::util::Errors one;
      CHECK(log.duplicate_keys(open->first, log.mark(), "/items/1", 1, one));
      CHECK(one.size() == 1);
    }
  }
  SECTION("past 64 keys an object's duplicates are not tracked, as in a document") {
    std::string many = "{\"items\": [{";
    for (int k = 0; k < 64; ++k) many += "\"k" + std::to_string(k) + "\": 0, ";
    many += "\"k0\": 1}, {\"x\": 0, \"x\": 0}]}";
    const jsonio::Document many_whole = jsonio::parse_strict(many, 64, 10);
    REQUIRE(many_whole.errors.size() == 1);
    jsonio::EventLog log;
    jsonio::StrictParser parser(64, 10);
    dtraced::util::Errors errors;
    parser.record_elements("items", &log, [&](std::size_t i, const jsonio::EventLog& l, jsonio::EventLog::Mark begin) {
      l.duplicate_keys(begin, l.mark(), "/items/" + std::to_string(i), 10, errors);
    });
    REQUIRE(parser.write(many));
    REQUIRE(parser.finish().parsed);
    REQUIRE(errors.size() == 1);
    CHECK(errors[0].message == many_whole.errors[0].message);
    CHECK(errors[0].path == many_whole.errors[0].path);
  }
  SECTION("a cursor walks an element's events, texts whole") {
    jsonio::EventLog log;
    jsonio::StrictParser parser(64, 10);
    std::vector<std::string> seen;
    parser.record_elements("items", &log, [&](std::size_t, const jsonio::EventLog& l, jsonio::EventLog::Mark begin) {
      jsonio::EventLog::Cursor c(l, begin, l.mark());
      while (c.next()) seen.push_back(std::to_string(int(c.kind())) + ":" + std::string(c.text()));
    });
    const std::string_view small = R"({"items": [{"ab\u0063": [2.50, 3]}, "t"]})";
    for (std::size_t at = 0; at < small.size(); at += 2) REQUIRE(parser.write(small.substr(at, 2)));
    REQUIRE(parser.finish().parsed);
    using K = jsonio::EventLog::Kind;
    const auto k = [](K kind, std::string_view t = {}) { return std::to_string(int(kind)) + ":" + std::string(t); };
    CHECK(seen == std::vector<std::string>{k(K::kObjectBegin), k(K::kKey, "abc"), k(K::kArrayBegin),
                                           k(K::kDouble, "2.50"), k(K::kInt64), k(K::kArrayEnd), k(K::kObjectEnd),
                                           k(K::kString, "t")});
  }
}

TEST_CASE("StrictParser: a syntax error found in a later piece has the whole text's position", "[jsonio][stream]") {
  const std::string text = "{\"items\": [1,\n 2,\n 3 4]}";  // line 3, column 4
  const jsonio::Document whole = jsonio::parse_strict(text, 64, 10);
  REQUIRE_FALSE(whole.parsed);
  REQUIRE(whole.errors.size() == 1);
  for (const std::size_t piece : {std::size_t(1), std::size_t(5), text.size()}) {
    INFO("piece " << piece);
    jsonio::StrictParser parser(64, 10);
    std::size_t elements = 0;
    parser.split_array("items", [&](std::size_t, json::value&) { ++elements; });
    for (std::size_t at = 0; at < text.size(); at += piece) {
      if (!parser.write(std::string_view(text).substr(at, piece))) break;
    }
    const jsonio::Document doc = parser.finish();
    CHECK_FALSE(doc.parsed);
    REQUIRE(doc.errors.size() == 1);
    CHECK(doc.errors[0].message == whole.errors[0].message);
    CHECK(doc.errors[0].message.find("line 3, column 4") != std::string::npos);
    CHECK(doc.errors[0].path == whole.errors[0].path);
    CHECK(elements == 3);  // 1, 2 and 3 were complete
  }
  SECTION("unexpected end of input") {
    jsonio::StrictParser parser(64, 10);
    REQUIRE(parser.write("{\"a\": [1,\n"));
    const jsonio::Document doc = parser.finish();
    CHECK_FALSE(doc.parsed);
    REQUIRE(doc.errors.size() == 1);
    CHECK(doc.errors[0].message == jsonio::parse_strict("{\"a\": [1,\n", 64, 10).errors[0].message);
  }
}
