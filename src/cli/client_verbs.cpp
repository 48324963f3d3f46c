#include "cli/client_verbs.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <thread>
#include <utility>

#include <fmt/format.h>

#include "cli/overrides_flags.h"
#include "cli/retry.h"
#include "cli/session.h"
#include "http/client.h"
#include "image/image_io.h"
#include "protocol/messages.h"
#include "protocol/worker_messages.h"
#include "render/cost_map.h"
#include "render/render_scene.h"
#include "scene/load.h"
#include "util/file.h"
#include "util/token_file.h"

namespace dtraced::cli {

namespace {

constexpr int kExitOk = 0;
constexpr int kExitFailed = 1;
constexpr int kExitUsage = 2;
// An image response can be a 16384^2 PFM.
constexpr std::uint64_t kMaxImageResponse = std::uint64_t(16384) * 16384 * 12 + (1 << 20);

// "64 spp", or with adaptive sampling the mean over the stored tiles and the cap: "21.3/64 spp".
std::string samples_text(const protocol::JobStatus& s) {
  if (s.mean_spp && *s.mean_spp != double(s.samples)) return fmt::format("{:.1f}/{} spp", *s.mean_spp, s.samples);
  return fmt::format("{} spp", s.samples);
}

// A sequence's frames: "  frames 2/4, frame 8: 5/12 tiles"; nothing for a single frame.
std::string frames_text(const protocol::JobStatus& s) {
  if (!s.frames) return {};
  const protocol::FrameProgress& f = *s.frames;
  return fmt::format("  frames {}/{}, frame {}: {}/{} tiles", f.frames_done, f.frames_total, f.frame,
                     f.frame_tiles_done, f.frame_tiles_total);
}

void print_status_line(const protocol::JobStatus& s) {
  fmt::print("{:>6}  {:<10} {:>4}  {:>5}x{:<5} {:>16}  {:>6}/{:<6} tiles  {:>8}  eta {:>8}  {}{}{}\n", s.id,
             protocol::to_string(s.state), s.priority, s.width, s.height, samples_text(s), s.tiles_done, s.tiles_total,
             format_seconds(s.elapsed_s), s.eta_s ? format_seconds(*s.eta_s) : "-", s.output, frames_text(s),
             s.no_worker_s ? fmt::format("  (no worker for {})", format_seconds(*s.no_worker_s)) : std::string());
}

// The cost pre-pass is skipped for scenes of more primitives (objects, a mesh counting its
// triangles) than this: building their BVH in the client takes longer than the order saves on a
// small farm (about 0.1 s for 100,000 spheres), and a large job's tail is a small part of it.
constexpr std::size_t kMaxCostPassPrimitives = 100'000;

std::size_t primitive_count(const scene::SceneDesc& desc) {
  std::size_t n = 0;
  for (const scene::Object& o : desc.objects) {
    n += o.type == scene::ObjectType::kMesh && o.mesh ? o.mesh->vertices.size() / 3 : 1;
  }
  return n;
}

// The estimated cost of each tile of the job's first frame (render/cost_map.h), or nothing when the
// scene is too large for a cheap pre-pass.
std::vector<float> estimate_tile_costs(const protocol::JobSubmit& submit) {
  if (primitive_count(submit.scene) > kMaxCostPassPrimitives) return {};
  scene::RenderSettings s = protocol::effective_settings(submit);
  s.frame = protocol::frame_number(s, 0);
  s.frames.reset();
  const render::AnimatedScene prepared = render::AnimatedScene::prepare(submit.scene);
  const std::shared_ptr<const render::RenderScene> frame = prepared.frame(s.frame);
  return render::tile_cost_map(*frame, s, scene::tile_size_or_default(submit.overrides)).costs;
}

bool finished(protocol::JobState s) { return s == protocol::JobState::kDone || s == protocol::JobState::kCancelled; }

}  // namespace

// One reader for both roles and every client verb (util/token_file.h), whose errors say that it
// is the token file that could not be used.
util::Result<std::string> read_token_file(const std::string& path) { return util::read_token_file(path); }

int run_submit(const ClientArgs& client, const SubmitArgs& args) {
  scene::LoadResult loaded = scene::load_scene_file(args.scene);
  if (!loaded.ok()) {
    for (const auto& e : loaded.errors) fmt::print(stderr, "{}\n", e.to_string());
    return kExitFailed;
  }
  if (!args.output.empty()) {
    if (util::Status ok = protocol::check_output_name(args.output); !ok) {
      fmt::print(stderr, "--output: {}\n", ok.error().message);
      return kExitFailed;
    }
  }
  // Mesh files travel inside the scene: the canonical form (what protocol::encode sends) carries
  // each OBJ's text as "obj", since a worker host has no such file.
  // Name as written -> (bytes, objects using it): a file placed n times is inlined n times.
  std::map<std::string, std::pair<std::size_t, std::size_t>> mesh_files;
  for (const scene::Object& o : loaded.scene->objects) {
    if (o.type == scene::ObjectType::kMesh && !o.mesh->file.empty()) {
      auto& [bytes, uses] = mesh_files[o.mesh->file];
      bytes = o.mesh->obj.size();
      ++uses;
    }
  }
  protocol::JobSubmit submit;
  submit.scene = std::move(*loaded.scene);
  submit.output = args.output;
  submit.priority = args.priority;
  submit.overrides = args.overrides;
  if (submit.overrides.crop) {
    // Refused here as `render --crop` refuses it, rather than by the collector.
    const scene::RenderSettings effective = protocol::effective_settings(submit);
    if (util::Status inside = check_crop(*submit.overrides.crop, effective.width, effective.height); !inside) {
      fmt::print(stderr, "{}\n", inside.error().to_string());
      return kExitUsage;
    }
  }
  if (args.cost_pass) submit.tile_costs = estimate_tile_costs(submit);
  std::string body = protocol::encode(submit);
  // Refused here with the reason, rather than by the collector as a bare 413.
  if (body.size() > protocol::kMaxJobSubmitBytes) {
    fmt::print(stderr,
               "{}: the job is {} bytes with its meshes inlined, over the collector's limit of {} bytes ({} MiB)\n",
               args.scene, body.size(), protocol::kMaxJobSubmitBytes, protocol::kMaxJobSubmitBytes >> 20);
    for (const auto& [file, size] : mesh_files) {
      fmt::print(stderr, "  mesh file {}: {} bytes, inlined {} time{}\n", file, size.first, size.second,
                 size.second == 1 ? "" : "s");
    }
    return kExitFailed;
  }
  Session session;
  if (!session.init(client)) return kExitFailed;
  auto resp = session.call(http::Verb::post, "/v1/jobs", std::move(body));
  if (!resp) return kExitFailed;
  auto created = decode_or_report(protocol::decode_job_created(resp->body()), "POST /v1/jobs");
  if (!created) return kExitFailed;
  fmt::print("{}\n", created->id);
  return kExitOk;
}

int run_list(const ClientArgs& client, const ListArgs& args) {
  std::string target = "/v1/jobs";
  char sep = '?';
  if (!args.state.empty()) {
    if (!protocol::job_state_from_string(args.state)) {
      fmt::print(stderr, "--state: '{}' is not a job state (queued, rendering, paused, done, cancelled)\n", args.state);
      return kExitFailed;
    }
    target += fmt::format("{}state={}", sep, args.state);
    sep = '&';
  }
  if (args.limit > 0) target += fmt::format("{}limit={}", sep, args.limit);
  Session session;
  if (!session.init(client)) return kExitFailed;
  auto resp = session.call(http::Verb::get, target);
  if (!resp) return kExitFailed;
  auto list = decode_or_report(protocol::decode_job_list(resp->body()), "GET " + target);
  if (!list) return kExitFailed;
  if (args.json) {
    fmt::print("{}\n", protocol::encode(*list));
    return kExitOk;
  }
  fmt::print("{:>6}  {:<10} {:>4}  {:>11} {:>16}  {:>13} tiles  {:>8}  {:>12}  {}\n", "id", "state", "prio", "size",
             "samples", "done/total", "elapsed", "eta", "output");
  for (const auto& s : list->jobs) print_status_line(s);
  return kExitOk;
}

int run_status(const ClientArgs& client, const StatusArgs& args) {
  Session session;
  if (!session.init(client)) return kExitFailed;
  const std::string target = fmt::format("/v1/jobs/{}", args.id);
  const bool bar = args.wait && !args.json && ::isatty(STDERR_FILENO);
  // With --wait, a collector restart is ridden out like the workers do, for --retry-for-s.
  if (args.wait) {
    session.retry_for(std::chrono::seconds(args.retry_for_s), fmt::format("--retry-for-s {}", args.retry_for_s));
  }
  while (true) {
    auto resp = session.call(http::Verb::get, target);
    if (!resp) return kExitFailed;
    auto st = decode_or_report(protocol::decode_job_status(resp->body()), "GET " + target);
    if (!st) return kExitFailed;
    const bool done = finished(st->state);
    if (bar) {
      constexpr int kWidth = 40;
      const double frac = st->tiles_total ? double(st->tiles_done) / st->tiles_total : 0.0;
      const int filled = int(frac * kWidth);
      fmt::print(
          stderr, "\rjob {} [{:#<{}}{:-<{}}] {:3d}% {}/{} tiles{}, eta {}   ", st->id, "", filled, "", kWidth - filled,
          int(frac * 100), st->tiles_done, st->tiles_total,
          st->frames ? fmt::format(", frame {}/{}", st->frames->frames_done, st->frames->frames_total) : std::string(),
          st->eta_s ? format_seconds(*st->eta_s) : "-");
      if (done) fmt::print(stderr, "\n");
    }
    if (!args.wait || done) {
      if (args.json) {
        fmt::print("{}\n", protocol::encode(*st));
      } else {
        print_status_line(*st);
      }
      return st->state == protocol::JobState::kCancelled && args.wait ? kExitFailed : kExitOk;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(args.poll_ms));
  }
}

int run_fetch(const ClientArgs& client, std::uint64_t id, const std::string& output,
              std::optional<std::uint32_t> frame) {
  const auto format = image::format_from_path(output);
  if (!format) {
    fmt::print(stderr, "{}: unsupported output format (use {})\n", output, image::extension_list());
    return kExitFailed;
  }
  Session session;
  if (!session.init(client)) return kExitFailed;
  auto resp = session.call(http::Verb::get,
                           fmt::format("/v1/jobs/{}/image?format={}{}", id, image::format_info(*format).name,
                                       frame ? fmt::format("&frame={}", *frame) : std::string()),
                           {}, kMaxImageResponse);
  if (!resp) return kExitFailed;
  if (util::Status written = util::write_file_atomic(output, resp->body()); !written) {
    fmt::print(stderr, "{}\n", written.error().to_string());
    return kExitFailed;
  }
  return kExitOk;
}

namespace {

// POSTs to one of a job's change endpoints (cancel, priority, requeue, pause, resume) and prints
// the job's status from the answer.
int change_job(const ClientArgs& client, std::uint64_t id, std::string_view change, std::string body = {}) {
  Session session;
  if (!session.init(client)) return kExitFailed;
  const std::string target = fmt::format("/v1/jobs/{}/{}", id, change);
  auto resp = session.call(http::Verb::post, target, std::move(body));
  if (!resp) return kExitFailed;
  auto st = decode_or_report(protocol::decode_job_status(resp->body()), "POST " + target);
  if (!st) return kExitFailed;
  print_status_line(*st);
  return kExitOk;
}

}  // namespace

int run_cancel(const ClientArgs& client, std::uint64_t id) { return change_job(client, id, "cancel"); }

int run_priority(const ClientArgs& client, std::uint64_t id, std::int32_t priority) {
  return change_job(client, id, "priority", protocol::encode(protocol::JobPriority{priority}));
}

int run_requeue(const ClientArgs& client, std::uint64_t id) { return change_job(client, id, "requeue"); }

// "1.2M" style counts for the rays column.
std::string short_count(std::uint64_t n) {
  if (n < 10'000) return std::to_string(n);
  if (n < 10'000'000) return fmt::format("{:.1f}k", double(n) / 1e3);
  if (n < 10'000'000'000ull) return fmt::format("{:.1f}M", double(n) / 1e6);
  return fmt::format("{:.1f}G", double(n) / 1e9);
}

int run_workers(const ClientArgs& client, bool json) {
  Session session;
  if (!session.init(client)) return kExitFailed;
  auto resp = session.call(http::Verb::get, "/v1/workers", {}, protocol::kMaxWorkerListBytes);
  if (!resp) return kExitFailed;
  auto list = decode_or_report(protocol::decode_worker_list(resp->body()), "GET /v1/workers");
  if (!list) return kExitFailed;
  if (json) {
    fmt::print("{}\n", protocol::encode(*list));
    return kExitOk;
  }
  // Names and addresses vary in width: size those columns to the longest (bounded by the protocol).
  std::size_t name_width = 4;
  std::size_t peer_width = 4;
  for (const auto& w : list->workers) {
    name_width = std::max(name_width, w.name.size());
    peer_width = std::max(peer_width, w.peer.size());
  }
  const std::string recent = fmt::format("last {}", format_seconds(list->recent_window_s));
  fmt::print("{:<{}}  {:<{}}  {:<6} {:>7}  {:<6} {:>9}  {:>8} {:>8}  {:>8} {:>6} {:>7}  ({})\n", "name", name_width,
             "peer", peer_width, "state", "threads", "isa", "last seen", "tiles", "rays", "all", "faulty", "refused",
             recent);
  for (const auto& w : list->workers) {
    fmt::print("{:<{}}  {:<{}}  {:<6} {:>7}  {:<6} {:>9}  {:>8} {:>8}  {:>8} {:>6} {:>7}\n", w.name, name_width,
               w.peer.empty() ? "-" : w.peer, peer_width, w.quiet ? "quiet" : "active",
               w.threads == 0 ? std::string("-") : std::to_string(w.threads), w.isa.empty() ? "-" : w.isa,
               format_seconds(w.last_seen_s) + " ago", w.recent_tiles, short_count(w.recent_rays), w.tiles,
               w.faulty_duplicates, w.refused);
  }
  if (list->workers.empty()) fmt::print(stderr, "no worker has asked this collector for work yet\n");
  return kExitOk;
}

int run_pause(const ClientArgs& client, std::uint64_t id, bool pause) {
  return change_job(client, id, pause ? "pause" : "resume");
}

int run_delete(const ClientArgs& client, std::uint64_t id, bool delete_image) {
  Session session;
  if (!session.init(client)) return kExitFailed;
  const std::string target = fmt::format("/v1/jobs/{}{}", id, delete_image ? "?image=delete" : "");
  auto resp = session.call(http::Verb::delete_, target);
  if (!resp) return kExitFailed;
  auto deleted = decode_or_report(protocol::decode_job_deleted(resp->body()), "DELETE " + target);
  if (!deleted) return kExitFailed;
  fmt::print("job {} deleted with {} stored tile(s); image {}\n", deleted->id, deleted->tiles, deleted->image);
  if (!deleted->image_error.empty()) {
    fmt::print(stderr, "the image file was not removed: {}\n", deleted->image_error);
    return kExitFailed;
  }
  return kExitOk;
}

}  // namespace dtraced::cli
