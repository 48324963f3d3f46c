// Tests for dtraced::protocol's messages: every JSON codec round trips exactly, and malformed
// bodies are refused with the JSON path of the problem (embedded scenes included), in the words
// scene files and config files use for the same mistake. test_protocol_payload.cpp has the tile
// payload.
#include <algorithm>
#include <bit>
#include <cfloat>
#include <cstdint>
#include <functional>
#include <limits>
#include <string>
#include <string_view>
#include <variant>
#include <vector>

#include <catch2/catch.hpp>

#include "protocol/messages.h"
#include "scene/load.h"

namespace {

namespace protocol = dtraced::protocol;
using protocol::Decoded;
using DecodeError = dtraced::util::Error;

const std::string kDigest(64, 'a');

constexpr std::string_view kSceneJson = R"({
  "camera": {"position": [0.1, 0.2, 5.3], "look_at": [0, 0, 0], "fov": 37.5},
  "render": {"width": 64, "height": 48, "samples": 2, "background": [0.1, 0.2, 0.3], "seed": 7},
  "scene_objects": [
    {"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"color": [0.9, 0.1, 1e-7]}},
    {"type": "box", "loc": [2, 0, 0], "size": [1, 1, 1]},
    {"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0]},
    {"type": "sphere", "loc": [0.30000000000000004, 1, -2], "radius": 0.5}
  ],
  "scene_lights": [{"type": "point", "loc": [5, 5, 5], "intensity": 3.25}]
})";

// A submission body around a scene, with extra top-level members.
std::string submit_body(std::string_view scene, std::string_view extra = "") {
  std::string body = "{\"scene\": " + std::string(scene);
  if (!extra.empty()) body += ", " + std::string(extra);
  return body + "}";
}

// kSceneJson with its fourth object's radius replaced.
std::string scene_with_radius(std::string_view radius) {
  std::string scene(kSceneJson);
  const std::string from = "\"radius\": 0.5";
  scene.replace(scene.find(from), from.size(), "\"radius\": " + std::string(radius));
  return scene;
}

dtraced::scene::SceneDesc test_scene() {
  auto r = dtraced::scene::load_scene_string(kSceneJson, "test");
  INFO(dtraced::scene::format_errors(r.errors));
  REQUIRE(r.ok());
  return *r.scene;
}

protocol::JobStatus test_status() {
  protocol::JobStatus s;
  s.id = 42;
  s.state = protocol::JobState::kRendering;
  s.output = "frame-0001.png";
  s.priority = -7;
  s.width = 640;
  s.height = 480;
  s.samples = 16;
  s.tiles_done = 12;
  s.tiles_total = 300;
  s.elapsed_s = 12.345678901234567;
  s.eta_s = 0.1;
  s.digest = kDigest;
  return s;
}

template <typename T>
T round_trip(const T& m, Decoded<T> (*decode)(std::string_view)) {
  const std::string text = protocol::encode(m);
  Decoded<T> d = decode(text);
  INFO(text);
  if (!d.ok()) INFO(dtraced::util::to_string(d.error()));
  REQUIRE(d.ok());
  return std::move(d).value();
}

bool same_bits(double a, double b) { return std::bit_cast<std::uint64_t>(a) == std::bit_cast<std::uint64_t>(b); }

}  // namespace

// ---- round trips ---------------------------------------------------------------------------

TEST_CASE("a job submission round trips, scene and overrides included", "[protocol][json]") {
  protocol::JobSubmit m;
  m.scene = test_scene();
  m.output = "out.pfm";
  m.priority = -1000;
  m.overrides.tile_size = 16;
  m.overrides.width = 1;
  m.overrides.height = 16384;
  m.overrides.samples = 65536;
  m.overrides.max_depth = 0;
  m.overrides.seed = dtraced::scene::kMaxSeed;
  m.overrides.frame = std::numeric_limits<std::uint32_t>::max();
  m.overrides.background = dtraced::scene::Color{0.1, 0.30000000000000004, 3e38};
  m.overrides.png_bit_depth = 16;
  const protocol::JobSubmit back = round_trip(m, protocol::decode_job_submit);
  CHECK(back == m);
  CHECK(same_bits(back.scene.objects[3].sphere.center.x, 0.30000000000000004));
  CHECK(same_bits(back.overrides.background->y, 0.30000000000000004));

  const auto s = protocol::effective_settings(back);
  CHECK(s.width == 1);
  CHECK(s.height == 16384);
  CHECK(s.seed == dtraced::scene::kMaxSeed);
  CHECK(s.background == *m.overrides.background);
  CHECK(s.max_depth == 0);
}

TEST_CASE("every override of scene::Overrides has a key of its own in a submission", "[protocol][json]") {
  // One override at a time, so a key that another one's value happens to hide cannot pass.
  const std::vector<std::pair<std::string, std::function<void(dtraced::scene::Overrides&)>>> each = {
      {"width", [](auto& o) { o.width = 7; }},
      {"height", [](auto& o) { o.height = 9; }},
      {"samples", [](auto& o) { o.samples = 5; }},
      {"max_depth", [](auto& o) { o.max_depth = 3; }},
      {"seed", [](auto& o) { o.seed = 99; }},
      {"frame", [](auto& o) { o.frame = 12; }},
      {"background",
       [](auto& o) {
         o.background = dtraced::scene::Color{1, 2, 3};
       }},
      {"error_target", [](auto& o) { o.error_target = 0.5; }},
      {"min_samples", [](auto& o) { o.min_samples = 2; }},
      {"tile_size", [](auto& o) { o.tile_size = 1; }},
      {"png_bit_depth", [](auto& o) { o.png_bit_depth = 16; }},
  };
  for (const auto& [key, set] : each) {
    INFO(key);
    protocol::JobSubmit m;
    m.scene = test_scene();
    set(m.overrides);
    const std::string body = protocol::encode(m);
    CHECK(body.find("\"" + key + "\"") != std::string::npos);
    CHECK(round_trip(m, protocol::decode_job_submit) == m);
  }
  CHECK(protocol::decode_job_submit(submit_body(kSceneJson, R"("png_bit_depth": 12)")).error().front().path ==
        "/png_bit_depth");
  CHECK(protocol::decode_job_submit(submit_body(kSceneJson, R"("background": [1, -1, 0])")).error().front().path ==
        "/background/1");
}

TEST_CASE("a minimal submission takes the defaults", "[protocol][json]") {
  const auto d = protocol::decode_job_submit(submit_body(kSceneJson));
  REQUIRE(d.ok());
  CHECK(d.value().scene == test_scene());
  CHECK(d.value().output.empty());
  CHECK(d.value().priority == 0);
  CHECK(d.value().overrides == dtraced::scene::Overrides{});
  CHECK(dtraced::scene::tile_size_or_default(d.value().overrides) == dtraced::scene::kDefaultTileSize);
  CHECK(protocol::effective_settings(d.value()) == test_scene().render);
  // Written without the optional keys it did not have, and read back the same.
  CHECK(round_trip(d.value(), protocol::decode_job_submit) == d.value());
}

TEST_CASE("integral doubles are accepted where integers are expected", "[protocol][json]") {
  const auto d = protocol::decode_job_submit(submit_body(kSceneJson, R"("tile_size": 64.0, "width": 1e3)"));
  REQUIRE(d.ok());
  CHECK(d.value().overrides.tile_size == 64u);
  CHECK(d.value().overrides.width == 1000u);
}

TEST_CASE("job created, status and list round trip", "[protocol][json]") {
  CHECK(round_trip(protocol::JobCreated{protocol::kMaxId, kDigest}, protocol::decode_job_created) ==
        protocol::JobCreated{protocol::kMaxId, kDigest});

  protocol::JobStatus s = test_status();
  CHECK(round_trip(s, protocol::decode_job_status) == s);
  CHECK(same_bits(round_trip(s, protocol::decode_job_status).elapsed_s, s.elapsed_s));
  s.eta_s.reset();
  CHECK(protocol::encode(s).find("\"eta_s\":null") != std::string::npos);
  CHECK(round_trip(s, protocol::decode_job_status) == s);
  for (const auto state : {protocol::JobState::kQueued, protocol::JobState::kRendering, protocol::JobState::kDone,
                           protocol::JobState::kCancelled}) {
    s.state = state;
    CHECK(round_trip(s, protocol::decode_job_status) == s);
  }

  protocol::JobList list;
  CHECK(round_trip(list, protocol::decode_job_list) == list);
  list.jobs = {test_status(), s};
  CHECK(round_trip(list, protocol::decode_job_list) == list);
}

TEST_CASE("lease request and both lease replies round trip", "[protocol][json]") {
  const protocol::LeaseRequest req{"render-host-12 (rack 3)", 64};
  CHECK(round_trip(req, protocol::decode_lease_request) == req);

  protocol::Lease lease;
  lease.job = 7;
  lease.digest = kDigest;
  lease.tile = 12;
  lease.rect = {32, 16, 32, 16};
  lease.settings = test_scene().render;
  lease.settings.background = {0.1, 1e-30, 3.4028234663852886e38};
  lease.settings.seed = dtraced::scene::kMaxSeed;
  lease.settings.frame = 99;
  const protocol::LeaseReply reply = lease;
  const protocol::LeaseReply back = round_trip(reply, protocol::decode_lease_reply);
  REQUIRE(std::holds_alternative<protocol::Lease>(back));
  CHECK(std::get<protocol::Lease>(back) == lease);
  for (std::size_t i = 0; i < 3; ++i) {
    CHECK(same_bits(std::get<protocol::Lease>(back).settings.background[i], lease.settings.background[i]));
  }

  const protocol::LeaseReply retry = protocol::RetryAfter{500};
  CHECK(protocol::encode(retry) == R"({"retry_after_ms":500})");
  CHECK(round_trip(retry, protocol::decode_lease_reply) == retry);
}

TEST_CASE("submit results and error bodies round trip", "[protocol][json]") {
  for (const auto r :
       {protocol::SubmitResult::kStored, protocol::SubmitResult::kAlreadyDone, protocol::SubmitResult::kJobGone}) {
    CHECK(round_trip(r, protocol::decode_submit_result) == r);
  }
  CHECK(protocol::encode(protocol::SubmitResult::kAlreadyDone) == R"({"result":"already_done"})");

  const protocol::ErrorBody e{"must be > 0 (got -1) \xc3\xa9 \"quoted\"", "/scene/scene_objects/3/radius"};
  CHECK(round_trip(e, protocol::decode_error_body) == e);
  const auto no_field = protocol::decode_error_body(R"({"error": "unauthorized"})");
  REQUIRE(no_field.ok());
  CHECK(no_field.value() == protocol::ErrorBody{"unauthorized", ""});
}

TEST_CASE("settings round trip as the store keeps them", "[protocol][json]") {
  dtraced::scene::RenderSettings s;
  s.width = 16384;
  s.height = 1;
  s.samples = 3;
  s.max_depth = 64;
  s.background = {0.7, 0, 123.456e-20};
  s.seed = 123456789;
  s.frame = 4;
  const std::string text = protocol::encode_settings({s});
  const auto back = protocol::decode_settings(text);
  REQUIRE(back.ok());
  CHECK(back.value() == protocol::JobSettings{s});
  CHECK(same_bits(back.value().render.background.z, s.background.z));
  // Integral values are written as integers; an 8-bit job does not name its bit depth.
  CHECK(text.find("\"width\":16384") != std::string::npos);
  CHECK(text.find("[7E-1,0,") != std::string::npos);
  CHECK(text.find("png_bit_depth") == std::string::npos);

  const protocol::JobSettings deep{s, 16};
  CHECK(protocol::decode_settings(protocol::encode_settings(deep)).value() == deep);
  CHECK(protocol::decode_settings(R"({"width":1})").error().front().path == "/height");
}

// ---- malformed bodies ----------------------------------------------------------------------

namespace {

struct BadBody {
  const char* name;
  std::function<std::vector<DecodeError>(std::string_view)> decode;
  std::string body;
  std::string path;
  std::string fragment;
};

template <typename T>
std::function<std::vector<DecodeError>(std::string_view)> errors_of(Decoded<T> (*decode)(std::string_view)) {
  return [decode](std::string_view body) {
    Decoded<T> d = decode(body);
    return d.ok() ? std::vector<DecodeError>{} : d.error();
  };
}

const auto submit = errors_of(protocol::decode_job_submit);
const auto created = errors_of(protocol::decode_job_created);
const auto status = errors_of(protocol::decode_job_status);
const auto list = errors_of(protocol::decode_job_list);
const auto lease_request = errors_of(protocol::decode_lease_request);
const auto lease_reply = errors_of(protocol::decode_lease_reply);
const auto submit_result = errors_of(protocol::decode_submit_result);
const auto error_body = errors_of(protocol::decode_error_body);
const auto settings = errors_of(protocol::decode_settings);

std::string lease_body(std::string_view rect, std::string_view settings_json) {
  return R"({"lease": {"job": 7, "digest": ")" + kDigest + R"(", "tile": 3, )" + std::string(rect) +
         R"(, "settings": )" + std::string(settings_json) + "}}";
}
constexpr std::string_view kRect = R"("x": 0, "y": 0, "width": 32, "height": 32)";
constexpr std::string_view kSettings =
    R"({"width": 64, "height": 64, "samples": 1, "max_depth": 8, "background": [0, 0, 0], "seed": 0, "frame": 0})";

std::string status_body(std::string_view field, std::string_view value) {
  std::string body = protocol::encode(test_status());
  const std::string key = "\"" + std::string(field) + "\":";
  const std::size_t start = body.find(key) + key.size();
  const std::size_t end = body.find_first_of(",}", body[start] == '"' ? body.find('"', start + 1) : start);
  body.replace(start, end - start, value);
  return body;
}

std::string nested_arrays(int n) { return std::string(n, '[') + std::string(n, ']'); }

// Each body is refused, and among its errors is one at `path` whose message holds `fragment`.
void check_refused(const std::vector<BadBody>& cases) {
  for (const BadBody& c : cases) {
    INFO(c.name);
    const std::vector<DecodeError> errors = c.decode(c.body);
    REQUIRE_FALSE(errors.empty());
    std::string all;
    for (const DecodeError& e : errors) all += e.to_string() + "\n";
    INFO(all);
    const bool found = std::any_of(errors.begin(), errors.end(), [&](const DecodeError& e) {
      return e.path == c.path && e.message.find(c.fragment) != std::string::npos;
    });
    CHECK(found);
  }
}

}  // namespace

TEST_CASE("malformed submissions are refused with the JSON path of the problem", "[protocol][json][errors]") {
  // The body is level 1 and may nest 65 levels: 64 arrays fit under "x", the 65th is one too many
  // and sits at index 0 of the 64th.
  std::string deep_path = "/x";
  for (int i = 0; i < 64; ++i) deep_path += "/0";

  check_refused({
      // submissions
      // Unknown keys are worded as in scene and config files: a suggestion, or the known keys.
      {"unknown key", submit, submit_body(kSceneJson, R"("priorty": 1)"), "/priorty",
       "unknown key \"priorty\" (did you mean \"priority\"?)"},
      {"priority as a string", submit, submit_body(kSceneJson, R"("priority": "high")"), "/priority",
       "expected an integer, got a string"},
      {"priority out of range", submit, submit_body(kSceneJson, R"("priority": 1001)"), "/priority",
       "[-1000, 1000] (got 1001)"},
      {"priority beyond int64", submit, submit_body(kSceneJson, R"("priority": 18446744073709551615)"), "/priority",
       "[-1000, 1000]"},
      {"tile size too small", submit, submit_body(kSceneJson, R"("tile_size": 0)"), "/tile_size", "[1, 1024] (got 0)"},
      {"tile size fractional", submit, submit_body(kSceneJson, R"("tile_size": 32.5)"), "/tile_size",
       "must be an integer (got 32.5)"},
      {"width overflows a double", submit, submit_body(kSceneJson, R"("width": 1e999)"), "/width",
       "overflows a double"},
      {"width above the scene limit", submit, submit_body(kSceneJson, R"("width": 16385)"), "/width",
       "[1, 16384] (got 16385)"},
      {"samples 0", submit, submit_body(kSceneJson, R"("samples": 0)"), "/samples", "[1, 65536] (got 0)"},
      {"seed 2^53", submit, submit_body(kSceneJson, R"("seed": 9007199254740992)"), "/seed", "[0, 9007199254740991]"},
      {"too many tiles", submit, submit_body(kSceneJson, R"("width": 16384, "height": 16384, "tile_size": 8)"),
       "/tile_size", "more than the limit of 262144"},
      {"scene missing", submit, R"({"output": "a.png"})", "/scene", "required key is missing"},
      {"scene not an object", submit, submit_body("[1, 2]"), "/scene", "expected an object (a scene), got an array"},
      {"scene object with a negative radius", submit, submit_body(scene_with_radius("-1")),
       "/scene/scene_objects/3/radius", "must be > 0 (got -1)"},
      {"scene object with a radius as a string", submit, submit_body(scene_with_radius("\"big\"")),
       "/scene/scene_objects/3/radius", "expected a number"},
      {"scene with a misspelt camera key", submit,
       submit_body(R"({"camera": {"fvo": 40}, "scene_objects": [], "scene_lights": []})"), "/scene/camera/fvo",
       "unknown key \"fvo\""},
      {"scene missing its lights", submit, submit_body(R"({"camera": {}, "scene_objects": []})"), "/scene/scene_lights",
       "required key is missing"},
      {"duplicate key inside the scene", submit,
       submit_body(R"({"camera": {"fov": 40, "fov": 50}, "scene_objects": [], "scene_lights": []})"),
       "/scene/camera/fov", "duplicate key \"fov\""},
      {"output climbing out", submit, submit_body(kSceneJson, R"("output": "../x.png")"), "/output", "without '/'"},
      {"output with dot-dot", submit, submit_body(kSceneJson, R"("output": "x..png")"), "/output",
       "must not contain \"..\""},
      {"output in a directory", submit, submit_body(kSceneJson, R"("output": "a/b.png")"), "/output", "without '/'"},
      {"output with a backslash", submit, submit_body(kSceneJson, R"("output": "a\\b.png")"), "/output",
       "without '/' or '\\'"},
      {"output of the wrong type", submit, submit_body(kSceneJson, R"("output": "x.exe")"), "/output",
       "must end in .png, .ppm, .pfm, .exr or .gif"},
      {"output upper-case extension", submit, submit_body(kSceneJson, R"("output": "x.PNG")"), "/output",
       "must end in .png"},
      {"output only an extension", submit, submit_body(kSceneJson, R"("output": ".png")"), "/output",
       "must not start with '.'"},
      {"output empty", submit, submit_body(kSceneJson, R"("output": "")"), "/output", "must not be empty"},
      {"output too long", submit, submit_body(kSceneJson, "\"output\": \"" + std::string(252, 'x') + ".png\""),
       "/output", "256 bytes, longer than the limit of 255"},
      {"output with a newline", submit, submit_body(kSceneJson, R"("output": "a\nb.png")"), "/output",
       "control characters"},
      {"duplicate top-level key", submit, submit_body(kSceneJson, R"("priority": 1, "priority": 2)"), "/priority",
       "duplicate key \"priority\""},
      {"truncated body", submit, R"({"scene": {"camera": )", "/scene/camera", "unexpected end of input"},
      {"not an object", submit, "[]", "", "expected a JSON object at the top level, got an array"},
      {"empty body", submit, "", "", "unexpected end of input"},
      {"trailing garbage", submit, submit_body(kSceneJson) + "x", "", "invalid JSON"},
      {"too deep", submit, submit_body(kSceneJson, "\"x\": " + nested_arrays(65)), deep_path,
       "deeper than the limit of 65 levels"},
      {"body too large", submit, std::string(protocol::kMaxJobSubmitBytes + 1, ' '), "", "larger than the limit"},
  });
}

TEST_CASE("malformed answers and worker messages are refused with the JSON path of the problem",
          "[protocol][json][errors]") {
  check_refused({
      // job created
      {"id 0", created, R"({"id": 0, "digest": ")" + kDigest + "\"}", "/id", "[1, 9007199254740991] (got 0)"},
      {"short digest", created, R"({"id": 1, "digest": "abc"})", "/digest", "64 lower-case hex digits"},
      {"upper-case digest", created, R"({"id": 1, "digest": ")" + std::string(64, 'A') + "\"}", "/digest",
       "lower-case hex"},
      {"digest missing", created, R"({"id": 1})", "/digest", "required key is missing"},
      // status and list
      {"unknown state", status, status_body("state", "\"suspended\""), "/state", "unknown state \"suspended\""},
      {"eta as a string", status, status_body("eta_s", "\"soon\""), "/eta_s", "expected a number, got a string"},
      {"negative elapsed", status, status_body("elapsed_s", "-1"), "/elapsed_s", "(got -1)"},
      {"more tiles done than total", status, status_body("tiles_done", "301"), "/tiles_done",
       "must be <= tiles_total (got 301 > 300)"},
      {"status output with a slash", status, status_body("output", "\"/etc/passwd.png\""), "/output", "without '/'"},
      {"list element with a bad id", list,
       R"({"jobs": [)" + protocol::encode(test_status()) + "," + status_body("id", "-3") + "]}", "/jobs/1/id",
       "(got -3)"},
      {"jobs not an array", list, R"({"jobs": {}})", "/jobs", "expected an array, got an object"},
      // lease request
      {"worker name too long", lease_request, R"({"worker": ")" + std::string(129, 'w') + R"(", "threads": 1})",
       "/worker", "longer than the limit of 128"},
      {"worker name with a control character", lease_request, R"({"worker": "a\tb", "threads": 1})", "/worker",
       "printable ASCII"},
      {"worker name empty", lease_request, R"({"worker": "", "threads": 1})", "/worker", "printable ASCII"},
      {"threads 0", lease_request, R"({"worker": "w", "threads": 0})", "/threads", "[1, 4096] (got 0)"},
      {"threads missing", lease_request, R"({"worker": "w"})", "/threads", "required key is missing"},
      {"unknown key far from any", lease_request, R"({"worker": "w", "threads": 1, "zzz": 1})", "/zzz",
       "unknown key \"zzz\"; known keys: worker, threads"},
      // lease reply
      {"both lease and retry", lease_reply, R"({"lease": {}, "retry_after_ms": 5})", "", "exactly one of"},
      {"neither lease nor retry", lease_reply, "{}", "", "exactly one of"},
      {"retry too long", lease_reply, R"({"retry_after_ms": 1e9})", "/retry_after_ms", "[0, 60000]"},
      {"negative background in a lease", lease_reply,
       lease_body(kRect,
                  R"({"width": 64, "height": 64, "samples": 1, "max_depth": 8, "background": [0, -1, 0],
                      "seed": 0, "frame": 0})"),
       "/lease/settings/background/1", "must be >= 0 (got -1)"},
      {"tile wider than allowed", lease_reply, lease_body(R"("x": 0, "y": 0, "width": 2000, "height": 32)", kSettings),
       "/lease/width", "[1, 1024] (got 2000)"},
      {"tile past the image", lease_reply, lease_body(R"("x": 48, "y": 0, "width": 32, "height": 32)", kSettings),
       "/lease/width", "tile columns [48, 80) extend past the image width 64"},
      {"lease missing settings", lease_reply,
       R"({"lease": {"job": 7, "digest": ")" + kDigest + R"(", "tile": 3, )" + std::string(kRect) + "}}",
       "/lease/settings", "required key is missing"},
      // submit result, error body, settings
      {"unknown result", submit_result, R"({"result": "ok"})", "/result", "unknown result \"ok\""},
      {"error field not a pointer", error_body, R"({"error": "x", "field": "priority"})", "/field", "JSON Pointer"},
      {"settings missing the seed", settings,
       R"({"width": 1, "height": 1, "samples": 1, "max_depth": 0, "background": [0, 0, 0], "frame": 0})", "/seed",
       "required key is missing"},
      {"settings frame beyond u32", settings,
       R"({"width": 1, "height": 1, "samples": 1, "max_depth": 0, "background": [0, 0, 0], "seed": 0,
           "frame": 4294967296})",
       "/frame", "[0, 4294967295]"},
      {"settings background of 2 numbers", settings,
       R"({"width": 1, "height": 1, "samples": 1, "max_depth": 0, "background": [0, 0], "seed": 0, "frame": 0})",
       "/background", "expected an array of 3 numbers, got 2 elements"},
  });
}

TEST_CASE("every problem of a body is reported, and the error body summarises them", "[protocol][json][errors]") {
  const auto d = protocol::decode_job_submit(
      submit_body(scene_with_radius("-1"), R"("priority": 5000, "tile_size": "big", "output": "a/b.png")"));
  REQUIRE_FALSE(d.ok());
  CHECK(d.error().size() == 4);
  const protocol::ErrorBody body = protocol::error_body(d.error());
  CHECK(body.field == "/scene/scene_objects/3/radius");
  CHECK(body.error.starts_with("must be > 0 (got -1) (3 more: /output: output name"));
  CHECK(body.error.find("/tile_size: expected an integer, got a string") != std::string::npos);

  const protocol::ErrorBody one = protocol::error_body({{"bad", "/x"}});
  CHECK(one == protocol::ErrorBody{"bad", "/x"});
}

TEST_CASE("output names", "[protocol]") {
  for (const char* good : {"a.png", "frame-0001.ppm", "x y.pfm", "caf\xc3\xa9.png", "a.b.png"}) {
    INFO(good);
    CHECK(protocol::check_output_name(good).ok());
  }
  for (const char* bad : {"", "png", ".png", "a.png/", "/a.png", "..", "a..png", "a.jpg", "a.png.exe", "a\\b.png"}) {
    INFO(bad);
    CHECK_FALSE(protocol::check_output_name(bad).ok());
  }
  CHECK(protocol::check_output_name(std::string(251, 'x') + ".png").ok());
  CHECK_FALSE(protocol::check_output_name(std::string(252, 'x') + ".png").ok());
  CHECK(protocol::check_output_name("a.jpg").error().message ==
        "output name must end in .png, .ppm, .pfm, .exr or .gif (lower case)");
  CHECK(protocol::check_output_name("seed.pnm").ok());  // the seed's spelling of PPM
  CHECK_FALSE(protocol::check_output_name("seed.PNM").ok());
}

TEST_CASE("adaptive settings travel in submissions, leases and stored settings", "[protocol][json][adaptive]") {
  protocol::JobSubmit m;
  m.scene = test_scene();
  m.overrides.error_target = 0.025;
  m.overrides.min_samples = 4;
  const protocol::JobSubmit back = round_trip(m, protocol::decode_job_submit);
  CHECK(back == m);
  const auto s = protocol::effective_settings(back);
  CHECK(s.error_target == 0.025);
  CHECK(s.min_samples == 4u);

  // Stored settings: the adaptive keys appear only when they differ from the defaults, so a
  // uniform job's settings text is what it was before they existed, and old text still reads.
  dtraced::scene::RenderSettings uniform;
  const std::string text = protocol::encode_settings({uniform});
  CHECK(text.find("error_target") == std::string::npos);
  CHECK(text.find("min_samples") == std::string::npos);
  dtraced::scene::RenderSettings adaptive = uniform;
  adaptive.error_target = 0.1;
  adaptive.min_samples = 32;
  const auto decoded = protocol::decode_settings(protocol::encode_settings({adaptive}));
  REQUIRE(decoded.ok());
  CHECK(decoded.value().render == adaptive);
  const auto old = protocol::decode_settings(kSettings);
  REQUIRE(old.ok());
  CHECK(old.value().render.error_target == 0.0);
  CHECK(old.value().render.min_samples == dtraced::scene::RenderSettings{}.min_samples);
  CHECK(old.value().png_bit_depth == 8u);

  // A lease carries them to the worker.
  protocol::Lease lease;
  lease.job = 3;
  lease.digest = kDigest;
  lease.rect = {0, 0, 8, 8};
  lease.settings = adaptive;
  lease.settings.width = 8;
  lease.settings.height = 8;
  const protocol::LeaseReply reply = lease;
  const protocol::LeaseReply lease_back = round_trip(reply, protocol::decode_lease_reply);
  REQUIRE(std::holds_alternative<protocol::Lease>(lease_back));
  CHECK(std::get<protocol::Lease>(lease_back).settings == lease.settings);

  // The job status's mean spp: a number, null, or absent (an older collector).
  protocol::JobStatus st = test_status();
  st.mean_spp = 12.75;
  CHECK(round_trip(st, protocol::decode_job_status) == st);
  st.mean_spp.reset();
  CHECK(protocol::encode(st).find("\"mean_spp\":null") != std::string::npos);
  CHECK(round_trip(st, protocol::decode_job_status) == st);
  std::string without = protocol::encode(st);
  without.erase(without.find(",\"mean_spp\":null"), std::string(",\"mean_spp\":null").size());
  const auto old_status = protocol::decode_job_status(without);
  REQUIRE(old_status.ok());
  CHECK_FALSE(old_status.value().mean_spp.has_value());
}

TEST_CASE("adaptive settings out of range are refused by name", "[protocol][json][errors][adaptive]") {
  const std::vector<BadBody> cases = {
      {"negative error target", submit, submit_body(kSceneJson, R"("error_target": -0.5)"), "/error_target",
       "must be in [0, 1]"},
      {"error target above 1", submit, submit_body(kSceneJson, R"("error_target": 2)"), "/error_target",
       "must be in [0, 1]"},
      {"error target as a string", submit, submit_body(kSceneJson, R"("error_target": "0.1")"), "/error_target",
       "number"},
      {"min samples 0", submit, submit_body(kSceneJson, R"("min_samples": 0)"), "/min_samples", "[1, 65536] (got 0)"},
      {"min samples fractional", submit, submit_body(kSceneJson, R"("min_samples": 2.5)"), "/min_samples",
       "must be an integer"},
      {"lease error target out of range", lease_reply,
       lease_body(kRect, R"({"width": 64, "height": 64, "samples": 1, "max_depth": 8, "background": [0, 0, 0],
                             "seed": 0, "frame": 0, "error_target": 1.5})"),
       "/lease/settings/error_target", "must be in [0, 1]"},
      {"stored min samples too large", settings,
       R"({"width": 64, "height": 64, "samples": 1, "max_depth": 8, "background": [0, 0, 0], "seed": 0, "frame": 0,
           "min_samples": 65537})",
       "/min_samples", "[1, 65536]"},
      {"mean spp below 1", status, status_body("mean_spp", "0.5"), "/mean_spp", "must be in [1, 65536]"},
  };
  for (const BadBody& c : cases) {
    INFO(c.name << ": " << c.body);
    const std::vector<DecodeError> errors = c.decode(c.body);
    REQUIRE_FALSE(errors.empty());
    CHECK(errors.front().path == c.path);
    CHECK_THAT(errors.front().message, Catch::Matchers::Contains(c.fragment));
  }
}

TEST_CASE("a job status is encoded with plain decimals, not Boost's exponent form", "[protocol][json]") {
  protocol::JobStatus s = test_status();
  s.mean_spp = 21.5;
  s.no_worker_s = 1e-7;  // tiny: an exponent, but a valid JSON one
  const std::string text = protocol::encode(s);
  CHECK_THAT(text, Catch::Matchers::Contains(R"("elapsed_s":12.345678901234567,"eta_s":0.1,)"));
  CHECK_THAT(text, Catch::Matchers::Contains(R"("mean_spp":21.5,"no_worker_s":1e-07})"));
  CHECK(text.find('E') == std::string::npos);
  const auto back = protocol::decode_job_status(text);
  REQUIRE(back.ok());
  CHECK(back.value().elapsed_s == s.elapsed_s);
  CHECK(back.value().mean_spp == s.mean_spp);
  CHECK(back.value().no_worker_s == s.no_worker_s);
}
