// The command line's pure pieces, without running a verb or a daemon: did-you-mean for unknown
// verbs and flags, on the real command line main builds; --listen addresses and host names; the
// override flags that are parsed by hand (--frames, --crop).
#include <chrono>
#include <string>
#include <utility>
#include <vector>

#include <CLI/CLI.hpp>
#include <catch2/catch.hpp>

#include "cli/commands.h"
#include "cli/config_errors.h"
#include "cli/listen_address.h"
#include "cli/overrides_flags.h"
#include "cli/roles.h"
#include "cli/suggest.h"
#include "collector/config.h"
#include "worker/config.h"

namespace {

namespace cli = dtraced::cli;

// dtraced's own command line (as main builds it), parsed from `args`; returns the failure message
// CLI11 would print, with suggestions, or "" when the parse succeeded.
std::string parse_failure(std::vector<std::string> args) {
  CLI::App app{"test", "dtraced"};
  app.require_subcommand(0, 1);
  app.fallthrough(false);
  cli::RoleArgs role;
  cli::add_role_options(app, role);
  cli::LocalCommands local;
  cli::add_local_commands(app, local, role.isa);
  cli::ClientCommands client;
  cli::add_client_commands(app, client);
  std::vector<std::string> reversed(args.rbegin(), args.rend());  // CLI11 takes them last first
  try {
    app.parse(reversed);
  } catch (const CLI::ParseError& e) {
    return cli::failure_message_with_suggestions(&app, e);
  }
  return "";
}

}  // namespace

TEST_CASE("nearest_name picks the closest candidate within two edits") {
  const std::vector<std::string> verbs = {"render", "validate", "submit", "status"};
  CHECK(cli::nearest_name("rendr", verbs) == "render");
  CHECK(cli::nearest_name("stauts", verbs) == "status");
  CHECK(cli::nearest_name("valdiate", verbs) == "validate");
  CHECK(cli::nearest_name("frobnicate", verbs).empty());
  // Two letters are never "near" anything: "xy" is two edits from any two-letter name.
  CHECK(cli::nearest_name("xy", std::vector<std::string>{"ab"}).empty());
  CHECK(cli::nearest_name("render", std::vector<std::string>{}).empty());
}

TEST_CASE("An unknown verb is answered with the nearest verb") {
  const std::string text = parse_failure({"rendr", "scene.json"});
  CHECK_THAT(text, Catch::Contains("The following arguments were not expected: "));
  CHECK_THAT(text, Catch::Contains("rendr: did you mean render?"));
  // CLI11's own pointer to --help stays last.
  CHECK_THAT(text, Catch::EndsWith("Run with --help for more information.\n"));
}

TEST_CASE("An unknown flag of a verb is answered with the nearest flag of that verb") {
  const std::string text = parse_failure({"render", "scene.json", "-o", "x.png", "--sampels", "4"});
  CHECK_THAT(text, Catch::Contains("--sampels: did you mean --samples?"));
  CHECK_THAT(parse_failure({"status", "7", "--jsn"}), Catch::Contains("--jsn: did you mean --json?"));
  // "--flag=value" is judged by its name.
  CHECK_THAT(parse_failure({"list", "--colector=http://h:1"}),
             Catch::Contains("--colector: did you mean --collector?"));
}

TEST_CASE("An unknown role flag is answered with the nearest role flag") {
  const std::string text = parse_failure({"--role", "collector", "--stat-dir", "/tmp/s"});
  CHECK_THAT(text, Catch::Contains("--stat-dir: did you mean --state-dir?"));
}

TEST_CASE("The seed's render flags are mapped to dtraced's") {
  const std::string text = parse_failure({"render", "scene.json", "-o", "x.png", "-vpw", "64", "-vph", "48"});
  CHECK_THAT(text, Catch::Contains("-vpw: did you mean --width? (the seed's -vpw is dtraced's --width)"));
  CHECK_THAT(text, Catch::Contains("-vph: did you mean --height?"));
}

TEST_CASE("Nothing is suggested when nothing is near or the error is not an unknown argument") {
  const std::string text = parse_failure({"frobnicate"});
  CHECK_THAT(text, Catch::Contains("not expected: frobnicate"));
  CHECK_THAT(text, !Catch::Contains("did you mean"));
  CHECK_THAT(parse_failure({"render"}), !Catch::Contains("did you mean"));  // a missing argument
  CHECK(parse_failure({"validate", "scene.json"}).empty());
}

TEST_CASE("The listen address takes IPv4 and bracketed IPv6 addresses as they are") {
  const auto v4 = cli::parse_listen("127.0.0.1:7878");
  REQUIRE(v4.ok());
  CHECK(v4->host == "127.0.0.1");
  CHECK(v4->port == 7878);
  const auto v6 = cli::parse_listen("[::1]:0");
  REQUIRE(v6.ok());
  CHECK(v6->host == "::1");
  CHECK(v6->port == 0);
}

TEST_CASE("The listen address resolves a host name to an address") {
  const auto local = cli::parse_listen("localhost:0");
  REQUIRE(local.ok());
  // The first IPv4 address wins, so that localhost binds where IPv6 is off.
  CHECK(local->host == "127.0.0.1");
  CHECK(local->port == 0);
}

TEST_CASE("A bad listen address gets an error that says what is wrong with it") {
  const auto no_port = cli::parse_listen("localhost");
  REQUIRE_FALSE(no_port.ok());
  CHECK(no_port.error().to_string() == "--listen: expected HOST:PORT, got \"localhost\"");
  const auto bad_port = cli::parse_listen("127.0.0.1:70000");
  REQUIRE_FALSE(bad_port.ok());
  CHECK_THAT(bad_port.error().to_string(), Catch::StartsWith("--listen: bad port \"70000\""));
  const auto empty_port = cli::parse_listen("127.0.0.1:");
  REQUIRE_FALSE(empty_port.ok());
  CHECK_THAT(empty_port.error().message, Catch::Contains("bad port"));
  const auto unresolved = cli::parse_listen("nosuch.invalid:7878");
  REQUIRE_FALSE(unresolved.ok());
  CHECK_THAT(unresolved.error().to_string(),
             Catch::StartsWith("--listen: cannot resolve the host name \"nosuch.invalid\""));
  const auto bracketed_name = cli::parse_listen("[localhost]:1");
  REQUIRE_FALSE(bracketed_name.ok());
  CHECK_THAT(bracketed_name.error().message, Catch::Contains("is not an IP address"));
}

TEST_CASE("Configuration problems of either role are named by a flag dtraced has") {
  CLI::App app{"test", "dtraced"};
  cli::RoleArgs role;
  cli::add_role_options(app, role);
  dtraced::collector::CollectorConfig c;
  c.listen_address = "not an address";
  c.cpu_threads = 0;
  c.exit_when_done = true;
  dtraced::util::Errors errors = dtraced::collector::check_collector_config(c);
  dtraced::worker::WorkerConfig w;
  w.scene_cache = 0;
  w.timeouts.connect = std::chrono::milliseconds(0);
  for (dtraced::util::Error& e : dtraced::worker::validate(w)) errors.push_back(std::move(e));
  REQUIRE(errors.size() >= 8);
  for (const dtraced::util::Error& e : errors) {
    INFO(e.to_string());
    const std::string flag = cli::flag_of_field(e.path);
    REQUIRE_FALSE(flag.empty());
    CHECK(app.get_option_no_throw(flag) != nullptr);
    // Nothing came from a config file here: the problem is named by the flag.
    CHECK(cli::locate_role_error(app, e).path == flag);
  }
}

TEST_CASE("The --frames flag reads A-B, A-B:STEP and a single frame, and says what is wrong otherwise") {
  using dtraced::scene::FrameRange;
  CHECK(*cli::parse_frame_range("1-24") == FrameRange{1, 24, 1});
  CHECK(*cli::parse_frame_range("0-47:2") == FrameRange{0, 47, 2});
  CHECK(cli::parse_frame_range("0-47:2")->count() == 24);
  CHECK(*cli::parse_frame_range("7") == FrameRange{7, 7, 1});
  CHECK(*cli::parse_frame_range("0-4294967295:4294967295") == FrameRange{0, 4294967295u, 4294967295u});
  const auto why = [](std::string_view text) { return cli::parse_frame_range(text).error().message; };
  CHECK_THAT(why("5-3"), Catch::Contains("the last frame comes before the first"));
  CHECK_THAT(why("1-24:0"), Catch::Contains("the step must be an integer >= 1"));
  CHECK_THAT(why("a-b"), Catch::Contains("'a-b' is not a frame range"));
  CHECK_THAT(why("-3"), Catch::Contains("frame numbers are integers"));
  CHECK_THAT(why("1-"), Catch::Contains("frame numbers are integers"));
  CHECK_THAT(why(""), Catch::Contains("frame numbers are integers"));
  CHECK_THAT(why("0-4294967296"), Catch::Contains("frame numbers are integers"));
  CHECK_THAT(why("0-100000"), Catch::Contains("more than 100000 frames"));
}

TEST_CASE("The --crop flag reads X0,Y0,X1,Y1 as a half-open rectangle that must lie in the image") {
  using dtraced::scene::TileRect;
  CHECK(*cli::parse_crop("3,2,13,9") == TileRect{3, 2, 10, 7});
  CHECK_THAT(cli::parse_crop("3,2,3,9").error().message, Catch::Contains("empty crop"));
  CHECK_THAT(cli::parse_crop("3,2,13").error().message, Catch::Contains("four pixel coordinates"));
  CHECK_THAT(cli::parse_crop("3,2,13,9,1").error().message, Catch::Contains("four pixel coordinates"));
  CHECK_THAT(cli::parse_crop("-1,2,13,9").error().message, Catch::Contains("four pixel coordinates"));
  CHECK(cli::check_crop({3, 2, 10, 7}, 13, 9).ok());
  CHECK_THAT(cli::check_crop({3, 2, 10, 7}, 12, 9).error().message,
             Catch::Contains("--crop 3,2,13,9 reaches outside the 12x9 image"));
}

TEST_CASE("The render verb takes the sequence, display and crop flags") {
  CHECK(parse_failure({"render", "s.json", "-o", "o-%04d.png", "--frames", "1-24:2", "--fps", "12", "--exposure",
                       "-0.5", "--tone", "filmic", "--crop", "0,0,8,8", "--gif-dither"}) == "");
  CHECK_THAT(parse_failure({"render", "s.json", "-o", "o.png", "--tone", "aces"}), Catch::Contains("--tone"));
  CHECK_THAT(parse_failure({"render", "s.json", "-o", "o.png", "--frames", "9-1"}),
             Catch::Contains("the last frame comes before the first"));
  CHECK_THAT(parse_failure({"render", "s.json", "-o", "o.png", "--exposure", "40"}), Catch::Contains("--exposure"));
}
