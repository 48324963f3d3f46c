// dtraced-bench-scale: how a scene of many spheres scales (issue 16, "Scale"): load (JSON file to
// render-ready shapes), BVH build on 1 and N threads, a 1 spp render, peak RSS and bytes per
// sphere, and Embree's build time for the same spheres when the build found Embree 3.
// A benchmark, not a test: it prints figures and marks the targets MET or MISSED.
//
// Two modes, so that the process that measures memory holds nothing but the pipeline:
//   dtraced-bench-scale --write N FILE   writes scene::generate_sphere_field(N, 1) as canonical JSON
//   dtraced-bench-scale FILE             loads FILE, builds, renders, prints one line of figures
//   dtraced-bench-scale FILE --load-only only parses FILE (time and peak RSS), for profiles
//   dtraced-bench-scale FILE --cache-dir DIR   a worker's preparation of FILE (canonical JSON, as
//                                        --write writes it) from its JSON, which writes the binary
//                                        scene cache in DIR, then from that cache: load and build
// Peak RSS is the largest of the peaks of the parse, the build and the render (VmHWM, reset
// between them, each printed to stderr), read before the extra timing builds.
// The objects are loaded straight into render-ready arrays (render::RenderSceneBuilder).
// Times are wall time (steady_clock); the build figures are the median of --runs builds, each
// beside the CPU time of the build's threads.
//
// Exit codes: 0 done; 1 the scene could not be written, loaded or built; 2 usage error.
// Threading: the main thread drives; Geometry::build and render_local start their own threads.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "util/file.h"
#include "util/sha256.h"
#include "worker/scene_cache.h"

#ifdef DTRACED_BENCH_EMBREE
#include "bench/embree_tracer.h"
#endif

namespace dtraced::bench {
namespace {

using Clock = std::chrono::steady_clock;

double since(Clock::time_point start) { return std::chrono::duration<double>(Clock::now() - start).count(); }

double peak_rss_bytes() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_maxrss) * 1024.0;  // kilobytes on Linux
}

// The peak RSS since the last reset_peak_rss() (VmHWM), in bytes; 0 where /proc has none.
double phase_peak_bytes() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmHWM:", 0) == 0) return std::stod(line.substr(6)) * 1024.0;  // "VmHWM:  123 kB"
  }
  return 0.0;
}

// Starts a new phase of phase_peak_bytes (Linux: "5" to clear_refs resets VmHWM to the current
// RSS). getrusage's ru_maxrss, the figure the targets use, is not reset.
void reset_peak_rss() {
  std::ofstream clear("/proc/self/clear_refs");
  clear << "5";
}

// CPU time of the process (every thread), user and system: on a shared machine the wall times
// above wait for the CPU, while this only counts the work.
double cpu_seconds() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return double(u.ru_utime.tv_sec + u.ru_stime.tv_sec) + 1e-6 * double(u.ru_utime.tv_usec + u.ru_stime.tv_usec);
}

// Threads of this process now (entries of /proc/self/task); 0 where /proc has none.
std::size_t thread_count() {
  std::error_code ec;
  std::size_t count = 0;
  for (std::filesystem::directory_iterator it("/proc/self/task", ec), end; !ec && it != end; it.increment(ec)) ++count;
  return count;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

const char* verdict(bool met) { return met ? "MET" : "MISSED"; }

int write_scene(std::uint32_t count, const std::string& path) {
  const auto start = Clock::now();
  const scene::SceneDesc desc = scene::generate_sphere_field(count, 1);
  const auto written = util::write_file_atomic(path, scene::canonical_json(desc));
  if (!written) {
    fmt::print(stderr, "dtraced-bench-scale: {}\n", written.error().to_string());
    return 1;
  }
  fmt::print(stderr, "wrote {} ({} spheres) in {:.2f} s\n", path, count, since(start));
  return 0;
}

struct Figures {
  std::size_t spheres = 0;
  double load_s = 0, build1_s = 0, buildn_s = 0, render_s = 0, rss = 0;
  double build1_cpu = 0, buildn_cpu = 0;  // CPU time of the builds' threads, median
  double embree1_s = -1, embreen_s = -1;
};

int measure(const std::string& path, std::uint32_t threads, int runs, std::uint32_t width, std::uint32_t height,
            bool load_only, bool threaded_load) {
  Figures f;
  const accel::Isa isa = accel::best_isa();
  double pipeline_build_s = 0.0;
  {
    // The pipeline as `dtraced render` runs it: load, build, render.
    auto start = Clock::now();
    const double cpu_start = cpu_seconds();
    // The objects go straight into the render-ready arrays (render::RenderSceneBuilder): the
    // scene's description objects are never held.
    render::RenderSceneBuilder builder;
    scene::LoadOptions load_options;
    load_options.object_sink = &builder;
    // The objects read on a second thread while the first parses (scene::kParallelLoadBytes says
    // why that is not the default): for comparing the two on another machine.
    if (threaded_load) load_options.parallel_min_bytes = 0;
    reset_peak_rss();
    scene::LoadResult loaded = scene::load_scene_file(path, load_options);
    if (!loaded.ok()) {
      fmt::print(stderr, "{}", scene::format_errors(loaded.errors));
      return 1;
    }
    if (scene::is_animated(*loaded.scene)) {
      fmt::print(stderr, "dtraced-bench-scale: {} is animated; give it a static scene\n", path);
      return 1;
    }
    const double parse_s = since(start);
    const double parse_cpu = cpu_seconds() - cpu_start;
    const double parse_rss = phase_peak_bytes();
    if (load_only) {
      fmt::print("parse {:.3f} s (cpu {:.3f} s)  peak RSS {:.1f} MiB  {} objects\n", parse_s, parse_cpu,
                 peak_rss_bytes() / (1 << 20), builder.object_count());
      return 0;
    }
    reset_peak_rss();
    start = Clock::now();
    const render::RenderScene rs = std::move(builder).build(*loaded.scene, isa, threads);
    const double scene_s = since(start);
    const double build_rss = phase_peak_bytes();
    for (const accel::Shape& s : rs.geometry().fixed()->geometry.shapes())
      f.spheres += s.type == accel::ShapeType::kSphere;
    const accel::BuildStats& st = rs.geometry().fixed()->geometry.stats();
    pipeline_build_s = st.seconds + st.wide_seconds;
    f.load_s = parse_s + (scene_s - pipeline_build_s);
    scene::RenderSettings settings = loaded.scene->render;
    settings.width = width;
    settings.height = height;
    settings.samples = 1;
    settings.error_target = 0.0;
    render::LocalOptions options;
    options.threads = threads;
    reset_peak_rss();
    const render::LocalResult result = render::render_local(rs, settings, options);
    f.render_s = result.seconds;
    const double render_rss = phase_peak_bytes();
    // The peak over the phases (reset_peak_rss resets ru_maxrss too); without /proc, ru_maxrss.
    f.rss = std::max({parse_rss, build_rss, render_rss});
    if (f.rss == 0.0) f.rss = peak_rss_bytes();
    fmt::print(stderr,
               "load {:.3f} s (parse {:.3f}, cpu {:.3f}), pipeline build {:.3f} s on {} threads, render {:.3f} s; peak "
               "RSS of the parse {:.1f} MiB, of the build {:.1f} MiB, of the render {:.1f} MiB\n",
               f.load_s, parse_s, parse_cpu, pipeline_build_s, threads, f.render_s, parse_rss / (1 << 20),
               build_rss / (1 << 20), render_rss / (1 << 20));

    // The build alone, on 1 thread and on `threads`, from the same shapes.
    const std::vector<accel::Shape>& shapes = rs.geometry().fixed()->geometry.shapes();
    // The CPU time beside the wall time: on a shared machine the wall time waits for a core, so
    // two builds are best compared by their CPU. It is the CPU of the build's threads alone: the
    // shapes are copied before the call and the tree freed after it, and the build's own threads
    // are joined before it returns (Linux then counts their time in the process's), so with no
    // other thread in the process (checked) the process's CPU over the call is theirs.
    const std::size_t idle_threads = thread_count();
    if (idle_threads > 1) {
      fmt::print(stderr, "  note: {} threads in the process before the builds; build cpu counts them too\n",
                 idle_threads);
    }
    std::vector<double> one, many, one_cpu, many_cpu;
    for (int i = 0; i < runs; ++i) {
      for (const std::uint32_t t : {1u, threads}) {
        std::vector<accel::Shape> copy = shapes;
        const double cpu_before = cpu_seconds();
        const accel::Geometry g = accel::Geometry::build(std::move(copy), isa, t);
        const double cpu = cpu_seconds() - cpu_before;
        (t == 1 ? one : many).push_back(g.stats().seconds + g.stats().wide_seconds);
        (t == 1 ? one_cpu : many_cpu).push_back(cpu);
        fmt::print(
            stderr,
            "  build on {} thread{}: binary {:.3f} s + wide {:.3f} s, cpu {:.3f} s ({} nodes, {} leaves, {} wide, "
            "tree {:016x})\n",
            t, t == 1 ? "" : "s", g.stats().seconds, g.stats().wide_seconds, cpu, g.stats().nodes, g.stats().leaves,
            g.stats().wide_nodes, g.stats().tree_hash);
      }
    }
    f.build1_s = median(one);
    f.buildn_s = median(many);
    f.build1_cpu = median(one_cpu);
    f.buildn_cpu = median(many_cpu);
#ifdef DTRACED_BENCH_EMBREE
    std::vector<double> e1, en;
    for (int i = 0; i < runs; ++i) {
      for (const std::uint32_t t : {1u, threads}) {
        auto tracer = EmbreeTracer::build(shapes, EmbreeQuality::kMedium, t);
        if (!tracer) {
          fmt::print(stderr, "embree: {}\n", tracer.error().to_string());
          break;
        }
        (t == 1 ? e1 : en).push_back((*tracer)->build_seconds());
      }
    }
    if (!e1.empty()) f.embree1_s = median(e1);
    if (!en.empty()) f.embreen_s = median(en);
#endif
  }

  const double per_sphere = f.spheres ? f.rss / double(f.spheres) : 0.0;
  fmt::print(
      "spheres {:>9}  load {:7.3f} s  build 1t {:6.3f} s  {}t {:6.3f} s  render {:6.3f} s  peak RSS {:7.1f} MiB"
      "  {:6.1f} B/sphere",
      f.spheres, f.load_s, f.build1_s, threads, f.buildn_s, f.render_s, f.rss / (1 << 20), per_sphere);
  fmt::print("  build cpu 1t {:6.3f} s  {}t {:6.3f} s", f.build1_cpu, threads, f.buildn_cpu);
  if (f.embree1_s >= 0) fmt::print("  embree 1t {:6.3f} s  {}t {:6.3f} s", f.embree1_s, threads, f.embreen_s);
  fmt::print("\n");
  if (f.spheres >= 1'000'000) {
    fmt::print("  target load <= 1 s: {}; bytes/sphere <= 150: {}", verdict(f.load_s <= 1.0),
               verdict(per_sphere <= 150));
    if (f.embree1_s >= 0) {
      fmt::print("; build <= embree (1t): {}; ({}t): {}", verdict(f.build1_s <= f.embree1_s), threads,
                 verdict(f.buildn_s <= f.embreen_s));
    }
    fmt::print("\n");
  }
  return 0;
}

// worker::prepare_scene of a canonical scene file twice: from its JSON (writing the cache file in
// `dir`), then from the cache file. The load is the preparation less the BVH build.
int measure_cache(const std::string& path, const std::string& dir, std::uint32_t threads) {
  util::Result<std::string> text = util::read_file_limited(path, scene::kMaxSceneFileBytes);
  if (!text) {
    fmt::print(stderr, "dtraced-bench-scale: {}\n", text.error().to_string());
    return 1;
  }
  const std::string digest = util::sha256_hex(*text);  // the file is canonical: its digest
  std::filesystem::remove(worker::cached_scene_path(dir, digest));
  double load[2] = {0, 0}, cpu[2] = {0, 0};
  for (const int pass : {0, 1}) {
    const auto start = Clock::now();
    const double cpu_start = cpu_seconds();
    const worker::PreparedScene prepared = worker::prepare_scene(*text, digest, accel::best_isa(), threads, dir);
    const double all_s = since(start);
    cpu[pass] = cpu_seconds() - cpu_start;
    if (!prepared.scene || !prepared.warning.empty()) {
      fmt::print(stderr, "dtraced-bench-scale: {}{}\n", prepared.error, prepared.warning);
      return 1;
    }
    const accel::BuildStats& st = prepared.scene->frame(0)->geometry().fixed()->geometry.stats();
    load[pass] = all_s - (st.seconds + st.wide_seconds);
    fmt::print(stderr, "{}: prepare {:.3f} s (cpu {:.3f} s), of which the BVH build {:.3f} s\n",
               pass == 0 ? "from JSON (and writing the cache)" : "from the cache file", all_s, cpu[pass],
               st.seconds + st.wide_seconds);
  }
  fmt::print(
      "worker scene load, {}: from JSON {:.3f} s (prepare cpu {:.3f} s), from the cache {:.3f} s (prepare cpu "
      "{:.3f} s): {:.1f}x\n",
      path, load[0], cpu[0], load[1], cpu[1], load[1] > 0 ? load[0] / load[1] : 0.0);
  return 0;
}

}  // namespace
}  // namespace dtraced::bench

int main(int argc, char** argv) {
  CLI::App app("dtraced-bench-scale: load, build, render and memory of a large sphere scene");
  std::string file;
  std::uint32_t write_count = 0;
  std::uint32_t threads = 2;
  int runs = 3;
  std::uint32_t width = 640, height = 360;
  app.add_option("file", file, "Scene file to measure (or to write with --write)")->required();
  app.add_option("--write", write_count, "Write a scene of this many spheres to FILE instead")
      ->check(CLI::Range(1u, 9'999'999u));  // with the plane, the loader's 10M objects
  app.add_option("--threads", threads, "Threads of the parallel build and of the render")->check(CLI::Range(1u, 256u));
  app.add_option("--runs", runs, "Timed builds per thread count (median)")->check(CLI::Range(1, 100));
  app.add_option("--width", width, "Render width")->check(CLI::Range(1u, 8192u));
  app.add_option("--height", height, "Render height")->check(CLI::Range(1u, 8192u));
  bool load_only = false;
  app.add_flag("--load-only", load_only, "Only parse FILE: its time and peak RSS (for profiling the load)");
  bool threaded_load = false;
  app.add_flag("--threaded-load", threaded_load, "Read FILE's objects on a second thread while the first parses");
  std::string cache_dir;
  app.add_option("--cache-dir", cache_dir,
                 "Measure a worker's load of FILE from its JSON and then from the binary scene cache it writes here");
  CLI11_PARSE(app, argc, argv);
  if (write_count > 0) return dtraced::bench::write_scene(write_count, file);
  if (!cache_dir.empty()) return dtraced::bench::measure_cache(file, cache_dir, threads);
  return dtraced::bench::measure(file, threads, runs, width, height, load_only, threaded_load);
}
