// The web page's routes (docs/web-access.md): its embedded files, sign-in and sign-out, the tile
// delta of a job's preview and the focus that renders a region first. The page's other API
// routes are the /v1 handlers themselves (routes.h, page_may_call).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include <boost/beast/http/field.hpp>
#include <boost/json/array.hpp>
#include <boost/json/object.hpp>
#include <fmt/format.h>
#include <openssl/evp.h>

#include "collector/handlers.h"
#include "collector/web_access.h"
#include "image/image_io.h"
#include "jsonio/write.h"
#include "util/log.h"
#include "util/sha256.h"
#include "web/assets.h"

namespace dtraced::collector {
namespace {

namespace bhttp = boost::beast::http;
namespace json = boost::json;

// A tile delta carries at most this many pixels (the atlas's cells), so one answer stays small
// and quick to encode; `more` tells the page to ask again at once.
constexpr std::uint64_t kMaxDeltaPixels = 2u << 20;

std::string_view header(const http::Request& req, bhttp::field f) {
  const auto it = req.find(f);
  return it == req.end() ? std::string_view() : std::string_view(it->value().data(), it->value().size());
}

// Whether If-None-Match names `etag` (or is *). A list of tags is searched as text: each is quoted.
bool etag_matches(const http::Request& req, std::string_view etag) {
  const std::string_view inm = header(req, bhttp::field::if_none_match);
  return !inm.empty() && (inm == "*" || inm.find(etag) != std::string_view::npos);
}

http::Response not_modified(std::string_view etag) {
  http::Response res{http::Status::not_modified, 11};
  res.set(bhttp::field::etag, boost::beast::string_view(etag.data(), etag.size()));
  return res;
}

http::Response json_object(http::Status status, const json::object& o) {
  return http::make_text_response(status, jsonio::to_text(o), http::kJsonContentType);
}

std::int64_t whole_seconds(Duration d) { return std::chrono::duration_cast<std::chrono::seconds>(d).count(); }

// Logged like a refused bearer token (router.cpp): rate-limited, with the peer, never the token.
void note_sign_in_failure(Context& c, const http::Request& req, std::string_view why) {
  ++c.counters.auth_failures;
  ++c.counters.sign_in_failures;
  std::uint64_t held_back = 0;
  if (!c.auth_failure_log.allow(c.clock.now(), held_back)) return;
  const std::string peer = request_peer(req);
  util::log_warn(
      "collector: refused a web page sign-in from {}: {}{}", peer.empty() ? "an unknown address" : peer, why,
      held_back == 0 ? std::string() : fmt::format(" ({} more refused since the last such line)", held_back));
}

// The frame a page route shows: `frame` (a frame number), or the frame being rendered.
util::Result<std::uint32_t, Refusal> shown_frame(const JobRecord& job, std::optional<std::uint32_t> frame) {
  if (!frame) return std::min(job.frames_written, job.frames_total - 1);
  const std::optional<std::uint32_t> index = frame_index_of(job.settings, *frame);
  if (!index) {
    return Refusal{
        http::Status::not_found, util::Error(fmt::format("job {} renders no frame {}", job.id, *frame), "/frame"), {}};
  }
  return *index;
}

// The displayed image: the crop for a cropped job, else the whole frame.
scene::TileRect displayed_area(const JobRecord& job) {
  if (job.crop) return *job.crop;
  return {0, 0, job.settings.width, job.settings.height};
}

// `rect` (full-frame coordinates) clipped to the displayed area, in displayed coordinates; empty
// (width 0) when outside it.
scene::TileRect to_displayed(const scene::TileRect& rect, const scene::TileRect& area) {
  const std::uint32_t x0 = std::max(rect.x0, area.x0), y0 = std::max(rect.y0, area.y0);
  const std::uint32_t x1 = std::min(rect.x0 + rect.width, area.x0 + area.width);
  const std::uint32_t y1 = std::min(rect.y0 + rect.height, area.y0 + area.height);
  if (x1 <= x0 || y1 <= y0) return {};
  return {x0 - area.x0, y0 - area.y0, x1 - x0, y1 - y0};
}

// Gives the tiles restored at start-up (or read back by a requeue) their sequence numbers, once.
void ensure_seqs(JobRecord& job) {
  if (job.tile_seq.size() == job.tile_indices) return;
  job.tile_seq.assign(job.tile_indices, 0);
  for (TileIndex t = 0; t < job.tile_indices && t < job.restored.size(); ++t) {
    if (job.restored[t]) job.tile_seq[t] = ++job.last_seq;
  }
}

std::string base64(std::string_view bytes) {
  std::string out(4 * ((bytes.size() + 2) / 3) + 1, '\0');
  const int n = EVP_EncodeBlock(reinterpret_cast<unsigned char*>(out.data()),
                                reinterpret_cast<const unsigned char*>(bytes.data()), static_cast<int>(bytes.size()));
  out.resize(static_cast<std::size_t>(n));
  return out;
}

struct DeltaTile {
  TileIndex tile = 0;
  scene::TileRect full;       // in the frame
  scene::TileRect displayed;  // in the displayed image
  std::uint32_t seq = 0;
  std::uint32_t ax = 0, ay = 0;
};

}  // namespace

// ---- the registry of the page's view (called by the lease and tile handlers) -----------------

void note_page_lease(JobRecord& job, TileIndex tile, std::string_view worker) {
  if (job.leased_by.size() >= kMaxLeaseHolders && !job.leased_by.contains(tile)) return;
  job.leased_by[tile] = std::string(worker);
}

void note_page_stored(JobRecord& job, TileIndex tile, std::string_view worker) {
  ensure_seqs(job);
  if (tile >= job.tile_seq.size()) return;
  job.tile_seq[tile] = ++job.last_seq;
  job.leased_by.erase(tile);
  if (job.tile_worker.size() != job.tile_indices) job.tile_worker.assign(job.tile_indices, 0);
  auto name = std::find(job.worker_names.begin(), job.worker_names.end(), worker);
  if (name == job.worker_names.end()) {
    if (job.worker_names.size() >= kMaxJobWorkerNames) return;  // shown as unknown
    name = job.worker_names.insert(job.worker_names.end(), std::string(worker));
  }
  job.tile_worker[tile] = static_cast<std::uint16_t>(1 + (name - job.worker_names.begin()));
}

// ---- the page's files and sessions -------------------------------------------------------------

http::Response get_page_asset(const std::string& path, const http::Request& req) {
  const web::Asset* asset = web::find_asset(path);
  if (asset == nullptr) return http::make_error(http::Status::not_found, "no such endpoint");
  http::Response res =
      etag_matches(req, asset->etag)
          ? not_modified(asset->etag)
          : http::make_binary_response(http::Status::ok, std::string(asset->text()), asset->content_type);
  res.set(bhttp::field::etag, boost::beast::string_view(asset->etag.data(), asset->etag.size()));
  res.set(bhttp::field::cache_control, "no-cache");
  return res;
}

http::Response sign_in(Context& c, const http::Request& req) {
  const TimePoint now = c.clock.now();
  if (!c.sign_ins.allows(now)) {
    note_sign_in_failure(c, req, "too many failed sign-ins in the last minute");
    http::Response res =
        http::make_error(http::Status::too_many_requests, "too many failed sign-ins; wait a minute and try again");
    res.set(bhttp::field::retry_after,
            std::to_string(std::max<std::int64_t>(1, whole_seconds(c.sign_ins.retry_after(now)) + 1)));
    return res;
  }
  const std::string_view type = header(req, bhttp::field::content_type);
  if (!type.starts_with(http::kJsonContentType)) {
    return http::make_error(http::Status::unsupported_media_type, "a sign-in is sent as application/json");
  }
  auto token = decode_sign_in(req.body());
  if (!token) return respond(token.error());
  const Authentication auth = authenticate_token(*token, c.token, c.credentials);
  if (auth.kind != Authentication::Kind::kLive) {
    c.sign_ins.failed(now);
    const bool revoked = auth.kind == Authentication::Kind::kRevoked;
    note_sign_in_failure(c, req, revoked ? "a revoked credential" : "wrong token");
    return http::make_error(http::Status::unauthorized, revoked ? "this credential was revoked" : "wrong token",
                            "/token");
  }
  // The page is for people: a worker's credential signs in nowhere.
  if (auth.who.role == Role::kWorker) {
    ++c.counters.role_refusals[static_cast<std::size_t>(Role::kWorker)];
    return respond(role_refusal(Role::kWorker, RouteKind::kSessionCreate));
  }
  const std::optional<SessionStore::Created> session = c.sessions.create(now, auth.who);
  if (!session) return respond(busy("no random numbers for a session; retry later"));
  const std::int64_t max_age = whole_seconds(c.sessions.limits().lifetime);
  http::Response res = json_object(
      http::Status::ok, {{"csrf", session->csrf}, {"expires_in_s", max_age}, {"role", role_name(auth.who.role)}});
  res.set(bhttp::field::set_cookie, session_set_cookie(session->id, max_age, page_scheme(c.config.tls.enabled)));
  return res;
}

http::Response get_session(Context& c, const http::Request& req) {
  const std::optional<SessionStore::Live> live = c.sessions.find(session_cookie(req), c.clock.now());
  // Not signed in is an answer, not a failure: the page asks this at every load, and a 401 here
  // would be an error in the browser's console on each first visit.
  if (!live) return json_object(http::Status::ok, {{"signed_in", false}});
  return json_object(http::Status::ok, {{"signed_in", true},
                                        {"csrf", live->csrf},
                                        {"expires_in_s", whole_seconds(live->remaining)},
                                        {"role", role_name(live->who.role)}});
}

http::Response sign_out(Context& c, const http::Request& req) {
  c.sessions.remove(session_cookie(req));
  http::Response res{http::Status::no_content, 11};
  res.set(bhttp::field::set_cookie, session_clear_cookie(page_scheme(c.config.tls.enabled)));
  return res;
}

// ---- the tile delta ----------------------------------------------------------------------------

async::Awaitable<http::Response> get_job_tiles(Context& c, const Route& route, const http::Request& req) {
  JobRecord* job = c.find_job(route.job);
  if (job == nullptr) co_return respond(job_not_found(route.job));
  auto frame = shown_frame(*job, route.image_frame);
  if (!frame) co_return respond(frame.error());
  const std::uint32_t frame_index = *frame;
  const scene::TileRect area = displayed_area(*job);
  const bool written = !job->unfinished() || frame_index < job->frames_written;
  const TileIndex first = frame_index * job->tiles_per_frame;
  const TileIndex end = first + job->tiles_per_frame;

  // What is new, oldest first, up to the pixel cap.
  std::vector<DeltaTile> tiles;
  bool more = false;
  json::array leased;
  std::string lease_text;  // for the ETag
  if (!written) {
    ensure_seqs(*job);
    std::vector<std::pair<std::uint32_t, TileIndex>> fresh;
    for (TileIndex t = first; t < end && t < job->tile_seq.size(); ++t) {
      if (job->tile_seq[t] > route.since) fresh.emplace_back(job->tile_seq[t], t);
    }
    std::sort(fresh.begin(), fresh.end());
    std::uint64_t pixels = 0;
    for (const auto& [seq, t] : fresh) {
      const std::uint64_t cell = std::uint64_t{job->tile_size} * job->tile_size;
      if (!tiles.empty() && pixels + cell > kMaxDeltaPixels) {
        more = true;
        break;
      }
      pixels += cell;
      const scene::TileRect full = tile_place(*job, t).rect;
      tiles.push_back({t, full, to_displayed(full, area), seq});
    }
    const TimePoint now = c.clock.now();
    for (auto it = job->leased_by.lower_bound(first); it != job->leased_by.end() && it->first < end;) {
      if (!c.queue.has_lease(job->id, it->first, now)) {
        it = job->leased_by.erase(it);  // expired or stored: the outline goes
        continue;
      }
      const scene::TileRect shown = to_displayed(tile_place(*job, it->first).rect, area);
      leased.push_back(json::object{{"tile", it->first},
                                    {"x", shown.x0},
                                    {"y", shown.y0},
                                    {"width", shown.width},
                                    {"height", shown.height},
                                    {"worker", it->second}});
      lease_text += fmt::format("{}:{};", it->first, it->second);
      ++it;
    }
  }
  const std::uint32_t seq = tiles.empty()
                                ? static_cast<std::uint32_t>(std::min<std::uint64_t>(route.since, job->last_seq))
                                : tiles.back().seq;
  // Decided before any pixel is touched: the same request with nothing new is a 304.
  const std::string etag =
      fmt::format("\"{}\"", util::sha256_hex(fmt::format("{}/{}/{}/{}/{}/{}/{}/{}/{}", c.epoch, job->id, frame_index,
                                                         route.since, job->last_seq, protocol::to_string(job->state),
                                                         written, job->frames_written, lease_text))
                                .substr(0, 32));
  if (etag_matches(req, etag)) co_return not_modified(etag);

  json::object o{{"job", job->id},
                 {"generation", c.epoch},
                 {"frame", protocol::frame_number(job->settings, frame_index)},
                 {"frames_total", job->frames_total},
                 {"frame_index", frame_index},
                 {"width", area.width},
                 {"height", area.height},
                 {"tile_size", job->tile_size},
                 {"state", protocol::to_string(job->state)},
                 {"written", written},
                 {"seq", seq},
                 {"more", more}};
  json::array tile_list;
  if (!tiles.empty()) {
    // The atlas: a grid of tile_size cells, as square as it comes.
    const auto n = static_cast<std::uint32_t>(tiles.size());
    const auto columns = static_cast<std::uint32_t>(std::ceil(std::sqrt(double(n))));
    const std::uint32_t rows = (n + columns - 1) / columns;
    for (std::uint32_t i = 0; i < n; ++i) {
      tiles[i].ax = (i % columns) * job->tile_size;
      tiles[i].ay = (i / columns) * job->tile_size;
    }
    const std::uint16_t* who = job->tile_worker.empty() ? nullptr : job->tile_worker.data();
    for (const DeltaTile& t : tiles) {
      const std::uint16_t w = who != nullptr ? who[t.tile] : 0;
      tile_list.push_back(json::object{{"tile", t.tile},
                                       {"x", t.displayed.x0},
                                       {"y", t.displayed.y0},
                                       {"width", t.displayed.width},
                                       {"height", t.displayed.height},
                                       {"seq", t.seq},
                                       {"worker", w == 0 ? std::string() : job->worker_names[w - 1]},
                                       {"ax", t.ax},
                                       {"ay", t.ay}});
    }
    // On the pool, as GET image encodes: each new tile's pixels from the store (the collector keeps
    // no framebuffer). A tile the store cannot give stays black in the atlas, and is logged.
    const image::WriteOptions options{.png_bit_depth = 8, .display = job->settings.display};
    auto encode = [&reader = c.reader, id = job->id, &tiles, area, columns, rows, size = job->tile_size, options] {
      image::ImageRGBf atlas(columns * size, rows * size);
      for (const DeltaTile& t : tiles) {
        const std::size_t pixels = std::size_t{t.full.width} * t.full.height;
        util::Result<std::optional<std::vector<float>>> rgb = reader.tile_rgb(id, t.tile, pixels);
        if (!rgb || !rgb.value()) {
          if (!rgb)
            util::log_warn("collector: job {}: the preview cannot read tile {}: {}", id, t.tile, rgb.error().message);
          continue;
        }
        const std::vector<float>& from = *rgb.value();
        // displayed is in the displayed area; full in the frame: the displayed part's offset in the tile.
        const std::uint32_t dx = area.x0 + t.displayed.x0 - t.full.x0;
        const std::uint32_t dy = area.y0 + t.displayed.y0 - t.full.y0;
        for (std::uint32_t y = 0; y < t.displayed.height; ++y) {
          const float* row = from.data() + (std::size_t{dy + y} * t.full.width + dx) * 3;
          std::copy(row, row + std::size_t{t.displayed.width} * 3, atlas.pixel(t.ax, t.ay + y));
        }
      }
      return std::optional(image::encode_image(image::ImageFormat::kPng, atlas, options));
    };
    std::optional<util::Result<std::string>> encoded = co_await async::on_pool(c.pool, std::move(encode));
    if (!encoded->ok()) {
      const std::string why = encoded->error().to_string();
      util::log_error("collector: job {}: cannot encode a preview atlas: {}", route.job, why);
      co_return http::make_error(http::Status::internal_server_error, "cannot encode the preview: " + why);
    }
    o["atlas"] = base64(encoded->value());
  }
  o["tiles"] = std::move(tile_list);
  o["leased"] = std::move(leased);
  http::Response res = json_object(http::Status::ok, o);
  res.set(bhttp::field::etag, etag);
  co_return res;
}

// ---- focus -------------------------------------------------------------------------------------

http::Response focus_job(Context& c, JobId id, const http::Request& req) {
  auto rect = decode_focus(req.body());
  if (!rect) return respond(rect.error());
  JobRecord* job = c.find_job(id);
  if (job == nullptr) return respond(job_not_found(id));
  const scene::TileRect area = displayed_area(*job);
  if (rect->x >= area.width) {
    return respond(bad_request(fmt::format("x must be inside the {}x{} image", area.width, area.height), "/x"));
  }
  if (rect->y >= area.height) {
    return respond(bad_request(fmt::format("y must be inside the {}x{} image", area.width, area.height), "/y"));
  }
  std::size_t moved = 0;
  if (job->unfinished()) {
    // In frame coordinates, clipped to the displayed image.
    const auto x0 = static_cast<std::uint32_t>(rect->x) + area.x0;
    const auto y0 = static_cast<std::uint32_t>(rect->y) + area.y0;
    const std::uint32_t x1 =
        area.x0 + static_cast<std::uint32_t>(std::min<std::int64_t>(rect->x + rect->width, area.width));
    const std::uint32_t y1 =
        area.y0 + static_cast<std::uint32_t>(std::min<std::int64_t>(rect->y + rect->height, area.height));
    // Twice the centre, to stay in integers.
    const std::int64_t cx2 = std::int64_t{x0} + x1, cy2 = std::int64_t{y0} + y1;
    const std::uint32_t frame_index = std::min(job->frames_written, job->frames_total - 1);
    const scene::TileGrid grid(job->settings, job->tile_size);
    std::vector<std::pair<std::int64_t, TileIndex>> near;
    for (std::uint64_t i = 0; i < grid.count(); ++i) {
      const scene::TileRect r = grid.rect(i);
      if (r.x0 >= x1 || r.y0 >= y1 || r.x0 + r.width <= x0 || r.y0 + r.height <= y0) continue;
      const TileIndex t = frame_index * job->tiles_per_frame + static_cast<TileIndex>(i);
      if (!tile_of_job(*job, t)) continue;
      const std::int64_t dx = 2 * std::int64_t{r.x0} + r.width - cx2, dy = 2 * std::int64_t{r.y0} + r.height - cy2;
      near.emplace_back(dx * dx + dy * dy, t);
    }
    std::sort(near.begin(), near.end());
    std::vector<TileIndex> order;
    order.reserve(near.size());
    for (const auto& [d, t] : near) order.push_back(t);
    moved = c.queue.focus(id, order);
  }
  ++c.counters.focus_requests;
  c.counters.focus_tiles += moved;
  return json_object(http::Status::ok, {{"tiles", moved}});
}

}  // namespace dtraced::collector
