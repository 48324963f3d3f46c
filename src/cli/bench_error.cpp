#include "cli/bench_error.h"

#include <spawn.h>
#include <sys/wait.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <limits>
#include <vector>

#include <fmt/format.h>

#include "cli/bench_error_args.h"
#include "cli/overrides_flags.h"
#include "cli/roles.h"
#include "image/image_io.h"
#include "image/metrics.h"
#include "render/local_render.h"
#include "render/reference.h"
#include "render/render_scene.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "util/file.h"
#include "util/result.h"

extern char** environ;

namespace dtraced::cli {

namespace {

constexpr int kExitFailed = 1;
// The reference render's seed is the scene's plus this odd constant (the golden ratio's 64-bit
// fraction): its sample keys are disjoint from every row's, so its noise is independent of theirs.
constexpr std::uint64_t kReferenceSeedOffset = 0x9E3779B97F4A7C15ull;
constexpr std::uint32_t kReferenceFactor = 16;  // default reference spp = 16 * max spp
// The largest --max-spp: a quarter of the sample limit, so the reference (16 x, capped at the
// limit) still has at least 4 times the samples of the last row.
constexpr std::uint32_t kMaxRowSamples = scene::kMaxSamples / 4;
constexpr std::size_t kMaxTargets = 16;
constexpr std::uint32_t kMaxRepeats = 99;

struct Row {
  std::string kind;     // "uniform", "adaptive" or "cutoff"
  double target = 0.0;  // adaptive: the error target; cutoff: the branch cut-off
  double cutoff = 0.0;  // the branch cut-off the row rendered with
  double spp = 0.0;     // mean samples per pixel
  double seconds = 0.0;
  double mrays = 0.0;
  double rays_per_pixel = 0.0;  // every ray cast, border rays included, per image pixel
  image::ImageDiff diff;
  double efficiency() const { return 1.0 / (diff.rel_mse * seconds); }
};

struct Timed {
  render::LocalResult result;
  double seconds = 0.0;  // median over the repeats
};

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Renders `repeats` times and keeps the median wall time. Renders are deterministic, so every
// repeat must give the same bits: a difference is a bug and fails the run.
util::Result<Timed> timed_render(const render::RenderScene& rs, const scene::RenderSettings& s,
                                 const render::LocalOptions& opts, std::uint32_t repeats) {
  Timed t;
  std::vector<double> seconds;
  for (std::uint32_t i = 0; i < repeats; ++i) {
    render::LocalResult r = render::render_local(rs, s, opts);
    seconds.push_back(r.seconds);
    if (i == 0) {
      t.result = std::move(r);
    } else if (r.image.rgb != t.result.image.rgb) {
      return util::Error{
          fmt::format("two renders at {} spp gave different images: rendering is not deterministic", s.samples)};
    }
  }
  t.seconds = median(seconds);
  return t;
}

struct Reference {
  image::ImageRGBf image;
  double noise = 0.0;  // its own expected contribution to every row's relMSE
  std::string how;
};

// The mean over finite values of var / (ref^2 + epsilon): what the reference's own noise adds to
// the expected relMSE of an independent render measured against it.
double reference_noise(const image::ImageRGBf& ref, const image::ImageRGBf& var) {
  double sum = 0.0;
  std::size_t n = 0;
  for (std::size_t i = 0; i < ref.rgb.size() && i < var.rgb.size(); ++i) {
    const double r = ref.rgb[i], v = var.rgb[i];
    if (!std::isfinite(r) || !std::isfinite(v)) continue;
    sum += v / (r * r + image::kRelMseEpsilon);
    ++n;
  }
  return n ? sum / double(n) : 0.0;
}

std::optional<image::ImageRGBf> read_cached(const std::string& path, const scene::RenderSettings& s) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) return std::nullopt;
  util::Result<image::ImageRGBf> img = image::read_image(path);
  if (!img) {
    fmt::print(stderr, "ignoring the cached reference: {}\n", img.error().to_string());
    return std::nullopt;
  }
  if (img->width != s.width || img->height != s.height) {
    fmt::print(stderr, "ignoring the cached reference {}: {}x{}, expected {}x{}\n", path, img->width, img->height,
               s.width, s.height);
    return std::nullopt;
  }
  return std::move(img).value();
}

// The closed form when the scene has one, else a high-sample render with a disjoint seed, cached
// as PFM (image and its per-pixel variance of the mean) under a name that carries the digest of
// exactly what was rendered.
util::Result<Reference> make_reference(const scene::SceneDesc& desc, const render::RenderScene& rs,
                                       const BenchErrorArgs& args, const render::LocalOptions& base) {
  std::string why_not;
  if (std::optional<image::ImageRGBf> exact =
          render::closed_form_reference(desc, rs, render::kReferenceGrid, why_not)) {
    return Reference{std::move(*exact), 0.0,
                     fmt::format("closed form ({0}x{0} film positions per pixel)", render::kReferenceGrid)};
  }
  scene::SceneDesc ref_desc = desc;
  scene::RenderSettings& s = ref_desc.render;
  s.samples = args.reference_spp.value_or(std::min<std::uint32_t>(args.max_spp * kReferenceFactor, scene::kMaxSamples));
  s.seed += kReferenceSeedOffset;
  s.error_target = 0.0;
  // Branches the rows may cut are in the reference.
  s.branch_cutoff = std::min(s.branch_cutoff, scene::RenderSettings{}.branch_cutoff);

  const std::filesystem::path scene_path(args.scene);
  const std::filesystem::path dir =
      args.cache_dir.empty() ? scene_path.parent_path() : std::filesystem::path(args.cache_dir);
  const std::string stem = scene_path.stem().string();
  const std::string key = scene::scene_digest(ref_desc).substr(0, 16);
  const std::string image_path = (dir / fmt::format("{}.ref-{}.pfm", stem, key)).string();
  const std::string var_path = (dir / fmt::format("{}.ref-{}.var.pfm", stem, key)).string();

  Reference ref;
  std::optional<image::ImageRGBf> cached = read_cached(image_path, s);
  std::optional<image::ImageRGBf> cached_var = cached ? read_cached(var_path, s) : std::nullopt;
  if (cached && cached_var) {
    ref.image = std::move(*cached);
    ref.noise = reference_noise(ref.image, *cached_var);
    ref.how =
        fmt::format("{} spp render, seed {} (no closed form: {}); cached {}", s.samples, s.seed, why_not, image_path);
    return ref;
  }
  fmt::print(stderr, "rendering the reference at {} spp (no closed form: {})...\n", s.samples, why_not);
  render::LocalOptions opts = base;
  opts.want_variance = true;
  const render::LocalResult r = render::render_local(rs, s, opts);
  std::error_code ec;
  if (!dir.empty()) std::filesystem::create_directories(dir, ec);
  for (const auto& [path, img] : {std::pair{&image_path, &r.image}, std::pair{&var_path, &r.variance}}) {
    if (util::Status written = image::write_image(*path, *img); !written) {
      return util::Error{fmt::format("caching the reference: {}", written.error().to_string())};
    }
  }
  ref.image = r.image;
  ref.noise = reference_noise(r.image, r.variance);
  ref.how = fmt::format("{} spp render, seed {} (no closed form: {}); rendered in {:.2f} s, cached {}", s.samples,
                        s.seed, why_not, r.seconds, image_path);
  return ref;
}

// Least-squares slope of log(relMSE - noise) against log(spp) over the uniform rows from 2 spp up
// (1 spp goes through the pixel centre: a different estimator). NaN when fewer than two rows count.
double convergence_slope(const std::vector<Row>& rows, double noise) {
  std::vector<std::pair<double, double>> pts;
  for (const Row& r : rows) {
    const double e = r.diff.rel_mse - noise;
    if (r.kind == "uniform" && r.spp >= 2 && e > 0) pts.emplace_back(std::log(r.spp), std::log(e));
  }
  if (pts.size() < 2) return std::numeric_limits<double>::quiet_NaN();
  double mx = 0, my = 0;
  for (const auto& [x, y] : pts) mx += x, my += y;
  mx /= double(pts.size());
  my /= double(pts.size());
  double sxy = 0, sxx = 0;
  for (const auto& [x, y] : pts) sxy += (x - mx) * (y - my), sxx += (x - mx) * (x - mx);
  return sxy / sxx;
}

// Seconds uniform sampling needs to reach `rel_mse`, interpolated linearly in log-log between the
// two uniform rows that bracket it; nullopt outside their range. From 2 spp up, like the slope:
// the 1-spp row shoots through pixel centres, another estimator than the jittered rows.
std::optional<double> uniform_seconds_at(const std::vector<Row>& rows, double rel_mse) {
  const Row* prev = nullptr;
  for (const Row& r : rows) {
    if (r.kind != "uniform" || r.spp < 2.0) continue;
    if (prev && prev->diff.rel_mse >= rel_mse && r.diff.rel_mse <= rel_mse && prev->diff.rel_mse > r.diff.rel_mse &&
        rel_mse > 0) {
      const double f = (std::log(rel_mse) - std::log(prev->diff.rel_mse)) /
                       (std::log(r.diff.rel_mse) - std::log(prev->diff.rel_mse));
      return std::exp(std::log(prev->seconds) + f * (std::log(r.seconds) - std::log(prev->seconds)));
    }
    prev = &r;
  }
  return std::nullopt;
}

std::string csv_field(std::string s) {
  std::replace(s.begin(), s.end(), ',', '_');
  return s;
}

std::string csv_text(const std::vector<Row>& rows, const std::string& scene, std::string_view isa, double noise) {
  std::string out =
      "scene,isa,kind,target,spp,seconds,mrays_per_s,mse,rel_mse,psnr_db,max_abs,nonfinite,efficiency,ref_noise,"
      "rays_per_pixel,branch_cutoff\n";
  for (const Row& r : rows) {
    out += fmt::format("{},{},{},{},{:.4f},{:.6g},{:.4g},{:.6g},{:.6g},{:.4f},{:.6g},{},{:.6g},{:.6g},{:.6g},{:.6g}\n",
                       csv_field(scene), isa, r.kind, r.target, r.spp, r.seconds, r.mrays, r.diff.mse, r.diff.rel_mse,
                       r.diff.psnr_db, r.diff.max_abs, r.diff.nonfinite, r.efficiency(), noise, r.rays_per_pixel,
                       r.cutoff);
  }
  return out;
}

// A gnuplot single-quoted string: a quote is written twice.
std::string gp_quote(const std::string& s) {
  std::string out = "'";
  for (const char c : s) out += c == '\'' ? std::string("''") : std::string(1, c);
  return out + "'";
}

// Runs gnuplot on a script written beside the plot; the process's exit status decides.
util::Status draw_plot(const std::string& csv, const std::string& plot, const std::string& scene) {
  const std::string ext = std::filesystem::path(plot).extension().string();
  std::string terminal;
  if (ext == ".svg") terminal = "svg size 820,560 dynamic background rgb 'white'";
  if (ext == ".png") terminal = "pngcairo size 820,560 background rgb 'white'";
  if (terminal.empty()) return util::Error{fmt::format("{}: the plot must be .svg or .png", plot)};
  const std::string col = "(strcol(3) eq '{}' ? $9 : NaN)";
  std::string script = fmt::format(
      "set terminal {}\nset output {}\nset datafile separator ','\nset logscale xy\n"
      "set xlabel 'render seconds (median)'\nset ylabel 'relMSE (epsilon 0.01)'\n"
      "set title {} noenhanced\nset grid\nset key top right\n",
      terminal, gp_quote(plot), gp_quote(scene + ": error against time"));
  script += fmt::format(
      "plot {0} skip 1 using 6:{1} with linespoints pt 7 title 'uniform, 1, 2, 4, ... spp', \\\n"
      "  '' skip 1 using 6:{1}:(sprintf('%g', $5)) with labels offset 1.2,0.6 notitle, \\\n"
      "  '' skip 1 using 6:{2} with points pt 5 ps 1.4 title 'adaptive, per error target', \\\n"
      "  '' skip 1 using 6:{2}:(sprintf('%g', $4)) with labels offset -1.6,-0.8 notitle\n",
      gp_quote(csv), fmt::format(fmt::runtime(col), "uniform"), fmt::format(fmt::runtime(col), "adaptive"));
  const std::string script_path = plot + ".gp";
  if (util::Status written = util::write_file_atomic(script_path, script); !written) return written.error();

  std::string arg0 = "gnuplot", arg1 = script_path;
  char* argv[] = {arg0.data(), arg1.data(), nullptr};
  pid_t pid = 0;
  const int rc = ::posix_spawnp(&pid, "gnuplot", nullptr, nullptr, argv, environ);
  if (rc != 0) {
    return util::Error{
        fmt::format("cannot run gnuplot ({}): install gnuplot-nox, or pass --no-plot", std::strerror(rc))};
  }
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0) {
    if (errno != EINTR) return util::Error{fmt::format("waiting for gnuplot: {}", std::strerror(errno))};
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    return util::Error{fmt::format("gnuplot failed on {} (status {})", script_path, status)};
  }
  return {};
}

std::string fmt_target(double t) { return t > 0 ? fmt::format("{:g}", t) : std::string("-"); }

}  // namespace

CLI::App* add_bench_error_verb(CLI::App& app, BenchErrorArgs& args, std::optional<std::string>& isa_flag) {
  CLI::App* bench = app.add_subcommand("bench", "Benchmarks that print tables");
  bench->require_subcommand(1);
  CLI::App* e = bench->add_subcommand(
      "error", "Speed against error: uniform and adaptive renders of one scene measured against a reference");
  e->add_option("scene", args.scene, "Scene file (JSON)")->required();
  e->add_option("--max-spp", args.max_spp, "Uniform rows at 1, 2, 4, ... samples per pixel up to this")
      ->check(CLI::Range(1u, kMaxRowSamples));
  e->add_option("--targets", args.targets, "Adaptive rows: error targets (relative standard error), at --max-spp")
      ->check(CLI::Range(1e-6, 1.0))
      ->expected(1, int(kMaxTargets));
  e->add_flag("--no-adaptive", args.no_adaptive, "No adaptive rows");
  e->add_option("--cutoffs", args.cutoffs,
                "Cut-off rows: uniform renders at --max-spp with each of these branch cut-offs (default 1/255)")
      ->check(CLI::Range(scene::kMinBranchCutoff, scene::kMaxBranchCutoff))
      ->expected(1, int(kMaxTargets));
  e->add_flag("--no-cutoffs", args.no_cutoffs, "No cut-off rows");
  e->add_option("--min-samples", args.min_samples, "Adaptive rows: the first checkpoint")
      ->check(CLI::Range(1u, scene::kMaxSamples));
  e->add_option("--reference-spp", args.reference_spp,
                "Samples of the reference render when there is no closed form (default 16 x --max-spp)")
      ->check(CLI::Range(1u, scene::kMaxSamples));
  e->add_option("--cache-dir", args.cache_dir, "Where reference renders are cached (default: beside the scene)");
  e->add_option("--csv", args.csv, "CSV output (default: <scene name>-error.csv)");
  e->add_option("--plot", args.plot,
                "Log-log plot of relMSE against seconds, .svg or .png (default: <scene>-error.svg)");
  e->add_flag("--no-plot", args.no_plot, "Do not draw the plot (no gnuplot needed)");
  e->add_option("--repeats", args.repeats, "Renders per row; the median time is reported")
      ->check(CLI::Range(1u, kMaxRepeats));
  e->add_option("--spec-spp", args.spec_spp, "Samples of the specialised-against-generic comparison")
      ->check(CLI::Range(1u, scene::kMaxSamples));
  e->add_option("-t,--threads", args.threads, "Render threads (0: every core)")->check(CLI::Range(0u, 1024u));
  OverrideFlagOptions overrides;
  overrides.fields = kAllOverrides & ~(kOverrideSamples | kOverrideErrorTarget | kOverrideMinSamples |
                                       kOverridePngBitDepth | kOverrideFrames | kOverrideDisplay | kOverrideCrop);
  add_override_flags(*e, args.overrides, overrides);
  e->add_option("--isa", isa_flag, kIsaHelp);
  return e;
}

namespace {

// The flags that only make sense together, checked before any render.
util::Status check_bench_args(const BenchErrorArgs& args, const std::vector<double>& targets,
                              const std::string& plot_path) {
  if (args.min_samples >= args.max_spp && !targets.empty()) {
    return util::Error{fmt::format("--min-samples {} must be below --max-spp {} for adaptive rows to stop early",
                                   args.min_samples, args.max_spp)};
  }
  if (args.reference_spp && *args.reference_spp <= args.max_spp) {
    return util::Error{
        fmt::format("--reference-spp {} must be above --max-spp {}: the reference needs more samples than any row",
                    *args.reference_spp, args.max_spp)};
  }
  if (!args.no_plot) {
    const std::string ext = std::filesystem::path(plot_path).extension().string();
    if (ext != ".svg" && ext != ".png") {
      return util::Error{fmt::format("{}: the plot must be .svg or .png (or pass --no-plot)", plot_path)};
    }
  }
  return {};
}

// One row: the median time of `repeats` renders at `s`, and the image's error against the reference.
util::Result<Row> measure(const render::RenderScene& rs, const render::LocalOptions& opts, const BenchErrorArgs& args,
                          const Reference& ref, const char* kind, double target, const scene::RenderSettings& s) {
  util::Result<Timed> t = timed_render(rs, s, opts, args.repeats);
  if (!t) return std::move(t).error();
  const util::Result<image::ImageDiff> d = image::compare_images(t->result.image, ref.image);
  if (!d) return d.error();
  Row row{kind, target, s.branch_cutoff, double(s.samples), t->seconds, 0.0, 0.0, *d};
  if (!t->result.spp.empty()) {
    double total = 0;
    for (const std::uint32_t n : t->result.spp) total += n;
    row.spp = total / double(t->result.spp.size());
  }
  const double rays = double(t->result.stats.all_rays());
  row.mrays = t->seconds > 0 ? rays / t->seconds / 1e6 : 0.0;
  row.rays_per_pixel = rays / (double(s.width) * double(s.height));
  return row;
}

// The uniform rows at 1, 2, 4, ... spp, then one adaptive row per target, then one uniform row at
// max spp per branch cut-off.
util::Result<std::vector<Row>> measure_rows(const render::RenderScene& rs, const render::LocalOptions& opts,
                                            const BenchErrorArgs& args, const Reference& ref,
                                            const scene::RenderSettings& render, const std::vector<double>& targets,
                                            const std::vector<double>& cutoffs) {
  std::vector<Row> rows;
  scene::RenderSettings s = render;
  s.error_target = 0.0;
  for (std::uint32_t spp = 1; spp <= args.max_spp; spp *= 2) {
    s.samples = spp;
    util::Result<Row> row = measure(rs, opts, args, ref, "uniform", 0.0, s);
    if (!row) return std::move(row).error();
    rows.push_back(std::move(row).value());
  }
  for (const double target : targets) {
    s.samples = args.max_spp;
    s.error_target = target;
    s.min_samples = args.min_samples;
    util::Result<Row> row = measure(rs, opts, args, ref, "adaptive", target, s);
    if (!row) return std::move(row).error();
    rows.push_back(std::move(row).value());
  }
  for (const double cutoff : cutoffs) {
    s = render;
    s.samples = args.max_spp;
    s.error_target = 0.0;
    s.branch_cutoff = cutoff;
    util::Result<Row> row = measure(rs, opts, args, ref, "cutoff", cutoff, s);
    if (!row) return std::move(row).error();
    rows.push_back(std::move(row).value());
  }
  return rows;
}

// The table, the convergence slope and each adaptive row against uniform sampling.
void print_rows(const std::vector<Row>& rows, double noise) {
  fmt::print("\n{:<9} {:>7} {:>8} {:>9} {:>8} {:>8} {:>10} {:>10} {:>8} {:>9} {:>8} {:>11}\n", "kind", "target", "spp",
             "seconds", "Mrays/s", "rays/px", "MSE", "relMSE", "PSNR dB", "max abs", "NaN/Inf", "efficiency");
  for (const Row& r : rows) {
    fmt::print(
        "{:<9} {:>7} {:>8.2f} {:>9.4f} {:>8.2f} {:>8.1f} {:>10.3e} {:>10.3e} {:>8.2f} {:>9.3g} {:>8} {:>11.4g}\n",
        r.kind, fmt_target(r.target), r.spp, r.seconds, r.mrays, r.rays_per_pixel, r.diff.mse, r.diff.rel_mse,
        r.diff.psnr_db, r.diff.max_abs, r.diff.nonfinite, r.efficiency());
  }

  const double slope = convergence_slope(rows, noise);
  fmt::print("\nuniform relMSE against spp, 2 spp up{}: log-log slope {:.3f} (Monte Carlo's 1/spp is -1)\n",
             noise > 0 ? ", reference noise removed" : "", slope);
  for (const Row& r : rows) {
    if (r.kind != "adaptive") continue;
    const std::optional<double> u = uniform_seconds_at(rows, r.diff.rel_mse);
    if (u) {
      fmt::print(
          "adaptive {:g}: relMSE {:.3e} in {:.4f} s at a mean {:.1f} spp; uniform needs {:.4f} s: time ratio "
          "adaptive/uniform {:.2f}\n",
          r.target, r.diff.rel_mse, r.seconds, r.spp, *u, r.seconds / *u);
    } else {
      fmt::print("adaptive {:g}: relMSE {:.3e} in {:.4f} s at a mean {:.1f} spp; outside the uniform rows' range\n",
                 r.target, r.diff.rel_mse, r.seconds, r.spp);
    }
  }
  // Each cut-off row against the uniform row of the same spp (the scene's own cut-off).
  for (const Row& r : rows) {
    if (r.kind != "cutoff") continue;
    for (const Row& u : rows) {
      if (u.kind != "uniform" || u.spp != r.spp) continue;
      fmt::print(
          "branch cut-off {:g} at {:g} spp: {:.1f} rays/px against {:.1f} (cut-off {:g}), time ratio {:.2f}, "
          "relMSE {:.3e} against {:.3e} (x{:.3f}), PSNR {:+.2f} dB\n",
          r.target, r.spp, r.rays_per_pixel, u.rays_per_pixel, u.cutoff, r.seconds / u.seconds, r.diff.rel_mse,
          u.diff.rel_mse, r.diff.rel_mse / u.diff.rel_mse, r.diff.psnr_db - u.diff.psnr_db);
    }
  }
}

// The specialised path against the generic one: same bits, and what it saves. Whether the bits
// were the same.
util::Result<bool> compare_specialised(const render::RenderScene& rs, const render::LocalOptions& opts,
                                       const BenchErrorArgs& args, const scene::RenderSettings& render) {
  scene::RenderSettings ss = render;
  ss.samples = args.spec_spp;
  ss.error_target = 0.0;
  render::LocalOptions generic = opts, special = opts;
  generic.specialise = false;
  special.specialise = true;
  util::Result<Timed> tg = timed_render(rs, ss, generic, args.repeats);
  if (!tg) return std::move(tg).error();
  util::Result<Timed> ts = timed_render(rs, ss, special, args.repeats);
  if (!ts) return std::move(ts).error();
  const bool same_bits = tg->result.image.rgb == ts->result.image.rgb;
  fmt::print(
      "specialised path ({}) at {} spp: generic {:.4f} s, specialised {:.4f} s, speed-up x{:.2f}, same bits: "
      "{}\n",
      render::feature_names(rs.features()), ss.samples, tg->seconds, ts->seconds, tg->seconds / ts->seconds,
      same_bits ? "yes" : "NO");
  return same_bits;
}

int failed(const util::Error& e) {
  fmt::print(stderr, "{}\n", e.to_string());
  return kExitFailed;
}

}  // namespace

int run_bench_error(const BenchErrorArgs& args, accel::Isa isa) {
  scene::LoadResult loaded = scene::load_scene_file(args.scene);
  if (!loaded.ok()) {
    for (const util::Error& e : loaded.errors) fmt::print(stderr, "{}\n", e.to_string());
    return kExitFailed;
  }
  scene::SceneDesc desc = *loaded.scene;
  desc.render = scene::apply(args.overrides, desc.render);
  const std::vector<double> targets = args.no_adaptive ? std::vector<double>{} : args.targets;
  const std::vector<double> cutoffs = args.no_cutoffs ? std::vector<double>{} : args.cutoffs;
  const std::string stem = std::filesystem::path(args.scene).stem().string();
  const std::string csv_path = args.csv.empty() ? stem + "-error.csv" : args.csv;
  const std::string plot_path = args.plot.empty() ? stem + "-error.svg" : args.plot;
  if (const util::Status ok = check_bench_args(args, targets, plot_path); !ok) return failed(ok.error());

  const auto build_start = std::chrono::steady_clock::now();
  const render::RenderScene rs = render::RenderScene::build(desc, isa);
  const double build_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - build_start).count();
  render::LocalOptions opts;
  opts.threads = args.threads;
  opts.tile_size = scene::tile_size_or_default(args.overrides);

  const util::Result<Reference> ref = make_reference(desc, rs, args, opts);
  if (!ref) return failed(ref.error());
  const std::string_view isa_str = accel::isa_name(isa);
  fmt::print(
      "dtraced bench error {}: {}x{}, {} kernels, median of {} renders per row (scene build {:.3f} s, "
      "not counted)\n",
      args.scene, desc.render.width, desc.render.height, isa_str, args.repeats, build_s);
  fmt::print("features: {}\nbranch cut-off {:g}\nreference: {}\n", render::feature_names(rs.features()),
             desc.render.branch_cutoff, ref->how);
  if (ref->noise > 0) fmt::print("reference noise: adds about {:.3g} to every relMSE below\n", ref->noise);

  // One untimed render first: the first rows would otherwise also pay for cold caches, page
  // faults and thread start-up.
  {
    scene::RenderSettings warm = desc.render;
    warm.samples = 1;
    warm.error_target = 0.0;
    (void)render::render_local(rs, warm, opts);
  }
  const util::Result<std::vector<Row>> rows = measure_rows(rs, opts, args, *ref, desc.render, targets, cutoffs);
  if (!rows) return failed(rows.error());
  print_rows(*rows, ref->noise);
  const util::Result<bool> same_bits = compare_specialised(rs, opts, args, desc.render);
  if (!same_bits) return failed(same_bits.error());

  if (util::Status written = util::write_file_atomic(csv_path, csv_text(*rows, stem, isa_str, ref->noise)); !written) {
    return failed(written.error());
  }
  fmt::print("wrote {}\n", csv_path);
  if (!args.no_plot) {
    if (const util::Status drawn = draw_plot(csv_path, plot_path, stem); !drawn) return failed(drawn.error());
    fmt::print("wrote {}\n", plot_path);
  }
  if (!*same_bits) {
    fmt::print(stderr, "the specialised path rendered different bits from the generic one: a bug\n");
    return kExitFailed;
  }
  return 0;
}

}  // namespace dtraced::cli
