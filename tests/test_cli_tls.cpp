// The command line's TLS and enrollment rules: --tls auto|on|off against the listen address,
// join-code lifetimes and systemd instance names.
#include <catch2/catch.hpp>

#include "cli/enroll_verbs.h"
#include "cli/tls_flags.h"

using namespace dtraced::cli;

TEST_CASE("loopback addresses are told from the others", "[cli][tls]") {
  CHECK(is_loopback_address("127.0.0.1"));
  CHECK(is_loopback_address("127.8.9.10"));
  CHECK(is_loopback_address("::1"));
  CHECK_FALSE(is_loopback_address("0.0.0.0"));
  CHECK_FALSE(is_loopback_address("::"));
  CHECK_FALSE(is_loopback_address("10.0.0.7"));
  CHECK_FALSE(is_loopback_address("not an address"));
}

TEST_CASE("tls flag: auto is on off loopback and off on it", "[cli][tls]") {
  CHECK(resolve_tls("auto", "0.0.0.0", false).value() == true);
  CHECK(resolve_tls("auto", "192.0.2.1", false).value() == true);
  CHECK(resolve_tls("auto", "127.0.0.1", false).value() == false);
  CHECK(resolve_tls("auto", "::1", false).value() == false);
  CHECK(resolve_tls("on", "127.0.0.1", false).value() == true);
  CHECK(resolve_tls("off", "127.0.0.1", false).value() == false);
}

TEST_CASE("tls flag: plain HTTP off loopback needs --allow-plain-http", "[cli][tls]") {
  const auto refused = resolve_tls("off", "0.0.0.0", false);
  REQUIRE_FALSE(refused);
  CHECK(refused.error().path == "--tls");
  CHECK_THAT(refused.error().message, Catch::Contains("--allow-plain-http"));
  CHECK(resolve_tls("off", "0.0.0.0", true).value() == false);
  const auto unknown = resolve_tls("maybe", "127.0.0.1", false);
  REQUIRE_FALSE(unknown);
  CHECK_THAT(unknown.error().message, Catch::Contains("auto, on or off"));
}

TEST_CASE("join-code lifetimes read as durations within bounds", "[cli][enroll]") {
  CHECK(parse_duration_seconds("90s", 604800).value() == 90);
  CHECK(parse_duration_seconds("30m", 604800).value() == 1800);
  CHECK(parse_duration_seconds("1h", 604800).value() == 3600);
  CHECK(parse_duration_seconds("7d", 604800).value() == 604800);
  CHECK(parse_duration_seconds("45", 604800).value() == 45);
  for (const char* bad : {"", "h", "0s", "8d", "1.5h", "-1h", "1w", "1 h", "99999999999999999999s"}) {
    INFO(bad);
    CHECK_FALSE(parse_duration_seconds(bad, 604800));
  }
}

TEST_CASE("instance names are safe file and unit names", "[cli][enroll]") {
  CHECK(valid_instance_name("farm"));
  CHECK(valid_instance_name("render-01.studio_a"));
  CHECK_FALSE(valid_instance_name(""));
  CHECK_FALSE(valid_instance_name(".hidden"));
  CHECK_FALSE(valid_instance_name("-flag"));
  CHECK_FALSE(valid_instance_name("a/b"));
  CHECK_FALSE(valid_instance_name("a b"));
  CHECK_FALSE(valid_instance_name(std::string(65, 'a')));
}
