// dtraced-bench-scale: how a scene of many spheres scales (issue 16, "Scale"): load (JSON file to
// render-ready shapes), BVH build on 1 and N threads, a 1 spp render, peak RSS and bytes per
// sphere, and Embree's build time for the same spheres when the build found Embree 3.
// A benchmark, not a test: it prints figures and marks the targets MET or MISSED.
//
// Two modes, so that the process that measures memory holds nothing but the pipeline:
//   dtraced-bench-scale --write N FILE   writes scene::generate_sphere_field(N, 1) as canonical JSON
//   dtraced-bench-scale FILE             loads FILE, builds, renders, prints its figures
//   dtraced-bench-scale FILE --load-only only parses FILE (time and peak RSS), for profiles
//   dtraced-bench-scale FILE --cache-dir DIR   a worker's preparation of FILE (canonical JSON, as
//                                        --write writes it) from its JSON, which writes the binary
//                                        scene cache in DIR, then from that cache: load and build
// Peak RSS is the largest of the peaks of the parse, the build and the render (VmHWM, reset
// between them, each printed to stderr), read before the extra timing builds.
// The objects are loaded straight into render-ready arrays (render::RenderSceneBuilder).
//
// The build is timed two ways, ours and Embree's alike, each the median of its runs:
//  - fresh processes (what a render sees): the program runs itself again (the hidden
//    --fresh-build ours|embree) once per build; the child loads FILE as the pipeline does and
//    builds once, the first build of its process, and prints one line the parent reads. Ours is
//    RenderSceneBuilder::build, as `dtraced render` calls it; Embree's builds the same shapes.
//    --fresh-runs sets the count (default --runs; 0 leaves them out). Each run builds on 1 thread,
//    then N, ours and Embree's in an order that alternates between runs, so both see the
//    machine's same minutes.
//  - repeated builds in one process (--runs of each, after the render): each build inherits the
//    heap the build before left, so glibc's allocator state (which freed pages the next build
//    reuses without faults) moves them; they are printed beside figures measured that way.
// Times are wall time (steady_clock), each beside the CPU time of the build's threads (ours).
//
// The scene must be one tree: a static scene that RenderSceneBuilder splits into an opaque and a
// transparent layer (a compact glass part among opaque shapes) is refused, as the figures are
// those of one Geometry.
//
// Exit codes: 0 done; 1 the scene could not be written, loaded or built, or is split (or a child
// failed); 2 usage error.
// Threading: the main thread drives; Geometry::build and render_local start their own threads.
#include <spawn.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>
#include <span>
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

// The load average over 1, 5 and 15 minutes as /proc/loadavg gives it; "?" where it has none.
std::string load_average() {
  std::ifstream in("/proc/loadavg");
  std::string one, five, fifteen;
  if (!(in >> one >> five >> fifteen)) return "?";
  return one + " " + five + " " + fifteen;
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
  double load_s = 0, render_s = 0, rss = 0;
  // Medians of the repeated builds in one process, and of the builds in fresh processes; -1 where
  // none ran. CPU: of ours, the build's threads.
  double build1_s = 0, buildn_s = 0, build1_cpu = 0, buildn_cpu = 0;
  double embree1_s = -1, embreen_s = -1;
  double fresh1_s = -1, freshn_s = -1, fresh1_cpu = -1, freshn_cpu = -1, fresh_load_s = -1;
  double fresh_embree1_s = -1, fresh_embreen_s = -1;
  int fresh_runs = 0;
};

// Loads `path` as `dtraced render` does: its objects go straight into `builder`'s render-ready
// arrays, so the scene's description objects are never held. Prints why on failure (including an
// animated scene) and returns nothing.
std::optional<scene::LoadResult> load_into(const std::string& path, render::RenderSceneBuilder& builder,
                                           bool threaded_load) {
  scene::LoadOptions load_options;
  load_options.object_sink = &builder;
  // The objects read on a second thread while the first parses (scene::kParallelLoadBytes says
  // why that is not the default): for comparing the two on another machine.
  if (threaded_load) load_options.parallel_min_bytes = 0;
  scene::LoadResult loaded = scene::load_scene_file(path, load_options);
  if (!loaded.ok()) {
    fmt::print(stderr, "{}", scene::format_errors(loaded.errors));
    return std::nullopt;
  }
  if (scene::is_animated(*loaded.scene)) {
    fmt::print(stderr, "dtraced-bench-scale: {} is animated; give it a static scene\n", path);
    return std::nullopt;
  }
  return loaded;
}

// The scene's one tree, or null (and why, on stderr) where RenderSceneBuilder split it into an
// opaque and a transparent layer: its figures would then be the opaque layer's alone.
const accel::Geometry* one_tree(const render::RenderScene& rs, const std::string& path) {
  if (rs.geometry().transparent() != nullptr) {
    fmt::print(stderr,
               "dtraced-bench-scale: {}: the scene splits into an opaque and a transparent layer (a compact glass "
               "part); this benchmark measures one tree: give it a scene without one\n",
               path);
    return nullptr;
  }
  return &rs.geometry().fixed()->geometry;
}

// One fresh process's build, as its --fresh-build line gives it.
struct FreshBuild {
  double seconds = 0, cpu = -1, load_s = -1;
  std::uint64_t tree_hash = 0;
};

// --fresh-build: loads `path` as the pipeline does and builds once, the first build of this
// process, as a render's is: ours through RenderSceneBuilder::build (what `dtraced render`
// calls), or Embree's of the same shapes (copied out of the builder before the clock; Embree's
// figure is rtcCommitScene alone). Prints one line on stdout for the parent:
//   fresh ENGINE THREADS SECONDS CPU TREE_HASH LOAD
// CPU (ours only, else -1) is the process's over the call, which also joins the builder's
// page-mapping thread and puts the camera and lights around the tree (the load's threads are
// joined before it).
// LOAD is the load's time as the main figures count it (ours only, else -1).
int fresh_build(const std::string& path, const std::string& engine, std::uint32_t threads, bool threaded_load) {
  auto start = Clock::now();
  render::RenderSceneBuilder builder;
  std::optional<scene::LoadResult> loaded = load_into(path, builder, threaded_load);
  if (!loaded) return 1;
  const double parse_s = since(start);
  FreshBuild b;
  if (engine == "ours") {
    start = Clock::now();
    const double cpu_before = cpu_seconds();
    const render::RenderScene rs = std::move(builder).build(*loaded->scene, accel::best_isa(), threads);
    b.cpu = cpu_seconds() - cpu_before;
    const double scene_s = since(start);
    const accel::Geometry* tree = one_tree(rs, path);
    if (tree == nullptr) return 1;
    const accel::BuildStats& st = tree->stats();
    b.seconds = st.seconds + st.wide_seconds;
    b.tree_hash = st.tree_hash;
    b.load_s = parse_s + (scene_s - b.seconds);
  } else {
#ifdef DTRACED_BENCH_EMBREE
    const std::span<const accel::Shape> parts = builder.parts().shapes;
    const std::vector<accel::Shape> shapes(parts.begin(), parts.end());
    auto tracer = EmbreeTracer::build(shapes, EmbreeQuality::kMedium, threads);
    if (!tracer) {
      fmt::print(stderr, "embree: {}\n", tracer.error().to_string());
      return 1;
    }
    b.seconds = (*tracer)->build_seconds();
#else
    fmt::print(stderr, "dtraced-bench-scale: built without Embree\n");
    return 1;
#endif
  }
  fmt::print("fresh {} {} {:.6f} {:.6f} {:016x} {:.6f}\n", engine, threads, b.seconds, b.cpu, b.tree_hash, b.load_s);
  return 0;
}

// Runs this program again as `--fresh-build engine --threads threads` on `path` and reads the
// line it prints; nothing (and a message) when it fails.
std::optional<FreshBuild> run_fresh(const std::string& path, const std::string& engine, std::uint32_t threads,
                                    bool threaded_load) {
  const std::string threads_text = std::to_string(threads);
  std::vector<std::string> args = {"dtraced-bench-scale", path, "--fresh-build", engine, "--threads", threads_text};
  if (threaded_load) args.emplace_back("--threaded-load");
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  int fds[2];
  if (::pipe(fds) != 0) {
    fmt::print(stderr, "dtraced-bench-scale: pipe: {}\n", std::strerror(errno));
    return std::nullopt;
  }
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, fds[1], STDOUT_FILENO);
  posix_spawn_file_actions_addclose(&actions, fds[0]);
  posix_spawn_file_actions_addclose(&actions, fds[1]);
  pid_t pid = 0;
  const int rc = ::posix_spawn(&pid, "/proc/self/exe", &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  ::close(fds[1]);
  // The child prints one short line; more than this is kept only up to the limit (and then the
  // line does not parse).
  constexpr std::size_t kMaxChildOutput = 4096;
  std::string out;
  if (rc == 0) {
    char buf[512];
    for (ssize_t n; (n = ::read(fds[0], buf, sizeof buf)) != 0;) {
      if (n > 0)
        out.append(buf, std::min(std::size_t(n), kMaxChildOutput - std::min(out.size(), kMaxChildOutput)));
      else if (errno != EINTR)
        break;
    }
  }
  ::close(fds[0]);
  if (rc != 0) {
    fmt::print(stderr, "dtraced-bench-scale: cannot run itself again: {}\n", std::strerror(rc));
    return std::nullopt;
  }
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  FreshBuild b;
  char name[16] = {};
  unsigned t = 0;
  unsigned long long hash = 0;
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0 ||
      std::sscanf(out.c_str(), "fresh %15s %u %lf %lf %llx %lf", name, &t, &b.seconds, &b.cpu, &hash, &b.load_s) != 6 ||
      engine != name || t != threads) {
    const std::string how = WIFEXITED(status)     ? fmt::format("exit code {}", WEXITSTATUS(status))
                            : WIFSIGNALED(status) ? fmt::format("signal {}", WTERMSIG(status))
                                                  : fmt::format("wait status {}", status);
    fmt::print(stderr, "dtraced-bench-scale: the fresh {} build on {} threads failed ({}): {}\n", engine, threads, how,
               out);
    return std::nullopt;
  }
  b.tree_hash = hash;
  return b;
}

// The fresh-process builds of `path`: `runs` of each engine on 1 and `threads` threads, in
// runs that alternate the engines' order (ours first in even runs), so that both see the
// same minutes of a shared machine. Fills f's fresh figures; false when a child failed or ours
// built trees of different hashes (`hash`: the repeated builds' tree).
bool measure_fresh(const std::string& path, std::uint32_t threads, int runs, bool threaded_load, std::uint64_t hash,
                   Figures& f) {
  std::vector<std::uint32_t> counts = {1u};
  if (threads != 1) counts.push_back(threads);
  std::vector<std::string> engines = {"ours"};
#ifdef DTRACED_BENCH_EMBREE
  engines.emplace_back("embree");
#endif
  std::vector<double> ours[2], ours_cpu[2], embree[2], load;
  for (int r = 0; r < runs; ++r) {
    for (std::size_t c = 0; c < counts.size(); ++c) {
      for (std::size_t k = 0; k < engines.size(); ++k) {
        const std::string& engine = engines[r % 2 == 0 ? k : engines.size() - 1 - k];
        const std::optional<FreshBuild> b = run_fresh(path, engine, counts[c], threaded_load);
        if (!b) return false;
        if (engine == "ours") {
          if (b->tree_hash != hash) {
            fmt::print(stderr,
                       "dtraced-bench-scale: a fresh build's tree {:016x} is not the repeated builds' {:016x}\n",
                       b->tree_hash, hash);
            return false;
          }
          ours[c].push_back(b->seconds);
          ours_cpu[c].push_back(b->cpu);
          load.push_back(b->load_s);
          fmt::print(stderr, "  fresh process, ours on {} thread{}: {:.3f} s, cpu {:.3f} s (load {:.3f} s)\n",
                     counts[c], counts[c] == 1 ? "" : "s", b->seconds, b->cpu, b->load_s);
        } else {
          embree[c].push_back(b->seconds);
          fmt::print(stderr, "  fresh process, embree on {} thread{}: {:.3f} s\n", counts[c], counts[c] == 1 ? "" : "s",
                     b->seconds);
        }
      }
    }
  }
  const std::size_t n = counts.size() - 1;  // the `threads` figures (the 1-thread ones when threads is 1)
  f.fresh_runs = runs;
  f.fresh1_s = median(ours[0]);
  f.freshn_s = median(ours[n]);
  f.fresh1_cpu = median(ours_cpu[0]);
  f.freshn_cpu = median(ours_cpu[n]);
  f.fresh_load_s = median(load);
  if (!embree[0].empty()) {
    f.fresh_embree1_s = median(embree[0]);
    f.fresh_embreen_s = median(embree[n]);
  }
  return true;
}

int measure(const std::string& path, std::uint32_t threads, int runs, int fresh_runs, std::uint32_t width,
            std::uint32_t height, bool load_only, bool threaded_load) {
  Figures f;
  const accel::Isa isa = accel::best_isa();
  double pipeline_build_s = 0.0;
  std::uint64_t tree_hash = 0;
  {
    // The pipeline as `dtraced render` runs it: load, build, render.
    auto start = Clock::now();
    const double cpu_start = cpu_seconds();
    render::RenderSceneBuilder builder;
    reset_peak_rss();
    std::optional<scene::LoadResult> loaded = load_into(path, builder, threaded_load);
    if (!loaded) return 1;
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
    const render::RenderScene rs = std::move(builder).build(*loaded->scene, isa, threads);
    const double scene_s = since(start);
    const double build_rss = phase_peak_bytes();
    const accel::Geometry* tree = one_tree(rs, path);
    if (tree == nullptr) return 1;
    for (const accel::Shape& s : tree->shapes()) f.spheres += s.type == accel::ShapeType::kSphere;
    const accel::BuildStats& st = tree->stats();
    pipeline_build_s = st.seconds + st.wide_seconds;
    tree_hash = st.tree_hash;
    f.load_s = parse_s + (scene_s - pipeline_build_s);
    scene::RenderSettings settings = loaded->scene->render;
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
    const std::vector<accel::Shape>& shapes = tree->shapes();
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
    // 1 thread and `threads` (once where that is 1).
    const std::vector<std::uint32_t> counts = threads == 1 ? std::vector{1u} : std::vector{1u, threads};
    std::vector<double> one, many, one_cpu, many_cpu;
    for (int i = 0; i < runs; ++i) {
      for (const std::uint32_t t : counts) {
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
    f.buildn_s = threads == 1 ? f.build1_s : median(many);
    f.build1_cpu = median(one_cpu);
    f.buildn_cpu = threads == 1 ? f.build1_cpu : median(many_cpu);
#ifdef DTRACED_BENCH_EMBREE
    std::vector<double> e1, en;
    for (int i = 0; i < runs; ++i) {
      for (const std::uint32_t t : counts) {
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
    if (threads == 1) f.embreen_s = f.embree1_s;
#endif
  }
  // After the block: this process holds nothing of the scene while the children load and build.
  if (fresh_runs > 0 && !measure_fresh(path, threads, fresh_runs, threaded_load, tree_hash, f)) return 1;

  const double per_sphere = f.spheres ? f.rss / double(f.spheres) : 0.0;
  fmt::print("spheres {:>9}  load {:7.3f} s  render {:6.3f} s  peak RSS {:7.1f} MiB  {:6.1f} B/sphere\n", f.spheres,
             f.load_s, f.render_s, f.rss / (1 << 20), per_sphere);
  // "1t A s (cpu B)  Nt C s (cpu D)", the second only where `threads` is not 1; likewise Embree's.
  const auto print_builds = [threads](double s1, double cpu1, double sn, double cpun, double e1, double en) {
    fmt::print("1t {:6.3f} s (cpu {:6.3f})", s1, cpu1);
    if (threads != 1) fmt::print("  {}t {:6.3f} s (cpu {:6.3f})", threads, sn, cpun);
    if (e1 < 0) return;
    fmt::print("  embree 1t {:6.3f} s", e1);
    if (threads != 1) fmt::print("  {}t {:6.3f} s", threads, en);
  };
  if (f.fresh_runs > 0) {
    fmt::print("  build, fresh processes ({} runs, what a render sees): ", f.fresh_runs);
    print_builds(f.fresh1_s, f.fresh1_cpu, f.freshn_s, f.freshn_cpu, f.fresh_embree1_s, f.fresh_embreen_s);
    fmt::print("  load {:6.3f} s\n", f.fresh_load_s);
  }
  fmt::print("  build, repeated in one process ({} runs): ", runs);
  print_builds(f.build1_s, f.build1_cpu, f.buildn_s, f.buildn_cpu, f.embree1_s, f.embreen_s);
  fmt::print("\n");
  // Issue 16's targets: the load, bytes and build ones are the 1M scene's; of 10M only that it
  // renders (it did, to get here).
  if (f.spheres >= 2'000'000) {
    fmt::print("  target renders: MET (the load, bytes and build targets are the 1M scene's)\n");
  } else if (f.spheres >= 1'000'000) {
    fmt::print("  target load <= 1 s: {}; bytes/sphere <= 150: {}", verdict(f.load_s <= 1.0),
               verdict(per_sphere <= 150));
    // "(1t): MET; (Nt): MISSED", the second only where `threads` is not 1.
    const auto print_verdicts = [threads](double s1, double e1, double sn, double en) {
      fmt::print(" (1t): {}", verdict(s1 <= e1));
      if (threads != 1) fmt::print("; ({}t): {}", threads, verdict(sn <= en));
    };
    if (f.fresh_embree1_s >= 0) {
      fmt::print("; build <= embree, fresh processes");
      print_verdicts(f.fresh1_s, f.fresh_embree1_s, f.freshn_s, f.fresh_embreen_s);
    }
    if (f.embree1_s >= 0) {
      fmt::print("; repeated builds");
      print_verdicts(f.build1_s, f.embree1_s, f.buildn_s, f.embreen_s);
    }
    fmt::print("\n");
  }
  fmt::print("  load average {}\n", load_average());
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
    const accel::Geometry* tree = one_tree(*prepared.scene->frame(0), path);
    if (tree == nullptr) return 1;
    const accel::BuildStats& st = tree->stats();
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
  app.add_option("--runs", runs, "Timed builds per thread count (median), repeated in this process")
      ->check(CLI::Range(1, 100));
  int fresh_runs = -1;
  app.add_option("--fresh-runs", fresh_runs,
                 "Builds per thread count and engine, each in a fresh process (median; default --runs, 0: none)")
      ->check(CLI::Range(0, 100));
  app.add_option("--width", width, "Render width")->check(CLI::Range(1u, 8192u));
  app.add_option("--height", height, "Render height")->check(CLI::Range(1u, 8192u));
  bool load_only = false;
  app.add_flag("--load-only", load_only, "Only parse FILE: its time and peak RSS (for profiling the load)");
  bool threaded_load = false;
  app.add_flag("--threaded-load", threaded_load, "Read FILE's objects on a second thread while the first parses");
  std::string cache_dir;
  app.add_option("--cache-dir", cache_dir,
                 "Measure a worker's load of FILE from its JSON and then from the binary scene cache it writes here");
  // The child of a fresh-process build (see the header); not for use by hand.
  std::string fresh_engine;
  app.add_option("--fresh-build", fresh_engine)->check(CLI::IsMember({"ours", "embree"}))->group("");
  CLI11_PARSE(app, argc, argv);
  if (!fresh_engine.empty()) return dtraced::bench::fresh_build(file, fresh_engine, threads, threaded_load);
  if (write_count > 0) return dtraced::bench::write_scene(write_count, file);
  if (!cache_dir.empty()) return dtraced::bench::measure_cache(file, cache_dir, threads);
  return dtraced::bench::measure(file, threads, runs, fresh_runs < 0 ? runs : fresh_runs, width, height, load_only,
                                 threaded_load);
}
