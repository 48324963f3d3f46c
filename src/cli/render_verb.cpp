// The render verb: one image, or a sequence of frames (--frames, a %0Nd output pattern, a GIF),
// on this machine, interruptible and resumable frame by frame.
#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <system_error>
#include <thread>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "cli/overrides_flags.h"
#include "cli/partial_render.h"
#include "cli/verb_report.h"
#include "cli/verbs.h"
#include "image/gif_io.h"
#include "image/image_io.h"
#include "image/sequence.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "scene/tiling.h"
#include "util/file.h"
#include "util/sha256.h"

namespace dtraced::cli {
namespace {

using report::kExitFailed;
using report::kExitOk;
using report::kExitUsage;
using report::reported;

// A one-line progress bar on stderr for the whole render (every frame of a sequence), redrawn in
// place; only used when stderr is a terminal.
class ProgressBar {
 public:
  void draw(std::uint64_t done, std::uint64_t total, std::string_view frame) {
    constexpr int kWidth = 40;
    const double frac = total ? double(done) / double(total) : 1.0;
    const int filled = int(frac * kWidth);
    const int pct = int(frac * 100.0);
    if (finished_ || (pct == last_pct_ && frame == last_frame_)) return;
    last_pct_ = pct;
    last_frame_ = frame;
    fmt::print(stderr, "\r[{:#<{}}{:-<{}}] {:3d}% {}/{} tiles{}", "", filled, "", kWidth - filled, pct, done, total,
               frame);
    if (done == total) {
      fmt::print(stderr, "\n");
      finished_ = true;
    }
    std::fflush(stderr);
  }

 private:
  bool finished_ = false;
  int last_pct_ = -1;
  std::string last_frame_;
};

// The samples each pixel took as an image: raw counts for PFM and EXR; for the 8/16-bit formats,
// which sRGB-encode what they write, the linear value whose encoding is n / samples, so that the
// code values grow in proportion to n. `spp` empty means every pixel took `samples`.
image::ImageRGBf spp_image(std::uint32_t width, std::uint32_t height, std::uint32_t samples,
                           const std::vector<std::uint32_t>& spp, image::ImageFormat format) {
  image::ImageRGBf out(width, height);
  const bool raw = format == image::ImageFormat::kPfm || format == image::ImageFormat::kExr;
  for (std::size_t i = 0; i < std::size_t(width) * height; ++i) {
    const std::uint32_t n = spp.empty() ? samples : spp[i];
    const float v = raw ? float(n) : image::srgb_to_linear(float(n) / float(samples));
    for (int c = 0; c < 3; ++c) out.rgb[i * 3 + c] = v;
  }
  return out;
}

// kExitUsage, with the problem on stderr, when an output (the image, the --spp-map) has an unknown
// format, a directory that is missing or not writable, or would put two frames of `frames` in one
// file; kExitOk otherwise.
int check_outputs(const RenderArgs& args, std::uint32_t frames) {
  const std::pair<const std::string*, const char*> outputs[] = {{&args.output, "--output"},
                                                                {&args.spp_map, "--spp-map"}};
  for (const auto& [path, flag] : outputs) {
    if (path->empty() && path == &args.spp_map) continue;
    const std::optional<image::ImageFormat> format = image::format_from_path(*path);
    if (!format) {
      fmt::print(stderr, "{}: {}: unsupported format (use {})\n", flag, *path, image::extension_list());
      return kExitUsage;
    }
    if (path == &args.spp_map && *format == image::ImageFormat::kGif) {
      fmt::print(stderr, "{}: {}: a sample-count map is not a GIF (use .pfm, .exr, .png or .ppm)\n", flag, *path);
      return kExitUsage;
    }
    if (const util::Status ok = image::check_sequence_path(*path, frames); !ok) {
      fmt::print(stderr, "{}: {}\n", flag, ok.error().to_string());
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

// A frame's partial file: the tiles an earlier, interrupted render kept, and the writer that
// keeps this render's.
struct Partial {
  std::string path;
  std::vector<render::Tile> resumed;
  std::vector<bool> skip;  // by tile index: resumed
  std::optional<PartialWriter> writer;
};

// OUT.partial continued (`resume`) or created; a partial file that is there is never replaced.
// `key` names the scene, settings and tile size (Run::partial_key). kExitOk, or the exit code with
// the problem on stderr.
// `say_fresh`: a --resume that finds no partial file says so (a single image; a sequence's frames
// without one are simply the ones not started).
int open_partial(const std::string& output, bool resume, bool say_fresh, const scene::SceneDesc& desc,
                 std::uint32_t tile_size, const std::string& key, Partial& p) {
  p.path = partial_path(output);
  std::error_code ec;
  if (!std::filesystem::exists(p.path, ec)) {
    if (resume && say_fresh) fmt::print(stderr, "{}: no partial render to resume; rendering from the start\n", p.path);
    util::Result<PartialWriter> made = PartialWriter::create(p.path, key);
    if (!reported(made)) return kExitFailed;
    p.writer.emplace(std::move(made).value());
    return kExitOk;
  }
  if (!resume) {
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
  util::Result<PartialWriter> reopened = PartialWriter::reopen(p.path, read->good_bytes, read->version);
  if (!reported(reopened)) return kExitFailed;
  p.writer.emplace(std::move(reopened).value());
  return kExitOk;
}

// Whether tile `r` has a pixel inside `crop`.
bool overlaps(const scene::TileRect& r, const scene::TileRect& crop) {
  return r.x0 < crop.x0 + crop.width && crop.x0 < r.x0 + r.width && r.y0 < crop.y0 + crop.height &&
         crop.y0 < r.y0 + r.height;
}

// The `crop` pixels of a full-size render: its image and, when adaptive, its spp counts.
void crop_result(const scene::TileRect& crop, std::uint32_t full_width, render::LocalResult& r) {
  image::ImageRGBf out(crop.width, crop.height);
  std::vector<std::uint32_t> spp;
  if (!r.spp.empty()) spp.resize(std::size_t{crop.width} * crop.height);
  for (std::uint32_t y = 0; y < crop.height; ++y) {
    const std::size_t from = std::size_t{crop.y0 + y} * full_width + crop.x0;
    std::copy_n(r.image.rgb.begin() + from * 3, std::size_t{crop.width} * 3,
                out.rgb.begin() + std::size_t{y} * crop.width * 3);
    if (!spp.empty()) std::copy_n(r.spp.begin() + from, crop.width, spp.begin() + std::size_t{y} * crop.width);
  }
  r.image = std::move(out);
  r.spp = std::move(spp);
}

// scene::kDefaultAdaptiveTileSize is the tile side of an adaptive render that names none. Each
// tile also traces the first checkpoint's samples of the one-pixel ring around it (render/tile.h),
// 4 s + 4 pixels for s^2 of its own: 13 % more first-pass rays at 32 px, 6 % at 64. Adaptive
// images are the same bits under any tiling, so this changes only the time: whitted10 at 1280x720
// (-s 16 --min-samples 1 --error-target 0.1) traced 9.24 M rays against 9.60 M; at 1 thread
// 3.4 % less CPU time and 2.8 % less wall time (12 pairs), at 2 threads 4.5 % less CPU time (wall
// within noise, and 4-7 % worse on a machine loaded 5-7 deep on 2 cores, where the fewer, larger
// tiles balance worse). 128 px traced 9.05 M but took no less CPU time than 64 (cache), with 4
// times fewer tiles for the threads to share.

// What every frame of one render shares: the arguments, the interruption flag and the progress.
struct Run {
  const RenderArgs& args;
  std::uint32_t tile_size = 0;
  std::optional<scene::TileRect> crop{};
  std::uint32_t frame_count = 1;
  std::uint64_t tiles_per_frame = 0;
  std::uint64_t tiles_before = 0;  // of the frames already done, for the progress bar
  std::optional<ProgressBar> bar{};
  std::atomic<bool> stop{false};
  std::atomic<int> signal_number{0};
  bool features_printed = false;                    // the scene's features are printed once, with the first frame
  std::optional<render::AnimatedScene> prepared{};  // every frame's render-ready scene comes from here
  double prepare_s = 0;                             // its build time, not yet reported
  double load_s = 0;  // reading the file (for a static scene, into render-ready objects), not yet reported
  // A static scene's objects were streamed into the render-ready scene while it loaded (the
  // description holds none): this is their digest (scene::ObjectsDigest). Empty: the
  // description holds its objects.
  std::string objects_digest{};

  // The key of a frame's partial file: cli::partial_key of the frame, or for a streamed scene the
  // same over its description without objects and the objects' digest.
  std::string partial_key(const scene::SceneDesc& frame) const {
    if (objects_digest.empty()) return cli::partial_key(frame, tile_size);
    return util::sha256_hex(
        fmt::format("{}\nobjects {}\ntile_size {}", scene::scene_digest(frame), objects_digest, tile_size));
  }
};

// Renders one frame (`desc` is that frame's static scene) to `image_path` (and `spp_path`, if
// not empty), through its partial file. kExitOk, 128 + the signal when interrupted (the finished
// tiles kept), or another exit code with the problem on stderr.
int render_frame(Run& run, const scene::SceneDesc& desc, const std::string& image_path, const std::string& spp_path) {
  const RenderArgs& args = run.args;
  const scene::RenderSettings& s = desc.render;
  Partial partial;
  if (const int code = open_partial(image_path, args.resume, run.frame_count == 1, desc, run.tile_size,
                                    run.partial_key(desc), partial);
      code != kExitOk) {
    return code;
  }
  // A static scene was built once (prepare); an animated one builds only this frame's moving
  // layer here, the static layer shared.
  const auto build_start = std::chrono::steady_clock::now();
  const std::shared_ptr<const render::RenderScene> scene_of_frame = run.prepared->frame(s.frame);
  const render::RenderScene& rs = *scene_of_frame;
  const double build_s =
      run.prepare_s + std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
  const double load_s = std::exchange(run.load_s, 0.0);
  run.prepare_s = 0;  // counted once, with the first frame rendered

  render::LocalOptions opts;
  opts.threads = args.threads;
  opts.tile_size = run.tile_size;
  const std::string frame_label =
      run.frame_count > 1 ? fmt::format(", frame {} ({} frames)", s.frame, run.frame_count) : std::string();
  if (run.bar) {
    opts.progress = [&run, &frame_label](std::size_t done, std::size_t) {
      run.bar->draw(run.tiles_before + done, run.tiles_per_frame * run.frame_count, frame_label);
    };
  }
  const scene::TileGrid grid(s, run.tile_size);
  opts.skip = partial.skip;
  if (run.crop) {  // tiles without a pixel in the crop are not rendered (they count as done)
    opts.skip.resize(grid.count(), false);
    for (std::uint64_t i = 0; i < grid.count(); ++i) opts.skip[i] = opts.skip[i] || !overlaps(grid.rect(i), *run.crop);
  }
  // Every finished tile goes to the partial file, so that an interrupted render keeps it.
  std::optional<util::Error> partial_failed;  // only tile_done touches it (calls are serialised)
  opts.tile_done = [&partial, &partial_failed](std::size_t index, const render::Tile& t) {
    if (partial_failed) return;
    if (util::Status kept = partial.writer->append(static_cast<std::uint32_t>(index), t); !kept) {
      partial_failed = kept.error();
      fmt::print(stderr, "warning: {}; the render goes on, but an interruption would lose its tiles\n",
                 kept.error().to_string());
    }
  };
  opts.stop_requested = [&run] { return run.stop.load(); };
  render::LocalResult result = render::render_local(rs, s, opts);
  if (!result.complete) {
    const util::Status synced = partial.writer->sync();
    if (!synced || partial_failed) {
      fmt::print(stderr, "interrupted: {}: the partial file is incomplete (see above)\n",
                 synced ? partial.path : synced.error().to_string());
      return 128 + run.signal_number.load();
    }
    fmt::print(stderr, "interrupted: {} of {} tiles are kept in {}; the same command with --resume continues\n",
               partial.resumed.size() + result.tiles_rendered, grid.count(), partial.path);
    return 128 + run.signal_number.load();
  }
  for (const render::Tile& t : partial.resumed) render::paste_tile(t, s.width, result);
  if (run.crop) crop_result(*run.crop, s.width, result);

  image::WriteOptions wopts;
  wopts.png_bit_depth = static_cast<int>(scene::png_bit_depth_or_default(args.overrides));
  wopts.display = s.display;
  wopts.exr_float = args.exr_float;
  std::vector<float> spp_channel;  // an adaptive render's counts travel with an EXR image
  if (!result.spp.empty() && image::format_from_path(image_path) == image::ImageFormat::kExr) {
    spp_channel.assign(result.spp.begin(), result.spp.end());
    wopts.sample_counts = spp_channel;
  }
  if (!reported(image::write_image(image_path, result.image, wopts))) return kExitFailed;
  if (!spp_path.empty()) {
    image::WriteOptions map_opts;
    map_opts.png_bit_depth = 16;
    const image::ImageRGBf map =
        spp_image(result.image.width, result.image.height, s.samples, result.spp, *image::format_from_path(spp_path));
    if (!reported(image::write_image(spp_path, map, map_opts))) return kExitFailed;
  }
  partial.writer.reset();
  std::error_code removed;
  std::filesystem::remove(partial.path, removed);  // the image holds it all now
  if (args.quiet) return kExitOk;
  if (!partial.resumed.empty()) fmt::print(stderr, "resumed {} tiles from {}\n", partial.resumed.size(), partial.path);
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
             "rendered {}x{} at {} in {:.3f} s ({} threads, {}-px tiles, {} kernels; scene load {:.3f} s, build "
             "{:.3f} s): {:.2f} M rays, {:.2f} Mrays/s, {} NaN and {} Inf samples; wrote {}\n",
             result.image.width, result.image.height, spp, result.seconds, result.threads, run.tile_size,
             accel::isa_name(rs.geometry().isa()), load_s, build_s, mrays,
             result.seconds > 0 ? mrays / result.seconds : 0.0, result.stats.nan_samples, result.stats.inf_samples,
             image_path);
  if (!run.features_printed) {
    run.features_printed = true;
    fmt::print(stderr, "scene features: {} (the tracer is specialised to them)\n",
               render::feature_names(rs.features()));
  }
  return kExitOk;
}

// Where the frames of a GIF are kept until it is written: linear PFM files in OUT.frames/, which
// a --resume finds like any sequence's frames.
std::string gif_frames_dir(const std::string& gif) { return gif + ".frames"; }

// Encodes the GIF from its frames' PFM files, one frame in memory at a time, then removes them.
int write_gif(const RenderArgs& args, const scene::RenderSettings& s, const std::vector<std::string>& frame_files) {
  image::GifOptions gopts;
  gopts.fps = s.fps;
  gopts.dither = args.gif_dither;
  gopts.display = s.display;
  std::optional<image::GifEncoder> gif;
  for (const std::string& file : frame_files) {
    util::Result<image::ImageRGBf> frame = image::read_image(file);
    if (!reported(frame)) return kExitFailed;
    if (!gif) {
      util::Result<image::GifEncoder> made = image::GifEncoder::create(frame->width, frame->height, gopts);
      if (!reported(made)) return kExitFailed;
      gif.emplace(std::move(made).value());
    }
    if (!reported(gif->add_frame(*frame))) return kExitFailed;
  }
  util::Result<std::vector<std::uint8_t>> bytes = gif->finish();
  if (!reported(bytes)) return kExitFailed;
  const std::string_view view(reinterpret_cast<const char*>(bytes->data()), bytes->size());
  if (!reported(util::write_file_atomic(args.output, view))) return kExitFailed;
  std::error_code ec;
  std::filesystem::remove_all(gif_frames_dir(args.output), ec);
  if (!args.quiet) {
    fmt::print(stderr, "wrote {}: {} frames at {} fps, {} bytes\n", args.output, frame_files.size(), s.fps,
               bytes->size());
  }
  return kExitOk;
}

}  // namespace

int run_render(const RenderArgs& args) {
  // A static scene's objects go straight into the render-ready scene as they are read (the
  // description never holds them: a few times less memory for a large scene); an animated one is
  // loaded again whole, since its frames are built from the description.
  std::optional<render::RenderSceneBuilder> builder(std::in_place);
  std::optional<scene::ObjectsDigest> objects(std::in_place, &*builder);
  scene::LoadOptions streamed;
  streamed.object_sink = &*objects;
  const auto load_start = std::chrono::steady_clock::now();
  scene::LoadResult loaded = scene::load_scene_file(args.scene, streamed);
  if (loaded.ok() && scene::is_animated(*loaded.scene)) {
    objects.reset();
    builder.reset();
    loaded = scene::load_scene_file(args.scene);
  }
  const double load_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - load_start).count();
  if (!loaded.ok()) {
    report::print_errors(loaded);
    return kExitFailed;
  }
  report::print_warnings(loaded);
  scene::SceneDesc& desc = *loaded.scene;
  desc.render = scene::apply(args.overrides, desc.render);
  const scene::FrameRange range = scene::frame_range(desc.render);
  // The outputs first: a render may take hours, and a typo in a path should not cost them.
  if (const int usage = check_outputs(args, range.count()); usage != kExitOk) return usage;
  Run run{.args = args};
  run.load_s = load_s;
  run.tile_size = !args.overrides.tile_size && desc.render.error_target > 0
                      ? scene::kDefaultAdaptiveTileSize
                      : scene::tile_size_or_default(args.overrides);
  if (objects) run.objects_digest = objects->hex();
  run.crop = args.overrides.crop;
  if (run.crop) {
    if (const util::Status inside = check_crop(*run.crop, desc.render.width, desc.render.height); !inside) {
      fmt::print(stderr, "{}\n", inside.error().to_string());
      return kExitUsage;
    }
  }
  run.frame_count = range.count();
  run.tiles_per_frame = scene::TileGrid(desc.render, run.tile_size).count();
  if (!args.quiet && ::isatty(STDERR_FILENO)) run.bar.emplace();

  const bool gif = image::format_from_path(args.output) == image::ImageFormat::kGif;
  util::Result<image::SequencePattern> pattern = image::parse_sequence_pattern(args.output);
  if (!reported(pattern)) return kExitUsage;
  std::optional<image::SequencePattern> spp_pattern;
  if (!args.spp_map.empty()) {
    util::Result<image::SequencePattern> p = image::parse_sequence_pattern(args.spp_map);
    if (!reported(p)) return kExitUsage;
    spp_pattern = *p;
  }
  if (gif) {
    std::error_code ec;
    const std::string dir = gif_frames_dir(args.output);
    if (std::filesystem::exists(dir, ec) && !args.resume) {
      fmt::print(stderr, "{}: the frames of an interrupted render are there: --resume continues it\n", dir);
      return kExitUsage;
    }
    std::filesystem::create_directories(dir, ec);
    if (ec) {
      fmt::print(stderr, "{}: cannot create the directory for the GIF's frames: {}\n", dir, ec.message());
      return kExitFailed;
    }
  }

  // Without --resume, a partial file of any frame is refused now, not after the frames before it.
  if (!gif && !args.resume && range.count() > 1) {
    for (std::uint32_t i = 0; i < range.count(); ++i) {
      const std::string partial = partial_path(image::frame_path(*pattern, range.at(i)));
      std::error_code ec;
      if (std::filesystem::exists(partial, ec)) {
        fmt::print(stderr,
                   "{}: a partial render of this output is there: --resume continues it; delete it to start "
                   "over\n",
                   partial);
        return kExitUsage;
      }
    }
  }

  const auto prepare_start = std::chrono::steady_clock::now();
  if (builder) {
    objects.reset();
    run.prepared.emplace(render::AnimatedScene::still(std::move(*builder).build(desc, args.isa, args.threads)));
    builder.reset();
  } else {
    run.prepared.emplace(render::AnimatedScene::prepare(desc, args.isa, args.threads));
  }
  run.prepare_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - prepare_start).count();

  std::vector<std::string> gif_frames;
  std::uint32_t skipped = 0;
  const StopOnSignals on_signals(run.stop, run.signal_number);
  for (std::uint32_t i = 0; i < range.count(); ++i) {
    const std::uint32_t frame = range.at(i);
    const std::string image_path = gif ? fmt::format("{}/frame-{:06d}.pfm", gif_frames_dir(args.output), frame)
                                       : image::frame_path(*pattern, frame);
    if (gif) gif_frames.push_back(image_path);
    const std::string spp_path = spp_pattern ? image::frame_path(*spp_pattern, frame) : std::string();
    run.tiles_before = std::uint64_t{i} * run.tiles_per_frame;
    std::error_code ec;
    // A frame is written in one rename once complete, so a file that is there is a whole frame.
    if (range.count() > 1 && args.resume && std::filesystem::exists(image_path, ec) &&
        !std::filesystem::exists(partial_path(image_path), ec)) {
      ++skipped;
      continue;
    }
    if (run.stop.load()) return 128 + run.signal_number.load();
    const int code = render_frame(run, scene::scene_at_frame(desc, frame), image_path, spp_path);
    if (code != kExitOk) {
      if (range.count() > 1 && code > 128) {
        fmt::print(stderr, "{} of {} frames are complete; the same command with --resume continues the sequence\n", i,
                   range.count());
      }
      return code;
    }
  }
  if (skipped > 0) fmt::print(stderr, "resumed: {} frames were already complete\n", skipped);
  if (run.bar) run.bar->draw(run.tiles_per_frame * run.frame_count, run.tiles_per_frame * run.frame_count, "");
  if (gif) return write_gif(args, desc.render, gif_frames);
  return kExitOk;
}

}  // namespace dtraced::cli
