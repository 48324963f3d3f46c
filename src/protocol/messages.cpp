#include "protocol/messages.h"

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <type_traits>

#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/string.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "image/image_io.h"
#include "scene/digest.h"
#include "scene/json_reader.h"

namespace dtraced::protocol {
namespace {

namespace json = boost::json;
using scene::json_finite_number;
using scene::json_kind_name;

// Every integer bound below fits an int64 and is at most 2^53, so a bound is exact as a double.
constexpr std::int64_t kMaxExactInteger = std::int64_t{1} << 53;
static_assert(kMaxId < kMaxExactInteger && scene::kMaxSeed < kMaxExactInteger);

// Longest string read where one of a few keywords is expected ("state", "result").
constexpr std::size_t kMaxKeywordBytes = 32;

// ---- paths ---------------------------------------------------------------------------------

std::string child(const std::string& at, std::string_view key) { return at + "/" + scene::json_pointer_escape(key); }
std::string child(const std::string& at, std::size_t index) { return at + "/" + std::to_string(index); }

// ---- reading -------------------------------------------------------------------------------

// Collects located errors while a body is read; every check reports and carries on, so one
// answer names every problem (up to kMaxDecodeErrors).
class Reader {
 public:
  void error(std::string path, std::string message) {
    if (errors_.size() < kMaxDecodeErrors) {
      errors_.push_back({std::move(message), std::move(path)});
    } else {
      ++dropped_;
    }
  }
  bool failed() const { return !errors_.empty(); }
  // Errors so far: a reader of one part compares counts to learn whether that part was clean.
  std::size_t error_count() const { return errors_.size() + dropped_; }

  util::Errors take_errors() {
    if (dropped_ > 0) error("", fmt::format("{} more problems not shown", dropped_));
    dropped_ = 0;
    return std::move(errors_);
  }

  // The body as a JSON value, or nullopt after reporting why not.
  std::optional<json::value> parse(std::string_view body, std::size_t max_bytes, std::size_t max_depth) {
    if (body.size() > max_bytes) {
      error("", fmt::format("body is {} bytes, larger than the limit of {} bytes", body.size(), max_bytes));
      return std::nullopt;
    }
    scene::JsonDocument doc = scene::read_json_strict(body, max_depth, kMaxDecodeErrors);
    // Duplicate keys are errors here too: which of two values a sender meant is anyone's guess.
    for (scene::JsonIssue& issue : doc.issues) error(std::move(issue.path), std::move(issue.message));
    if (!doc.parsed) return std::nullopt;
    return std::move(doc.value);
  }

  const json::object* object(const json::value& v, const std::string& at) {
    if (const json::object* o = v.if_object()) return o;
    error(at, fmt::format("expected an object, got {}", json_kind_name(v)));
    return nullptr;
  }

  void check_keys(const json::object& o, const std::string& at, std::initializer_list<std::string_view> known) {
    for (const auto& member : o) {
      const std::string_view key = member.key();
      if (std::find(known.begin(), known.end(), key) != known.end()) continue;
      std::string list;
      for (const std::string_view k : known) list += fmt::format("{}\"{}\"", list.empty() ? "" : ", ", k);
      error(child(at, key), fmt::format("unknown key \"{}\"; known keys: {}", key, list));
    }
  }

  // An integer in [lo, hi]. Integral doubles (640.0, 1e3) count, as they do in scene files.
  std::optional<std::int64_t> integer(const json::value& v, const std::string& at, std::int64_t lo, std::int64_t hi) {
    assert(lo <= hi && hi <= kMaxExactInteger && lo >= -kMaxExactInteger);
    const auto out_of_range = [&](auto got) {
      error(at, fmt::format("must be an integer in [{}, {}] (got {})", lo, hi, got));
      return std::nullopt;
    };
    switch (v.kind()) {
      case json::kind::int64: {
        const std::int64_t i = v.get_int64();
        if (i < lo || i > hi) return out_of_range(i);
        return i;
      }
      case json::kind::uint64:  // only values above INT64_MAX arrive as uint64: always too large
        return out_of_range(v.get_uint64());
      case json::kind::double_: {
        const double d = v.get_double();
        if (!std::isfinite(d)) {
          error(at, "number is out of range (overflows a double)");
          return std::nullopt;
        }
        if (d != std::floor(d)) {
          error(at, fmt::format("must be an integer (got {})", d));
          return std::nullopt;
        }
        // Compared as doubles first: converting a double beyond int64 is undefined behaviour.
        if (d < static_cast<double>(lo) || d > static_cast<double>(hi)) return out_of_range(d);
        return static_cast<std::int64_t>(d);
      }
      default:
        error(at, fmt::format("expected an integer, got {}", json_kind_name(v)));
        return std::nullopt;
    }
  }

  // A finite number in [lo, hi]; -0 becomes +0 (as in scene files).
  std::optional<double> number(const json::value& v, const std::string& at, double lo, double hi) {
    std::string problem;
    const std::optional<double> number = json_finite_number(v, problem);
    if (!number) {
      error(at, problem);
      return std::nullopt;
    }
    const double d = *number;
    if (!(d >= lo && d <= hi)) {
      error(at, fmt::format("must be in [{}, {}] (got {})", lo, hi, d));
      return std::nullopt;
    }
    return d == 0 ? 0.0 : d;
  }

  std::optional<std::string> string(const json::value& v, const std::string& at, std::size_t max_bytes) {
    const json::string* s = v.if_string();
    if (s == nullptr) {
      error(at, fmt::format("expected a string, got {}", json_kind_name(v)));
      return std::nullopt;
    }
    if (s->size() > max_bytes) {
      error(at, fmt::format("string is {} bytes, longer than the limit of {}", s->size(), max_bytes));
      return std::nullopt;
    }
    return std::string(s->data(), s->size());
  }

 private:
  util::Errors errors_;
  std::size_t dropped_ = 0;
};

enum class Need { kRequired, kOptional };

// The members of one JSON object, read field by field into a struct. Unknown keys are reported
// on construction; every accessor reports a missing required key.
class Fields {
 public:
  Fields(Reader& reader, const json::object& o, std::string at, std::initializer_list<std::string_view> known)
      : r_(reader), o_(o), at_(std::move(at)) {
    r_.check_keys(o_, at_, known);
  }

  std::string path(std::string_view key) const { return child(at_, key); }

  const json::value* get(std::string_view key, Need need) {
    if (const json::value* v = o_.if_contains(key)) return v;
    if (need == Need::kRequired) r_.error(path(key), "required key is missing");
    return nullptr;
  }

  template <typename T>
  void integer(std::string_view key, T& out, std::int64_t lo, std::int64_t hi, Need need = Need::kRequired) {
    static_assert(std::is_integral_v<T>);
    assert(lo >= static_cast<std::int64_t>(std::numeric_limits<T>::min()));
    assert(static_cast<std::uint64_t>(hi) <= static_cast<std::uint64_t>(std::numeric_limits<T>::max()));
    if (const json::value* v = get(key, need)) {
      if (auto i = r_.integer(*v, path(key), lo, hi)) out = static_cast<T>(*i);
    }
  }

  template <typename T>
  void optional_integer(std::string_view key, std::optional<T>& out, std::int64_t lo, std::int64_t hi) {
    if (o_.contains(key)) {
      T value{};
      const std::size_t before = r_.error_count();
      integer(key, value, lo, hi, Need::kOptional);
      if (r_.error_count() == before) out = value;
    }
  }

  void number(std::string_view key, double& out, double lo, double hi, Need need = Need::kRequired) {
    if (const json::value* v = get(key, need)) {
      if (auto d = r_.number(*v, path(key), lo, hi)) out = *d;
    }
  }

  void optional_number(std::string_view key, std::optional<double>& out, double lo, double hi) {
    if (const json::value* v = get(key, Need::kOptional)) {
      if (auto d = r_.number(*v, path(key), lo, hi)) out = *d;
    }
  }

  void string(std::string_view key, std::string& out, std::size_t max_bytes, Need need = Need::kRequired) {
    if (const json::value* v = get(key, need)) {
      if (auto s = r_.string(*v, path(key), max_bytes)) out = std::move(*s);
    }
  }

 private:
  Reader& r_;
  const json::object& o_;
  std::string at_;
};

// The object's required "digest".
void read_digest(Reader& r, Fields& f, std::string& out) {
  const std::size_t before = r.error_count();
  f.string("digest", out, kMaxMessageBytes);
  if (r.error_count() == before && f.get("digest", Need::kOptional) != nullptr && !is_digest(out)) {
    r.error(f.path("digest"), fmt::format("expected {} lower-case hex digits (a SHA-256)", kDigestHexChars));
  }
}

// The object's "output" (a file name, see check_output_name).
void read_output(Reader& r, Fields& f, std::string& out, Need need) {
  const json::value* v = f.get("output", need);
  if (v == nullptr) return;
  // One byte over the limit still reads, so that check_output_name can say what is wrong.
  if (auto name = r.string(*v, f.path("output"), kMaxOutputNameBytes + 1)) {
    if (auto why = check_output_name(*name)) {
      r.error(f.path("output"), "output name " + *why);
    } else {
      out = std::move(*name);
    }
  }
}

// The object's optional "png_bit_depth": 8 or 16.
void read_bit_depth(Reader& r, Fields& f, std::uint32_t& out) {
  std::uint32_t bits = out;
  const std::size_t before = r.error_count();
  f.integer("png_bit_depth", bits, 1, 64, Need::kOptional);
  if (r.error_count() != before) return;
  if (!scene::is_png_bit_depth(bits)) {
    r.error(f.path("png_bit_depth"), fmt::format("must be 8 or 16 (got {})", bits));
    return;
  }
  out = bits;
}

// A background colour, [r, g, b]: the scene loader's colour rule (non-negative, within the float
// range).
std::optional<scene::Color> read_background(Reader& r, const json::value& bg, const std::string& at) {
  const json::array* a = bg.if_array();
  if (a == nullptr || a->size() != 3) {
    r.error(at, a == nullptr ? fmt::format("expected an array of 3 numbers, got {}", json_kind_name(bg))
                             : fmt::format("expected an array of 3 numbers, got {} elements", a->size()));
    return std::nullopt;
  }
  scene::Color c;
  bool ok = true;
  for (std::size_t i = 0; i < 3; ++i) {
    if (auto channel = r.number((*a)[i], child(at, i), 0, FLT_MAX)) {
      c[i] = *channel;
    } else {
      ok = false;
    }
  }
  return ok ? std::optional<scene::Color>(c) : std::nullopt;
}

// The settings object of a Lease, or with `png_bit_depth` set, of a stored job (which may carry
// "png_bit_depth" too).
std::optional<scene::RenderSettings> read_settings(Reader& r, const json::value& v, const std::string& at,
                                                   std::uint32_t* png_bit_depth = nullptr) {
  const json::object* o = r.object(v, at);
  if (o == nullptr) return std::nullopt;
  const std::size_t before = r.error_count();
  std::initializer_list<std::string_view> lease_keys = {"width", "height", "samples",      "max_depth",  "background",
                                                        "seed",  "frame",  "error_target", "min_samples"};
  std::initializer_list<std::string_view> stored_keys = {"width",       "height",       "samples", "max_depth",
                                                         "background",  "seed",         "frame",   "error_target",
                                                         "min_samples", "png_bit_depth"};
  Fields f(r, *o, at, png_bit_depth != nullptr ? stored_keys : lease_keys);
  scene::RenderSettings s;
  f.integer("width", s.width, 1, scene::kMaxImageSide);
  f.integer("height", s.height, 1, scene::kMaxImageSide);
  f.integer("samples", s.samples, 1, scene::kMaxSamples);
  f.integer("max_depth", s.max_depth, 0, scene::kMaxDepth);
  if (const json::value* bg = f.get("background", Need::kRequired)) {
    if (auto c = read_background(r, *bg, f.path("background"))) s.background = *c;
  }
  f.integer("seed", s.seed, 0, scene::kMaxSeed);
  f.integer("frame", s.frame, 0, std::numeric_limits<std::uint32_t>::max());
  // Optional, so that settings stored before adaptive sampling existed still read (as uniform).
  f.number("error_target", s.error_target, 0, scene::kMaxErrorTarget, Need::kOptional);
  f.integer("min_samples", s.min_samples, 1, scene::kMaxSamples, Need::kOptional);
  if (png_bit_depth != nullptr) read_bit_depth(r, f, *png_bit_depth);
  if (r.error_count() != before) return std::nullopt;
  return s;
}

// The body's top-level object, or nullptr with the errors reported.
struct Body {
  std::optional<json::value> value;
  const json::object* object = nullptr;
};
Body parse_object(Reader& r, std::string_view text, std::size_t max_bytes, std::size_t max_depth) {
  Body body;
  body.value = r.parse(text, max_bytes, max_depth);
  if (body.value) body.object = r.object(*body.value, "");
  return body;
}

template <typename T>
Decoded<T> finish(Reader& r, T value) {
  if (r.failed()) return r.take_errors();
  return value;
}

std::optional<JobStatus> read_job_status(Reader& r, const json::value& v, const std::string& at) {
  const json::object* o = r.object(v, at);
  if (o == nullptr) return std::nullopt;
  const std::size_t before = r.error_count();
  Fields f(r, *o, at,
           {"id", "state", "output", "priority", "width", "height", "samples", "tiles_done", "tiles_total", "elapsed_s",
            "eta_s", "digest", "mean_spp"});
  JobStatus s;
  f.integer("id", s.id, 1, kMaxId);
  if (const json::value* state = f.get("state", Need::kRequired)) {
    if (auto text = r.string(*state, f.path("state"), kMaxKeywordBytes)) {
      if (auto parsed = job_state_from_string(*text)) {
        s.state = *parsed;
      } else {
        r.error(f.path("state"),
                fmt::format("unknown state \"{}\"; known states: queued, rendering, done, cancelled", *text));
      }
    }
  }
  read_output(r, f, s.output, Need::kRequired);
  f.integer("priority", s.priority, kMinPriority, kMaxPriority);
  f.integer("width", s.width, 1, scene::kMaxImageSide);
  f.integer("height", s.height, 1, scene::kMaxImageSide);
  f.integer("samples", s.samples, 1, scene::kMaxSamples);
  f.integer("tiles_done", s.tiles_done, 0, kMaxTilesPerJob);
  f.integer("tiles_total", s.tiles_total, 1, kMaxTilesPerJob);
  if (const json::value* e = f.get("elapsed_s", Need::kRequired)) {
    if (auto d = r.number(*e, f.path("elapsed_s"), 0, std::numeric_limits<double>::max())) s.elapsed_s = *d;
  }
  if (const json::value* e = f.get("eta_s", Need::kRequired); e != nullptr && !e->is_null()) {
    if (auto d = r.number(*e, f.path("eta_s"), 0, std::numeric_limits<double>::max())) s.eta_s = *d;
  }
  read_digest(r, f, s.digest);
  if (const json::value* m = f.get("mean_spp", Need::kOptional); m != nullptr && !m->is_null()) {
    if (auto d = r.number(*m, f.path("mean_spp"), 1, scene::kMaxSamples)) s.mean_spp = *d;
  }
  if (r.error_count() != before) return std::nullopt;
  if (s.tiles_done > s.tiles_total) {
    r.error(f.path("tiles_done"), fmt::format("must be <= tiles_total (got {} > {})", s.tiles_done, s.tiles_total));
    return std::nullopt;
  }
  return s;
}

// ---- writing -------------------------------------------------------------------------------

// Integral values as integers ("2", not Boost's "2E0"); others by Boost's Ryu, the shortest text
// that reads back (correctly rounded, as the reader reads it) to the same double.
json::value number(double d) {
  constexpr double kExact = 9007199254740992.0;  // 2^53
  if (d == std::floor(d) && std::abs(d) <= kExact) return json::value(static_cast<std::int64_t>(d));
  return json::value(d);
}

json::object settings_object(const scene::RenderSettings& s) {
  json::object o;
  o["width"] = s.width;
  o["height"] = s.height;
  o["samples"] = s.samples;
  o["max_depth"] = s.max_depth;
  json::array bg;
  for (std::size_t i = 0; i < 3; ++i) bg.push_back(number(s.background[i]));
  o["background"] = std::move(bg);
  o["seed"] = s.seed;
  o["frame"] = s.frame;
  // Written only when they differ from the defaults, as in the canonical scene form: the settings
  // of a uniform job keep the text (and the one-shot key) they had before adaptive sampling.
  if (s.error_target > 0 || s.min_samples != scene::RenderSettings{}.min_samples) {
    o["error_target"] = number(s.error_target);
    o["min_samples"] = s.min_samples;
  }
  return o;
}

json::object job_status_object(const JobStatus& s) {
  json::object o;
  o["id"] = s.id;
  o["state"] = to_string(s.state);
  o["output"] = s.output;
  o["priority"] = s.priority;
  o["width"] = s.width;
  o["height"] = s.height;
  o["samples"] = s.samples;
  o["tiles_done"] = s.tiles_done;
  o["tiles_total"] = s.tiles_total;
  o["elapsed_s"] = number(s.elapsed_s);
  o["eta_s"] = s.eta_s ? number(*s.eta_s) : json::value(nullptr);
  o["digest"] = s.digest;
  o["mean_spp"] = s.mean_spp ? number(*s.mean_spp) : json::value(nullptr);
  return o;
}

// Cuts `text` to at most `max_bytes` without splitting a UTF-8 sequence.
void truncate_utf8(std::string& text, std::size_t max_bytes) {
  if (text.size() <= max_bytes) return;
  std::size_t end = max_bytes;
  while (end > 0 && (static_cast<unsigned char>(text[end]) & 0xC0) == 0x80) --end;
  text.resize(end);
}

}  // namespace

// ---- shared validation ---------------------------------------------------------------------

std::optional<std::string> check_output_name(std::string_view name) {
  if (name.empty()) return "must not be empty";
  if (name.size() > kMaxOutputNameBytes) {
    return fmt::format("is {} bytes, longer than the limit of {}", name.size(), kMaxOutputNameBytes);
  }
  if (name.find('/') != std::string_view::npos || name.find('\\') != std::string_view::npos) {
    return "must be a plain file name, without '/' or '\\'";
  }
  if (name.find("..") != std::string_view::npos) return "must not contain \"..\"";
  if (name.front() == '.') return "must not start with '.'";
  for (const char c : name) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x20 || u == 0x7f) return "must not contain control characters";
  }
  for (const image::FormatInfo& f : image::image_formats()) {
    if (name.size() > f.extension.size() && name.ends_with(f.extension)) return std::nullopt;
  }
  return fmt::format("must end in {}", image::extension_list());
}

bool is_digest(std::string_view text) {
  if (text.size() != kDigestHexChars) return false;
  return std::all_of(text.begin(), text.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

// ---- JobSubmit -----------------------------------------------------------------------------

scene::RenderSettings effective_settings(const JobSubmit& submit) {
  return scene::apply(submit.overrides, submit.scene.render);
}

std::string encode(const JobSubmit& m) {
  json::object o;
  // The scene travels in its canonical form, which reloads to the identical SceneDesc.
  scene::JsonDocument doc = scene::read_json_strict(scene::canonical_json(m.scene), scene::kMaxJsonDepth, 1);
  assert(doc.parsed && doc.issues.empty());
  o["scene"] = std::move(doc.value);
  if (!m.output.empty()) o["output"] = m.output;
  o["priority"] = m.priority;
  const scene::Overrides& v = m.overrides;
  if (v.tile_size) o["tile_size"] = *v.tile_size;
  if (v.width) o["width"] = *v.width;
  if (v.height) o["height"] = *v.height;
  if (v.samples) o["samples"] = *v.samples;
  if (v.max_depth) o["max_depth"] = *v.max_depth;
  if (v.seed) o["seed"] = *v.seed;
  if (v.frame) o["frame"] = *v.frame;
  if (v.background) {
    json::array bg;
    for (std::size_t i = 0; i < 3; ++i) bg.push_back(number((*v.background)[i]));
    o["background"] = std::move(bg);
  }
  if (v.error_target) o["error_target"] = number(*v.error_target);
  if (v.min_samples) o["min_samples"] = *v.min_samples;
  if (v.png_bit_depth) o["png_bit_depth"] = *v.png_bit_depth;
  return json::serialize(o);
}

namespace {

// The scene of a submission: loaded from the embedded object, with paths under "/scene".
void read_submitted_scene(Reader& r, const json::value& s, scene::SceneDesc& out) {
  if (!s.is_object()) {
    r.error("/scene", fmt::format("expected an object (a scene), got {}", json_kind_name(s)));
    return;
  }
  // The loader reads text, so the embedded object goes back to text: exact, because the reader
  // converted its numbers with correct rounding and Boost writes the shortest digits that read
  // back to the same double. The body's size limit already bounds it.
  scene::LoadOptions options;
  options.max_bytes = std::numeric_limits<std::uint64_t>::max();
  options.max_errors = kMaxDecodeErrors;
  // A submission carries its meshes inline: a "file" would make the collector read a file of its
  // own host into the scene, and from there serve it to any worker.
  options.allow_mesh_files = false;
  scene::LoadResult loaded = scene::load_scene_string(json::serialize(s), "", options);
  for (util::Error& e : loaded.errors) r.error("/scene" + e.path, std::move(e.message));
  if (loaded.ok()) out = std::move(*loaded.scene);
}

// The submission's overrides: each an optional top-level key, with the limits of scene files.
void read_overrides(Reader& r, Fields& f, scene::Overrides& o) {
  f.optional_integer("tile_size", o.tile_size, scene::kMinTileSize, scene::kMaxTileSize);
  f.optional_integer("width", o.width, 1, scene::kMaxImageSide);
  f.optional_integer("height", o.height, 1, scene::kMaxImageSide);
  f.optional_integer("samples", o.samples, 1, scene::kMaxSamples);
  f.optional_integer("max_depth", o.max_depth, 0, scene::kMaxDepth);
  f.optional_integer("seed", o.seed, 0, scene::kMaxSeed);
  f.optional_integer("frame", o.frame, 0, std::numeric_limits<std::uint32_t>::max());
  if (const json::value* bg = f.get("background", Need::kOptional)) {
    o.background = read_background(r, *bg, f.path("background"));
  }
  f.optional_number("error_target", o.error_target, 0, scene::kMaxErrorTarget);
  f.optional_integer("min_samples", o.min_samples, 1, scene::kMaxSamples);
  if (f.get("png_bit_depth", Need::kOptional) != nullptr) {
    std::uint32_t bits = scene::kDefaultPngBitDepth;
    const std::size_t before = r.error_count();
    read_bit_depth(r, f, bits);
    if (r.error_count() == before) o.png_bit_depth = bits;
  }
}

}  // namespace

Decoded<JobSubmit> decode_job_submit(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxJobSubmitBytes, kMaxJobSubmitDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "",
           {"scene", "output", "priority", "tile_size", "width", "height", "samples", "max_depth", "seed", "frame",
            "background", "error_target", "min_samples", "png_bit_depth"});
  JobSubmit m;
  if (const json::value* s = f.get("scene", Need::kRequired)) read_submitted_scene(r, *s, m.scene);
  read_output(r, f, m.output, Need::kOptional);
  f.integer("priority", m.priority, kMinPriority, kMaxPriority, Need::kOptional);
  read_overrides(r, f, m.overrides);
  if (r.failed()) return r.take_errors();

  const scene::RenderSettings s = effective_settings(m);
  const std::uint32_t tile_size = scene::tile_size_or_default(m.overrides);
  const std::uint64_t tiles = scene::TileGrid(s, tile_size).count();
  if (tiles > kMaxTilesPerJob) {
    r.error("/tile_size", fmt::format("a {}x{} image in tiles of {} is {} tiles, more than the limit of {}", s.width,
                                      s.height, tile_size, tiles, kMaxTilesPerJob));
  }
  return finish(r, std::move(m));
}

// ---- JobCreated ----------------------------------------------------------------------------

std::string encode(const JobCreated& m) {
  json::object o;
  o["id"] = m.id;
  o["digest"] = m.digest;
  return json::serialize(o);
}

Decoded<JobCreated> decode_job_created(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxMessageBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"id", "digest"});
  JobCreated m;
  f.integer("id", m.id, 1, kMaxId);
  read_digest(r, f, m.digest);
  return finish(r, std::move(m));
}

// ---- JobStatus, JobList --------------------------------------------------------------------

std::string_view to_string(JobState state) {
  switch (state) {
    case JobState::kQueued:
      return "queued";
    case JobState::kRendering:
      return "rendering";
    case JobState::kDone:
      return "done";
    case JobState::kCancelled:
      return "cancelled";
  }
  return "?";
}

std::optional<JobState> job_state_from_string(std::string_view text) {
  for (const JobState s : {JobState::kQueued, JobState::kRendering, JobState::kDone, JobState::kCancelled}) {
    if (text == to_string(s)) return s;
  }
  return std::nullopt;
}

std::string encode(const JobStatus& m) { return json::serialize(job_status_object(m)); }

Decoded<JobStatus> decode_job_status(std::string_view text) {
  Reader r;
  std::optional<json::value> v = r.parse(text, kMaxMessageBytes, kMaxMessageDepth);
  if (!v) return r.take_errors();
  std::optional<JobStatus> s = read_job_status(r, *v, "");
  if (!s) return r.take_errors();
  return finish(r, std::move(*s));
}

std::string encode(const JobList& m) {
  json::array jobs;
  jobs.reserve(m.jobs.size());
  for (const JobStatus& s : m.jobs) jobs.push_back(job_status_object(s));
  json::object o;
  o["jobs"] = std::move(jobs);
  return json::serialize(o);
}

Decoded<JobList> decode_job_list(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxJobListBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"jobs"});
  JobList m;
  if (const json::value* v = f.get("jobs", Need::kRequired)) {
    const json::array* a = v->if_array();
    if (a == nullptr) {
      r.error("/jobs", fmt::format("expected an array, got {}", json_kind_name(*v)));
    } else if (a->size() > kMaxListedJobs) {
      r.error("/jobs", fmt::format("too many jobs: {} (limit {})", a->size(), kMaxListedJobs));
    } else {
      m.jobs.reserve(a->size());
      for (std::size_t i = 0; i < a->size(); ++i) {
        if (auto s = read_job_status(r, (*a)[i], child("/jobs", i))) m.jobs.push_back(std::move(*s));
      }
    }
  }
  return finish(r, std::move(m));
}

// ---- LeaseRequest --------------------------------------------------------------------------

std::string encode(const LeaseRequest& m) {
  json::object o;
  o["worker"] = m.worker;
  o["threads"] = m.threads;
  return json::serialize(o);
}

Decoded<LeaseRequest> decode_lease_request(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxMessageBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"worker", "threads"});
  LeaseRequest m;
  if (const json::value* v = f.get("worker", Need::kRequired)) {
    // The name ends up in logs and metrics labels: printable ASCII only.
    const std::string why =
        fmt::format("must be 1 to {} printable ASCII characters (0x20 to 0x7e)", kMaxWorkerNameBytes);
    if (auto name = r.string(*v, "/worker", kMaxWorkerNameBytes)) {
      const bool printable = std::all_of(name->begin(), name->end(), [](char c) { return c >= 0x20 && c < 0x7f; });
      if (name->empty() || !printable) {
        r.error("/worker", why);
      } else {
        m.worker = std::move(*name);
      }
    }
  }
  f.integer("threads", m.threads, 1, kMaxWorkerThreads);
  return finish(r, std::move(m));
}

// ---- LeaseReply ----------------------------------------------------------------------------

std::string encode(const LeaseReply& m) {
  json::object o;
  if (const Lease* lease = std::get_if<Lease>(&m)) {
    json::object l;
    l["job"] = lease->job;
    l["digest"] = lease->digest;
    l["tile"] = lease->tile;
    l["x"] = lease->rect.x0;
    l["y"] = lease->rect.y0;
    l["width"] = lease->rect.width;
    l["height"] = lease->rect.height;
    l["settings"] = settings_object(lease->settings);
    o["lease"] = std::move(l);
  } else {
    o["retry_after_ms"] = std::get<RetryAfter>(m).ms;
  }
  return json::serialize(o);
}

Decoded<LeaseReply> decode_lease_reply(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxMessageBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"lease", "retry_after_ms"});
  const json::value* lease_v = f.get("lease", Need::kOptional);
  const json::value* retry_v = f.get("retry_after_ms", Need::kOptional);
  if ((lease_v == nullptr) == (retry_v == nullptr)) {
    r.error("", "expected exactly one of \"lease\" and \"retry_after_ms\"");
    return r.take_errors();
  }
  if (retry_v != nullptr) {
    RetryAfter retry;
    f.integer("retry_after_ms", retry.ms, 0, kMaxRetryAfterMs);
    return finish(r, LeaseReply(retry));
  }

  const json::object* o = r.object(*lease_v, "/lease");
  if (o == nullptr) return r.take_errors();
  Fields l(r, *o, "/lease", {"job", "digest", "tile", "x", "y", "width", "height", "settings"});
  Lease lease;
  l.integer("job", lease.job, 1, kMaxId);
  read_digest(r, l, lease.digest);
  l.integer("tile", lease.tile, 0, kMaxTilesPerJob - 1);
  l.integer("x", lease.rect.x0, 0, scene::kMaxImageSide - 1);
  l.integer("y", lease.rect.y0, 0, scene::kMaxImageSide - 1);
  l.integer("width", lease.rect.width, 1, scene::kMaxTileSize);
  l.integer("height", lease.rect.height, 1, scene::kMaxTileSize);
  if (const json::value* s = l.get("settings", Need::kRequired)) {
    if (auto settings = read_settings(r, *s, "/lease/settings")) lease.settings = *settings;
  }
  if (r.failed()) return r.take_errors();
  if (lease.rect.x0 + lease.rect.width > lease.settings.width) {
    r.error("/lease/width", fmt::format("tile columns [{}, {}) extend past the image width {}", lease.rect.x0,
                                        lease.rect.x0 + lease.rect.width, lease.settings.width));
  }
  if (lease.rect.y0 + lease.rect.height > lease.settings.height) {
    r.error("/lease/height", fmt::format("tile rows [{}, {}) extend past the image height {}", lease.rect.y0,
                                         lease.rect.y0 + lease.rect.height, lease.settings.height));
  }
  return finish(r, LeaseReply(std::move(lease)));
}

// ---- SubmitResult --------------------------------------------------------------------------

std::string_view to_string(SubmitResult result) {
  switch (result) {
    case SubmitResult::kStored:
      return "stored";
    case SubmitResult::kAlreadyDone:
      return "already_done";
    case SubmitResult::kJobGone:
      return "job_gone";
  }
  return "?";
}

std::string encode(SubmitResult m) {
  json::object o;
  o["result"] = to_string(m);
  return json::serialize(o);
}

Decoded<SubmitResult> decode_submit_result(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxMessageBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"result"});
  std::string result;
  f.string("result", result, kMaxKeywordBytes);
  if (r.failed()) return r.take_errors();
  for (const SubmitResult s : {SubmitResult::kStored, SubmitResult::kAlreadyDone, SubmitResult::kJobGone}) {
    if (result == to_string(s)) return s;
  }
  r.error("/result", fmt::format("unknown result \"{}\"; known results: stored, already_done, job_gone", result));
  return r.take_errors();
}

// ---- ErrorBody -----------------------------------------------------------------------------

ErrorBody error_body(const util::Errors& errors) {
  assert(!errors.empty());
  ErrorBody body{errors.front().message, errors.front().path};
  if (errors.size() > 1) {
    body.error += fmt::format(" ({} more: ", errors.size() - 1);
    for (std::size_t i = 1; i < errors.size(); ++i) {
      if (i > 1) body.error += "; ";
      body.error += errors[i].to_string();
      if (body.error.size() > kMaxErrorMessageBytes) break;
    }
    body.error += ")";
  }
  truncate_utf8(body.error, kMaxErrorMessageBytes);
  return body;
}

std::string encode(const ErrorBody& m) {
  json::object o;
  o["error"] = m.error;
  o["field"] = m.field;
  return json::serialize(o);
}

Decoded<ErrorBody> decode_error_body(std::string_view text) {
  Reader r;
  const Body body = parse_object(r, text, kMaxMessageBytes, kMaxMessageDepth);
  if (body.object == nullptr) return r.take_errors();
  Fields f(r, *body.object, "", {"error", "field"});
  ErrorBody m;
  f.string("error", m.error, kMaxErrorMessageBytes);
  f.string("field", m.field, kMaxErrorMessageBytes, Need::kOptional);
  if (!r.failed() && !m.field.empty() && m.field.front() != '/') {
    r.error("/field", "expected a JSON Pointer (\"\" or starting with '/')");
  }
  return finish(r, std::move(m));
}

// ---- settings ------------------------------------------------------------------------------

std::string encode_settings(const JobSettings& settings) {
  json::object o = settings_object(settings.render);
  if (settings.png_bit_depth != scene::kDefaultPngBitDepth) o["png_bit_depth"] = settings.png_bit_depth;
  return json::serialize(o);
}

Decoded<JobSettings> decode_settings(std::string_view text) {
  Reader r;
  std::optional<json::value> v = r.parse(text, kMaxMessageBytes, kMaxMessageDepth);
  if (!v) return r.take_errors();
  JobSettings settings;
  std::optional<scene::RenderSettings> s = read_settings(r, *v, "", &settings.png_bit_depth);
  if (!s) return r.take_errors();
  settings.render = *s;
  return finish(r, settings);
}

}  // namespace dtraced::protocol
