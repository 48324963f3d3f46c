// dtraced-bench-frames: what a frame of an animation costs when only a few objects move. The scene
// is scene::generate_sphere_field (a large field of spheres that stays still) plus a few spheres
// that fly across it (a loc track each). Per frame it times scene::scene_at_frame (the frame's
// description, needed either way), then
//   (a) full rebuild: RenderScene::build of the frame's description (one BVH over everything),
//   (b) static shared: RenderScene::build_frame on the StaticPart built once (the moving layer only),
// and the render of the frame from each (render::render_local): the first render (what a frame
// pays: a freshly built BVH is cold in the caches) and a second one (the two-level traversal's own
// cost, both warm). Refit of the moving layer is not offered: the table times the moving layer's
// build alone, the most a refit could save, and it is a small part of (b).
// A benchmark, not a test: it prints a table of medians over the frames and judges nothing.
// Times are CPU time (builds: the building thread's; renders: the process's, all render threads),
// which a busy shared machine disturbs far less than wall time.
//
// Threading: main's thread builds; renders use --threads threads (render_local).
#include <time.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "accel/isa.h"
#include "accel/layered.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/animation.h"
#include "scene/generate.h"

namespace {

using namespace dtraced;

struct Options {
  std::uint32_t statics = 100'000;
  std::uint32_t moving = 8;
  std::uint32_t frames = 9;
  std::uint32_t width = 320;
  std::uint32_t height = 240;
  std::uint32_t threads = 0;
  std::string isa = "best";
};

double cpu_seconds(clockid_t clock) {
  timespec ts{};
  clock_gettime(clock, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

// CPU time of `f` on this thread (a build) or on every thread of the process (a render).
template <typename F>
double cpu_time(clockid_t clock, F&& f) {
  const double start = cpu_seconds(clock);
  f();
  return cpu_seconds(clock) - start;
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  return n % 2 == 1 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// The flying spheres: `moving` spheres above the field, each with a loc track carrying it along x
// (12, 24 or 36 units a second), and the field's own objects still.
void add_flyers(scene::SceneDesc& d, std::uint32_t moving) {
  auto animation = std::make_shared<scene::Animation>();
  const math::Vec3d at = d.camera.look_at;
  for (std::uint32_t i = 0; i < moving; ++i) {
    scene::Object o;
    o.type = scene::ObjectType::kSphere;
    o.sphere = {at + math::Vec3d{-4.0 + i, 1.5 + 0.3 * (i % 4), 2.0 - 0.5 * i}, 0.4};
    o.material.color = {0.9, 0.9, 0.95};
    scene::Track track;
    track.target = scene::Target::kObjectLoc;
    track.index = static_cast<std::uint32_t>(d.objects.size());
    track.keys = {{0.0, o.sphere.center}, {1.0, o.sphere.center + math::Vec3d{12.0 * (1 + i % 3), 0, 0}}};
    animation->tracks.push_back(track);  // objects' tracks in index order, as the loader sorts them
    d.objects.push_back(o);
  }
  d.animation = std::move(animation);
}

struct Row {
  std::string name;
  std::vector<double> build, render, again;
};

// The moving layer alone, as build_frame builds it: the frame's flying spheres, ids after the rest.
double moving_layer_seconds(const scene::SceneDesc& f, std::uint32_t moving, accel::Isa isa) {
  std::vector<accel::Shape> shapes;
  std::vector<std::uint32_t> ids;
  for (std::size_t i = f.objects.size() - moving; i < f.objects.size(); ++i) {
    accel::Shape s;
    s.type = accel::ShapeType::kSphere;
    s.sphere = {math::Vec3f(f.objects[i].sphere.center), float(f.objects[i].sphere.radius)};
    shapes.push_back(s);
    ids.push_back(static_cast<std::uint32_t>(i));
  }
  return cpu_time(CLOCK_THREAD_CPUTIME_ID, [&] { accel::Layer::build(std::move(shapes), std::move(ids), isa); });
}

int run(const Options& opt) {
  const std::optional<accel::Isa> isa = accel::parse_isa(opt.isa);
  if (!isa) {
    std::fprintf(stderr, "dtraced-bench-frames: --isa %s: not an instruction set this build knows\n", opt.isa.c_str());
    return 2;
  }
  scene::SceneDesc base = scene::generate_sphere_field(opt.statics, 7);
  base.render.width = opt.width;
  base.render.height = opt.height;
  base.render.samples = 1;
  add_flyers(base, opt.moving);

  render::AnimatedScene prepared;
  const double part_seconds =
      cpu_time(CLOCK_THREAD_CPUTIME_ID, [&] { prepared = render::AnimatedScene::prepare(base, *isa); });
  const render::StaticPart& part = *prepared.static_part();

  render::LocalOptions lo;
  lo.threads = opt.threads;
  Row full{"(a) full rebuild", {}, {}, {}}, shared{"(b) static shared + rebuild moving", {}, {}, {}};
  std::vector<double> moving_layer, evaluate;
  for (std::uint32_t k = 0; k < opt.frames; ++k) {
    scene::SceneDesc f;
    evaluate.push_back(cpu_time(CLOCK_THREAD_CPUTIME_ID, [&] { f = scene::scene_at_frame(base, k); }));
    render::RenderScene whole, layered;
    full.build.push_back(cpu_time(CLOCK_THREAD_CPUTIME_ID, [&] { whole = render::RenderScene::build(f, *isa); }));
    shared.build.push_back(
        cpu_time(CLOCK_THREAD_CPUTIME_ID, [&] { layered = render::RenderScene::build_frame(f, part); }));
    moving_layer.push_back(moving_layer_seconds(f, opt.moving, *isa));
    const auto render = [&](const render::RenderScene& rs) {
      return cpu_time(CLOCK_PROCESS_CPUTIME_ID, [&] { render::render_local(rs, f.render, lo); });
    };
    full.render.push_back(render(whole));
    shared.render.push_back(render(layered));
    full.again.push_back(render(whole));
    shared.again.push_back(render(layered));
  }

  fmt::print("dtraced-bench-frames: {} static spheres + {} moving, {}x{} 1 spp, isa {}, {} frames (medians)\n",
             opt.statics, opt.moving, opt.width, opt.height, accel::isa_name(*isa), opt.frames);
  fmt::print("static part, built once: {:.2f} ms\n", part_seconds * 1e3);
  fmt::print("{:<36} {:>10} {:>10} {:>10} {:>12}\n", "per frame (CPU time)", "build ms", "render ms", "total ms",
             "re-render ms");
  for (const Row& r : {full, shared}) {
    const double b = median(r.build), re = median(r.render);
    fmt::print("{:<36} {:>10.3f} {:>10.2f} {:>10.2f} {:>12.2f}\n", r.name, b * 1e3, re * 1e3, (b + re) * 1e3,
               median(r.again) * 1e3);
  }
  fmt::print("scene_at_frame (both): {:.3f} ms\n", median(evaluate) * 1e3);
  fmt::print("moving layer alone (the most a refit could save): {:.3f} ms\n", median(moving_layer) * 1e3);
  fmt::print("build speed-up (a)/(b): {:.0f}x; frame speed-up: {:.1f}x\n", median(full.build) / median(shared.build),
             (median(full.build) + median(full.render)) / (median(shared.build) + median(shared.render)));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Options opt;
  CLI::App app{"dtraced-bench-frames: per-frame cost of an animation whose large static part is built once"};
  app.add_option("--static", opt.statics, "Spheres that stay still")->check(CLI::Range(1u, 1'000'000u));
  app.add_option("--moving", opt.moving, "Spheres that move")->check(CLI::Range(1u, 1000u));
  app.add_option("--frames", opt.frames, "Frames timed")->check(CLI::Range(1u, 1000u));
  app.add_option("--width", opt.width, "Image width")->check(CLI::Range(1u, 4096u));
  app.add_option("--height", opt.height, "Image height")->check(CLI::Range(1u, 4096u));
  app.add_option("--threads", opt.threads, "Render threads (0 = every hardware thread)")->check(CLI::Range(0u, 1024u));
  app.add_option("--isa", opt.isa, "Traversal kernels: scalar, sse4, avx2, avx512 or best");
  CLI11_PARSE(app, argc, argv);
  return run(opt);
}
