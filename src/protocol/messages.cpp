// The shared validation and readers (codec.h), the worker's messages (lease, tile answers),
// error bodies and stored settings; job_messages.cpp has the job messages.
#include "protocol/messages.h"

#include <algorithm>
#include <array>
#include <cassert>
#include <limits>

#include <boost/json/object.hpp>
#include <boost/json/serialize.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "image/image_io.h"
#include "protocol/codec.h"
#include "scene/scene_json.h"

namespace dtraced::protocol {
namespace {

namespace json = boost::json;
using namespace detail;

// Indexed by SubmitResult.
constexpr std::array<std::string_view, 3> kSubmitResultNames = {"stored", "already_done", "job_gone"};

constexpr std::array<std::string_view, 2> kLeaseRequestKeys = {"worker", "threads"};
constexpr std::array<std::string_view, 8> kLeaseKeys = {"job", "digest", "tile",   "x",
                                                        "y",   "width",  "height", "settings"};
constexpr std::array<std::string_view, 1> kSubmitResultKeys = {"result"};
constexpr std::array<std::string_view, 2> kErrorBodyKeys = {"error", "field"};
constexpr auto kStoredSettingsKeys =
    jsonio::join_keys(scene::kRenderKeys, std::array<std::string_view, 2>{"png_bit_depth", "crop"});
constexpr std::array<std::string_view, 4> kCropKeys = {"x", "y", "width", "height"};
constexpr auto& kLeaseSettingsKeys = scene::kRenderKeys;

// Cuts `text` to at most `max_bytes` without splitting a UTF-8 sequence.
void truncate_utf8(std::string& text, std::size_t max_bytes) {
  if (text.size() <= max_bytes) return;
  std::size_t end = max_bytes;
  while (end > 0 && (static_cast<unsigned char>(text[end]) & 0xC0) == 0x80) --end;
  text.resize(end);
}

// The "lease" object of a LeaseReply: a tile inside its settings' image.
void read_lease(Reader& r, const json::value& v, const Path& at, Lease& lease) {
  const json::object* o = r.object(v, at);
  if (o == nullptr) return;
  Fields f(r, *o, at, kLeaseKeys);
  f.integer("job", lease.job, 1, kMaxId);
  read_digest(f, lease.digest);
  f.integer("tile", lease.tile, 0, kMaxTilesPerJob - 1);
  f.integer("x", lease.rect.x0, 0, scene::kMaxImageSide - 1);
  f.integer("y", lease.rect.y0, 0, scene::kMaxImageSide - 1);
  f.integer("width", lease.rect.width, 1, scene::kMaxTileSize);
  f.integer("height", lease.rect.height, 1, scene::kMaxTileSize);
  if (const json::value* s = f.get("settings", Need::kRequired)) {
    const Path settings_at = f.path("settings");
    if (const json::object* so = r.object(*s, settings_at)) {
      Fields sf(r, *so, settings_at, kLeaseSettingsKeys);
      scene::read_render_settings(sf, lease.settings, Need::kRequired);
    }
  }
  if (r.failed()) return;
  if (lease.rect.x0 + lease.rect.width > lease.settings.width) {
    r.error(f.path("width"), fmt::format("tile columns [{}, {}) extend past the image width {}", lease.rect.x0,
                                         lease.rect.x0 + lease.rect.width, lease.settings.width));
  }
  if (lease.rect.y0 + lease.rect.height > lease.settings.height) {
    r.error(f.path("height"), fmt::format("tile rows [{}, {}) extend past the image height {}", lease.rect.y0,
                                          lease.rect.y0 + lease.rect.height, lease.settings.height));
  }
}

}  // namespace

// ---- codec.h -------------------------------------------------------------------------------

void detail::read_digest(Fields& f, std::string& out) {
  if (f.string("digest", out, kMaxMessageBytes) && f.has("digest") && !is_digest(out)) {
    f.reader().error(f.path("digest"), fmt::format("expected {} lower-case hex digits (a SHA-256)", kDigestHexChars));
  }
}

void detail::read_output(Fields& f, std::string& out, Need need) {
  std::string name;
  // One byte over the limit still reads, so that check_output_name can say what is wrong.
  if (!f.string("output", name, kMaxOutputNameBytes + 1, need) || !f.has("output")) return;
  if (util::Status ok = check_output_name(name); !ok) {
    f.reader().error(f.path("output"), ok.error().message);
  } else {
    out = std::move(name);
  }
}

bool detail::read_bit_depth(Fields& f, std::uint32_t& out) {
  std::uint32_t bits = out;
  if (!f.integer("png_bit_depth", bits, 1, 64, Need::kOptional)) return false;
  if (!scene::is_png_bit_depth(bits)) {
    f.reader().error(f.path("png_bit_depth"), fmt::format("must be 8 or 16 (got {})", bits));
    return false;
  }
  out = bits;
  return true;
}

bool detail::read_crop(Fields& f, std::optional<scene::TileRect>& out) {
  const json::value* v = f.get("crop", Need::kOptional);
  if (v == nullptr) return true;
  Reader& r = f.reader();
  const Path at = f.path("crop");
  const json::object* o = r.object(*v, at);
  if (o == nullptr) return false;
  const std::size_t before = r.error_count();
  Fields cf(r, *o, at, kCropKeys);
  scene::TileRect crop;
  cf.integer("x", crop.x0, 0, scene::kMaxImageSide - 1);
  cf.integer("y", crop.y0, 0, scene::kMaxImageSide - 1);
  cf.integer("width", crop.width, 1, scene::kMaxImageSide);
  cf.integer("height", crop.height, 1, scene::kMaxImageSide);
  if (r.error_count() != before) return false;
  out = crop;
  return true;
}

void detail::check_crop_inside(Fields& f, const scene::TileRect& crop, std::uint32_t width, std::uint32_t height) {
  const Path at = f.path("crop");
  // 64 bits: x + width of two u32 near their limits must not wrap.
  if (std::uint64_t{crop.x0} + crop.width > width) {
    f.reader().error(at.key("width"), fmt::format("crop columns [{}, {}) extend past the image width {}", crop.x0,
                                                  std::uint64_t{crop.x0} + crop.width, width));
  }
  if (std::uint64_t{crop.y0} + crop.height > height) {
    f.reader().error(at.key("height"), fmt::format("crop rows [{}, {}) extend past the image height {}", crop.y0,
                                                   std::uint64_t{crop.y0} + crop.height, height));
  }
}

json::object detail::crop_object(const scene::TileRect& crop) {
  return json::object{{"x", crop.x0}, {"y", crop.y0}, {"width", crop.width}, {"height", crop.height}};
}

// ---- shared validation ---------------------------------------------------------------------

namespace {

// Why `name` is no output name, phrased to follow "output name "; nullopt when it is one.
std::optional<std::string> output_name_problem(std::string_view name) {
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
  // Any extension image::format_from_path knows (".pnm" too, the seed's spelling of PPM), in lower
  // case, after a non-empty stem.
  const std::size_t dot = name.rfind('.');
  const bool lower = dot != std::string_view::npos &&
                     std::none_of(name.begin() + dot, name.end(), [](char c) { return c >= 'A' && c <= 'Z'; });
  if (dot != std::string_view::npos && dot > 0 && lower && image::format_from_path(std::string(name))) {
    return std::nullopt;
  }
  return fmt::format("must end in {} (lower case)", image::extension_list());
}

}  // namespace

util::Status check_output_name(std::string_view name) {
  if (std::optional<std::string> why = output_name_problem(name)) return util::Error("output name " + *why);
  return {};
}

bool is_digest(std::string_view text) {
  if (text.size() != kDigestHexChars) return false;
  return std::all_of(text.begin(), text.end(), [](char c) { return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'); });
}

// ---- LeaseRequest --------------------------------------------------------------------------

std::string encode(const LeaseRequest& m) {
  return jsonio::to_text(json::object{{"worker", m.worker}, {"threads", m.threads}});
}

Decoded<LeaseRequest> decode_lease_request(std::string_view text) {
  return decode_object<LeaseRequest>(
      text, kMaxMessageBytes, kMaxMessageDepth, kLeaseRequestKeys, [](Fields& f, LeaseRequest& m) {
        std::string name;
        if (f.string("worker", name, kMaxWorkerNameBytes)) {
          // The name ends up in logs and metrics labels: printable ASCII only.
          const bool printable = std::all_of(name.begin(), name.end(), [](char c) { return c >= 0x20 && c < 0x7f; });
          if (name.empty() || !printable) {
            f.reader().error(f.path("worker"), fmt::format("must be 1 to {} printable ASCII characters (0x20 to 0x7e)",
                                                           kMaxWorkerNameBytes));
          }
          m.worker = std::move(name);
        }
        f.integer("threads", m.threads, 1, kMaxWorkerThreads);
      });
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
    l["settings"] = scene::render_settings_object(lease->settings);
    o["lease"] = std::move(l);
  } else {
    o["retry_after_ms"] = std::get<RetryAfter>(m).ms;
  }
  return jsonio::to_text(o);
}

void detail::read_lease_reply(Fields& f, LeaseReply& m) {
  const json::value* lease = f.get("lease", Need::kOptional);
  if ((lease == nullptr) == !f.has("retry_after_ms")) {
    f.reader().error(f.at(), "expected exactly one of \"lease\" and \"retry_after_ms\"");
  } else if (lease == nullptr) {
    RetryAfter retry;
    f.integer("retry_after_ms", retry.ms, 0, kMaxRetryAfterMs);
    m = retry;
  } else {
    Lease l;
    read_lease(f.reader(), *lease, f.path("lease"), l);
    m = std::move(l);
  }
}

Decoded<LeaseReply> decode_lease_reply(std::string_view text) {
  return decode_object<LeaseReply>(text, kMaxMessageBytes, kMaxMessageDepth, kLeaseReplyKeys, read_lease_reply);
}

// ---- SubmitResult --------------------------------------------------------------------------

std::string_view to_string(SubmitResult result) { return kSubmitResultNames[static_cast<std::size_t>(result)]; }

std::string encode(SubmitResult m) { return jsonio::to_text(json::object{{"result", to_string(m)}}); }

Decoded<SubmitResult> decode_submit_result(std::string_view text) {
  return decode_object<SubmitResult>(
      text, kMaxMessageBytes, kMaxMessageDepth, kSubmitResultKeys, [](Fields& f, SubmitResult& m) {
        f.read("result", m, Need::kRequired, [&f](const json::value& v, const Path& at) {
          const auto i = f.reader().choice(v, at, kSubmitResultNames, "result", "results");
          return i ? std::optional<SubmitResult>(static_cast<SubmitResult>(*i)) : std::nullopt;
        });
      });
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

std::string encode(const ErrorBody& m) { return jsonio::to_text(json::object{{"error", m.error}, {"field", m.field}}); }

Decoded<ErrorBody> decode_error_body(std::string_view text) {
  return decode_object<ErrorBody>(
      text, kMaxMessageBytes, kMaxMessageDepth, kErrorBodyKeys, [](Fields& f, ErrorBody& m) {
        f.string("error", m.error, kMaxErrorMessageBytes);
        f.string("field", m.field, kMaxErrorMessageBytes, Need::kOptional);
        if (!f.reader().failed() && !m.field.empty() && m.field.front() != '/') {
          f.reader().error(f.path("field"), "expected a JSON Pointer (\"\" or starting with '/')");
        }
      });
}

// ---- settings ------------------------------------------------------------------------------

std::string encode_settings(const JobSettings& settings) {
  json::object o = scene::render_settings_object(settings.render);
  if (settings.png_bit_depth != scene::kDefaultPngBitDepth) o["png_bit_depth"] = settings.png_bit_depth;
  if (settings.crop) o["crop"] = crop_object(*settings.crop);
  // Boost's own form, not jsonio::to_text: this text is hashed into the client key that a one-shot
  // collector stores with its job (collector/jobs.h), so new bytes would lose stored jobs.
  return json::serialize(o);
}

Decoded<JobSettings> decode_settings(std::string_view text) {
  return decode_object<JobSettings>(text, kMaxMessageBytes, kMaxMessageDepth, kStoredSettingsKeys,
                                    [](Fields& f, JobSettings& m) {
                                      scene::read_render_settings(f, m.render, Need::kRequired);
                                      read_bit_depth(f, m.png_bit_depth);
                                      if (read_crop(f, m.crop) && m.crop && !f.reader().failed()) {
                                        check_crop_inside(f, *m.crop, m.render.width, m.render.height);
                                      }
                                    });
}

}  // namespace dtraced::protocol
