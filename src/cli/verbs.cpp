#include "cli/verbs.h"

#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <optional>
#include <system_error>
#include <thread>

#include <fmt/format.h>

#include "cli/partial_render.h"
#include "image/image_io.h"
#include "image/metrics.h"
#include "jsonio/parse.h"
#include "jsonio/write.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/digest.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "scene/tiling.h"
#include "util/file.h"

namespace dtraced::cli {

namespace {

constexpr int kExitOk = 0;
constexpr int kExitFailed = 1;
constexpr int kExitUsage = 2;

// Whether `r` holds a value; prints its error on stderr when it does not.
template <typename R>
bool reported(const R& r) {
  if (!r) fmt::print(stderr, "{}\n", r.error().to_string());
  return r.ok();
}

void print_errors(const scene::LoadResult& r) {
  for (const util::Error& e : r.errors) fmt::print(stderr, "{}\n", e.to_string());
}

// What a loaded scene has that is legal but likely a mistake (no lights, an empty mesh): the
// same lines from validate and render, so a render never hides what validate would say.
void print_warnings(const scene::LoadResult& r) {
  for (const util::Error& w : r.warnings) fmt::print(stderr, "warning: {}\n", w.to_string());
}

// A one-line progress bar on stderr, redrawn in place; only used when stderr is a terminal.
class ProgressBar {
 public:
  void draw(std::size_t done, std::size_t total) {
    constexpr int kWidth = 40;
    const double frac = total ? double(done) / double(total) : 1.0;
    const int filled = int(frac * kWidth);
    const int pct = int(frac * 100.0);
    if (pct == last_pct_) return;
    last_pct_ = pct;
    fmt::print(stderr, "\r[{:#<{}}{:-<{}}] {:3d}% {}/{} tiles", "", filled, "", kWidth - filled, pct, done, total);
    if (done == total) fmt::print(stderr, "\n");
    std::fflush(stderr);
  }

 private:
  int last_pct_ = -1;
};

// The samples each pixel took as an image: raw counts for PFM; for the 8/16-bit formats, which
// sRGB-encode what they write, the linear value whose encoding is n / samples, so that the code
// values grow in proportion to n. `spp` empty means every pixel took settings.samples.
image::ImageRGBf spp_image(const scene::RenderSettings& s, const std::vector<std::uint32_t>& spp,
                           image::ImageFormat format) {
  image::ImageRGBf out(s.width, s.height);
  for (std::size_t i = 0; i < std::size_t(s.width) * s.height; ++i) {
    const std::uint32_t n = spp.empty() ? s.samples : spp[i];
    const float v = format == image::ImageFormat::kPfm ? float(n) : image::srgb_to_linear(float(n) / float(s.samples));
    for (int c = 0; c < 3; ++c) out.rgb[i * 3 + c] = v;
  }
  return out;
}

// kExitUsage, with the problem on stderr, when an output file (the image, the --spp-map) has an
// unknown format or a directory that is missing or not writable; kExitOk otherwise.
int check_outputs(const RenderArgs& args) {
  const std::pair<const std::string*, const char*> outputs[] = {{&args.output, "--output"},
                                                                {&args.spp_map, "--spp-map"}};
  for (const auto& [path, flag] : outputs) {
    if (path->empty() && path == &args.spp_map) continue;
    if (!image::format_from_path(*path)) {
      fmt::print(stderr, "{}: {}: unsupported format (use {})\n", flag, *path, image::extension_list());
      return kExitUsage;
    }
    if (const util::Status ok = util::check_output_path(*path); !ok) {
      fmt::print(stderr, "{}: {}\n", flag, ok.error().to_string());
      return kExitUsage;
    }
  }
  return kExitOk;
}

// SIGINT and SIGTERM, while one of these lives, set `stop` (and `number`) instead of ending the
// process: they are blocked in this thread, so in the render threads it starts (which inherit its
// signal mask), and a watcher thread of its own takes them with sigtimedwait. No handler and no
// global: the flag belongs to the verb. The mask is restored at the end.
class StopOnSignals {
 public:
  StopOnSignals(std::atomic<bool>& stop, std::atomic<int>& number) {
    ::sigemptyset(&set_);
    ::sigaddset(&set_, SIGINT);
    ::sigaddset(&set_, SIGTERM);
    ::pthread_sigmask(SIG_BLOCK, &set_, &old_);
    watcher_ = std::jthread([this, &stop, &number](std::stop_token done) {
      const timespec tick{0, 100'000'000};  // how soon the watcher sees `done`
      while (!done.stop_requested()) {
        const int sig = ::sigtimedwait(&set_, nullptr, &tick);
        if (sig <= 0) continue;
        if (!stop.exchange(true)) {
          number = sig;
          fmt::print(stderr, "\n{}: stopping once the tiles being rendered are done\n", ::strsignal(sig));
        }
      }
    });
  }
  ~StopOnSignals() {
    watcher_.request_stop();
    watcher_.join();
    // A signal that came after the watcher's last look would end the process once unblocked:
    // the render is over by now, so it is taken here and ignored.
    const timespec now{0, 0};
    while (::sigtimedwait(&set_, nullptr, &now) > 0) {
    }
    ::pthread_sigmask(SIG_SETMASK, &old_, nullptr);
  }
  StopOnSignals(const StopOnSignals&) = delete;
  StopOnSignals& operator=(const StopOnSignals&) = delete;

 private:
  sigset_t set_{};
  sigset_t old_{};
  std::jthread watcher_;
};

// A render's partial file: the tiles an earlier, interrupted render kept, and the writer that
// keeps this render's.
struct Partial {
  std::string path;
  std::vector<render::Tile> resumed;
  std::vector<bool> skip;  // by tile index: resumed
  std::optional<PartialWriter> writer;
};

// OUT.partial continued (--resume) or created; a partial file that is there is never replaced.
// kExitOk, or the exit code with the problem on stderr.
int open_partial(const RenderArgs& args, const scene::SceneDesc& desc, std::uint32_t tile_size, Partial& p) {
  p.path = partial_path(args.output);
  const std::string key = partial_key(desc, tile_size);
  std::error_code ec;
  if (!std::filesystem::exists(p.path, ec)) {
    if (args.resume) fmt::print(stderr, "{}: no partial render to resume; rendering from the start\n", p.path);
    util::Result<PartialWriter> made = PartialWriter::create(p.path, key);
    if (!reported(made)) return kExitFailed;
    p.writer.emplace(std::move(made).value());
    return kExitOk;
  }
  if (!args.resume) {
    fmt::print(stderr, "{}: a partial render of this output is there: --resume continues it; delete it to start over\n",
               p.path);
    return kExitUsage;
  }
  util::Result<PartialContents> read = read_partial(p.path, key, desc.render, tile_size);
  if (!reported(read)) return kExitFailed;
  if (read->dropped_bytes > 0) {
    fmt::print(stderr, "{}: dropped {} bytes of a tile cut short at its end\n", p.path, read->dropped_bytes);
  }
  const scene::TileGrid grid(desc.render, tile_size);
  p.skip.assign(grid.count(), false);
  for (const render::Tile& t : read->tiles)
    p.skip[t.rect.y0 / tile_size * grid.columns() + t.rect.x0 / tile_size] = true;
  p.resumed = std::move(read->tiles);
  util::Result<PartialWriter> reopened = PartialWriter::reopen(p.path, read->good_bytes);
  if (!reported(reopened)) return kExitFailed;
  p.writer.emplace(std::move(reopened).value());
  return kExitOk;
}

}  // namespace

std::string_view version_string() { return DTRACED_VERSION; }

int run_render(const RenderArgs& args) {
  // The outputs first: a render may take hours, and a typo in a path should not cost them.
  if (const int usage = check_outputs(args); usage != kExitOk) return usage;
  scene::LoadResult loaded = scene::load_scene_file(args.scene);
  if (!loaded.ok()) {
    print_errors(loaded);
    return kExitFailed;
  }
  print_warnings(loaded);
  scene::SceneDesc& desc = *loaded.scene;
  desc.render = scene::apply(args.overrides, desc.render);
  const scene::RenderSettings& s = desc.render;
  const std::uint32_t tile_size = scene::tile_size_or_default(args.overrides);
  Partial partial;
  if (const int code = open_partial(args, desc, tile_size, partial); code != kExitOk) return code;

  const auto build_start = std::chrono::steady_clock::now();
  const render::RenderScene rs = render::RenderScene::build(desc, args.isa);
  const double build_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();

  render::LocalOptions opts;
  opts.threads = args.threads;
  opts.tile_size = tile_size;
  ProgressBar bar;
  if (!args.quiet && ::isatty(STDERR_FILENO)) {
    opts.progress = [&bar](std::size_t done, std::size_t total) { bar.draw(done, total); };
  }
  // Every finished tile goes to the partial file, so that an interrupted render keeps it.
  opts.skip = partial.skip;
  std::optional<util::Error> partial_failed;  // only tile_done touches it (calls are serialised)
  opts.tile_done = [&partial, &partial_failed](std::size_t index, const render::Tile& t) {
    if (partial_failed) return;
    if (util::Status kept = partial.writer->append(static_cast<std::uint32_t>(index), t); !kept) {
      partial_failed = kept.error();
      fmt::print(stderr, "warning: {}; the render goes on, but an interruption would lose its tiles\n",
                 kept.error().to_string());
    }
  };
  std::atomic<bool> stop{false};
  std::atomic<int> signal_number{0};
  opts.stop_requested = [&stop] { return stop.load(); };
  render::LocalResult result;
  {
    const StopOnSignals on_signals(stop, signal_number);
    result = render::render_local(rs, s, opts);
  }
  if (!result.complete) {
    const util::Status synced = partial.writer->sync();
    if (!synced || partial_failed) {
      fmt::print(stderr, "interrupted: {}: the partial file is incomplete (see above)\n",
                 synced ? partial.path : synced.error().to_string());
      return 128 + signal_number.load();
    }
    fmt::print(stderr, "interrupted: {} of {} tiles are kept in {}; the same command with --resume continues\n",
               partial.resumed.size() + result.tiles_rendered, scene::TileGrid(s, tile_size).count(), partial.path);
    return 128 + signal_number.load();
  }
  for (const render::Tile& t : partial.resumed) render::paste_tile(t, s.width, result);

  image::WriteOptions wopts;
  wopts.png_bit_depth = static_cast<int>(scene::png_bit_depth_or_default(args.overrides));
  if (!reported(image::write_image(args.output, result.image, wopts))) return kExitFailed;
  if (!args.spp_map.empty()) {
    wopts.png_bit_depth = 16;
    const image::ImageRGBf map = spp_image(s, result.spp, *image::format_from_path(args.spp_map));
    if (!reported(image::write_image(args.spp_map, map, wopts))) return kExitFailed;
  }
  partial.writer.reset();
  std::error_code removed;
  std::filesystem::remove(partial.path, removed);  // the image holds it all now
  if (!args.quiet && !partial.resumed.empty()) {
    fmt::print(stderr, "resumed {} tiles from {}\n", partial.resumed.size(), partial.path);
  }
  if (!args.quiet) {
    const double mrays = double(result.stats.all_rays()) / 1e6;
    std::string spp = fmt::format("{} spp", s.samples);
    if (!result.spp.empty()) {
      std::uint64_t total = 0, early = 0;
      for (const std::uint32_t n : result.spp) {
        total += n;
        early += n < s.samples;
      }
      const double pixels = double(result.spp.size());
      spp = fmt::format("a mean {:.2f} of at most {} spp (error target {}, {:.1f}% of pixels stopped early)",
                        double(total) / pixels, s.samples, s.error_target, 100.0 * double(early) / pixels);
    }
    fmt::print(stderr,
               "rendered {}x{} at {} in {:.3f} s ({} threads, {}-px tiles, {} kernels; scene build {:.3f} s): {:.2f} "
               "M rays, {:.2f} Mrays/s, {} NaN and {} Inf samples; wrote {}\n",
               s.width, s.height, spp, result.seconds, result.threads, tile_size, accel::isa_name(rs.geometry().isa()),
               build_s, mrays, result.seconds > 0 ? mrays / result.seconds : 0.0, result.stats.nan_samples,
               result.stats.inf_samples, args.output);
    fmt::print(stderr, "scene features: {} (the tracer is specialised to them)\n",
               render::feature_names(rs.features()));
  }
  return kExitOk;
}

int run_validate(const std::vector<std::string>& files) {
  int code = kExitOk;
  for (const std::string& f : files) {
    const scene::LoadResult r = scene::load_scene_file(f);
    if (r.ok()) {
      print_warnings(r);
      // Meshes add their triangle counts; degenerate (zero-area) triangles are legal but never
      // seen, so a count is worth a look.
      std::size_t meshes = 0, triangles = 0, degenerate = 0;
      for (const scene::Object& o : r.scene->objects) {
        if (o.type != scene::ObjectType::kMesh) continue;
        ++meshes;
        triangles += o.mesh->triangle_count();
        degenerate += o.mesh->degenerate_triangles;
      }
      const std::string mesh_note =
          meshes == 0 ? std::string()
                      : fmt::format(", {} mesh{} of {} triangles, {} degenerate triangle{}", meshes,
                                    meshes == 1 ? "" : "es", triangles, degenerate, degenerate == 1 ? "" : "s");
      fmt::print("{}: OK ({} objects, {} lights{}, digest {})\n", f, r.scene->objects.size(), r.scene->lights.size(),
                 mesh_note, scene::scene_digest(*r.scene));
    } else {
      print_errors(r);
      fmt::print("{}: {} error{}\n", f, r.errors.size(), r.errors.size() == 1 ? "" : "s");
      code = kExitFailed;
    }
  }
  return code;
}

int run_compare(const CompareArgs& args) {
  const auto a = image::read_image(args.a);
  if (!reported(a)) return kExitFailed;
  const auto b = image::read_image(args.b);
  if (!reported(b)) return kExitFailed;
  const auto diff = image::compare_images(*a, *b);
  if (!reported(diff)) return kExitFailed;
  const std::string psnr = std::isinf(diff->psnr_db) ? "inf" : fmt::format("{:.2f}", diff->psnr_db);
  fmt::print("rmse {:.6g}  psnr {} dB  max_abs {:.6g}  ({}x{})\n", diff->rmse, psnr, diff->max_abs, a->width,
             a->height);
  if (args.max_rmse && !(diff->rmse <= *args.max_rmse)) {
    fmt::print(stderr, "rmse {:.6g} is above --max-rmse {:.6g}\n", diff->rmse, *args.max_rmse);
    return kExitFailed;
  }
  return kExitOk;
}

namespace {

// The mesh scene: its OBJ files first (so the scene never names a file that is not there yet),
// then the scene, then a load of what was written, for the digest and as a check.
int generate_mesh(const GenerateArgs& args) {
  const std::filesystem::path output(args.output);
  const std::filesystem::path dir = output.parent_path();
  const std::filesystem::path prefix = std::filesystem::path(args.models_dir) / output.stem();
  const scene::GeneratedMeshScene generated =
      scene::generate_mesh_scene(*args.mesh_triangles, args.seed, prefix.generic_string());
  for (const scene::GeneratedFile& obj : generated.objs) {
    const std::filesystem::path path = dir / obj.path;
    std::error_code ec;
    std::filesystem::create_directories(path.parent_path().empty() ? "." : path.parent_path(), ec);
    if (ec) {
      fmt::print(stderr, "{}: cannot create the directory: {}\n", path.parent_path().string(), ec.message());
      return kExitFailed;
    }
    if (!reported(util::write_file_atomic(path.string(), obj.text))) return kExitFailed;
  }
  if (!reported(util::write_file_atomic(args.output, generated.scene_json))) return kExitFailed;
  const scene::LoadResult loaded = scene::load_scene_file(args.output);
  if (!loaded.ok()) {  // a bug in the generator, not a user error; say so loudly
    print_errors(loaded);
    return kExitFailed;
  }
  fmt::print(stderr, "wrote {} and {} OBJ files ({} objects, {} triangles, digest {})\n", args.output,
             generated.objs.size(), loaded.scene->objects.size(), generated.triangles,
             scene::scene_digest(*loaded.scene));
  return kExitOk;
}

// The canonical text with plain decimals (2.2, not Boost's 2.2E0) for people to read: the same
// doubles (both forms are shortest round-trip), so the same scene and digest.
std::string readable_json(const std::string& canonical) {
  jsonio::Document doc = jsonio::parse_strict(canonical, scene::kMaxJsonDepth, 1);
  return doc.parsed ? jsonio::to_text(doc.value) + "\n" : canonical;
}

}  // namespace

int run_generate(const GenerateArgs& args) {
  if (args.mesh_triangles) return generate_mesh(args);
  const scene::SceneDesc desc = scene::generate_sphere_field(args.count, args.seed);
  if (!reported(util::write_file_atomic(args.output, readable_json(scene::canonical_json(desc))))) return kExitFailed;
  fmt::print(stderr, "wrote {} ({} objects, digest {})\n", args.output, desc.objects.size(), scene::scene_digest(desc));
  return kExitOk;
}

}  // namespace dtraced::cli
