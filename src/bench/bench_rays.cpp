// dtraced-bench-rays: ray throughput of our traversal paths (accel::Geometry for every instruction
// set this CPU runs) against Embree 3 on the same primitives and the very same rays, and the
// speed-up of whole renders (render::render_local) with the SIMD kernels over the scalar ones.
// A benchmark, not a test: it prints tables (and optionally a CSV) and judges nothing but the
// issue's throughput targets, which it marks MET or MISSED.
//
// Protocol:
// - Scenes are built in memory from a seed: "spheres" = scene::generate_sphere_field with its
//   infinite ground plane replaced by a tessellated triangle grid (Embree has no plane, and both
//   libraries must trace the same primitives); "small" = the same with 10 spheres (the size of the
//   seed's scenes) on a ground of two big triangles; "mesh" = about 1M triangles, lat-long
//   tessellated spheres on a tessellated ground.
// - Ray sets are generated once per scene and fed unchanged to every tracer: camera rays (pinhole,
//   1 spp, 16x16-pixel tiles cut into 4x4-pixel blocks, each two 4x2-pixel packets of 8), shadow rays from the camera
//   rays' hits to one point light (only where the light is in front of the surface, as the renderer would cast them),
//   and one cosine-weighted diffuse bounce from the same hits (seeded).
// - Mrays/s = valid rays / time. One thread: CPU time of the calling thread
//   (CLOCK_THREAD_CPUTIME_ID), which is steady on a shared machine. All threads: wall time, the
//   ray set cut into chunks handed out through one atomic counter. One warm-up, then the median
//   (and min-max) of --runs timed runs. Packet setup is inside the timed region for every tracer.
// - FTZ/DAZ stay off: the renderer does not set them, so neither does its benchmark.
// - Embree is timed with rtcIntersect8 / rtcOccluded8 on our packets and with rtcIntersect16 /
//   rtcOccluded16 on pairs of consecutive packets (4x4 camera pixels); the packet targets are met
//   only against the faster of the two, so both ratios are printed.
// - The secondary rays are timed one at a time (the secondary target's cell) and also in packets: 8 per
//   call (the set's packets) and 16 (pairs of them), ours with intersect8 / intersect16 (their direction
//   signs are mixed: the per-lane walk), Embree's with rtcIntersect8 / rtcIntersect16 and the INCOHERENT
//   flag. Their ratios to rtcIntersect1 and to Embree's call of the same width are both judged against
//   the secondary target, which packets meet only where both are MET (against the faster of Embree's
//   calls, as for camera and shadow rays).
// - Hit/miss (and, among hits, shape id) of every tracer are compared with our scalar single-ray
//   path, the reference; our SIMD paths must agree exactly, Embree up to ties at shared edges.
//
// Exit codes: 0 done; 1 a scene could not be loaded or the CSV not written; 2 usage error.
// Threading: main's thread drives everything; timed runs start and join their own threads.
#include <time.h>

#include <algorithm>
#include <atomic>
#include <bit>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <functional>
#include <memory>
#include <numbers>
#include <optional>
#include <sstream>
#include <string>
#include <string_view>
#include <thread>
#include <tuple>
#include <vector>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "math/ray.h"
#include "math/rng.h"
#include "math/vec.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/generate.h"
#include "scene/load.h"

#ifdef DTRACED_BENCH_EMBREE
#include "bench/embree_tracer.h"
#endif

namespace dtraced::bench {
namespace {

using accel::Geometry;
using accel::Isa;
using accel::Shape;
using math::Ray;
using math::Vec3d;
using math::Vec3f;

#ifndef DTRACED_BENCH_EMBREE
constexpr std::uint32_t kMissId = 0xffffffffu;
#endif
constexpr int kLanes = accel::kPacketSize;
// Packets per work item handed out to a thread in the all-threads runs (512 rays).
constexpr std::size_t kChunkPackets = 64;

struct Options {
  std::string scene = "all";
  int runs = 5;
  std::uint32_t threads = 0;
  std::uint32_t width = 1024, height = 768;
  std::string isas;  // comma separated; empty = every supported one
  bool quick = false;
  std::string csv;
  std::uint64_t seed = 1;
  std::uint32_t spheres = 100'000;
  std::uint32_t small_spheres = 10;  // the "small" scene: the seed's scenes are this size
  std::uint32_t mesh_spheres = 400;
  std::uint32_t ground_quads = 200;  // mesh ground side; the spheres scene uses 128
  bool embree = true;
  std::string embree_quality = "medium";
  std::string rays = "camera,shadow,secondary";  // the ray sets to time (perf of one path)
  bool render = false;
  bool render_only = false;
  std::string render_scene = std::string(DTRACED_SOURCE_DIR) + "/scenes/showcase.json";
  std::uint32_t render_width = 1920, render_height = 1080, render_spp = 16;
  int render_runs = 3;
};

// ---------------------------------------------------------------- timing

double thread_cpu_seconds() {
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

struct Stat {
  double median = 0, min = 0, max = 0;  // Mrays/s
  bool valid = false;
};

Stat summarize(std::vector<double> v) {
  Stat s;
  if (v.empty()) return s;
  std::sort(v.begin(), v.end());
  const std::size_t n = v.size();
  s.median = n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
  s.min = v.front();
  s.max = v.back();
  s.valid = true;
  return s;
}

// Traces packets [begin, end) of a ray set.
using RangeFn = std::function<void(std::size_t, std::size_t)>;

// One warm-up, then `runs` timed passes over `packets` packets holding `rays` valid rays.
Stat measure(const RangeFn& fn, std::size_t packets, std::size_t rays, std::uint32_t threads, int runs) {
  std::vector<double> rates;
  for (int run = -1; run < runs; ++run) {
    double seconds = 0;
    if (threads <= 1) {
      const double t0 = thread_cpu_seconds();
      fn(0, packets);
      seconds = thread_cpu_seconds() - t0;
    } else {
      std::atomic<std::size_t> next{0};
      const auto t0 = std::chrono::steady_clock::now();
      {
        std::vector<std::jthread> pool;
        for (std::uint32_t i = 0; i < threads; ++i) {
          pool.emplace_back([&] {
            for (std::size_t b = next.fetch_add(kChunkPackets); b < packets; b = next.fetch_add(kChunkPackets)) {
              fn(b, std::min(packets, b + kChunkPackets));
            }
          });
        }
      }
      seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    }
    if (run >= 0) rates.push_back(double(rays) / std::max(seconds, 1e-9) / 1e6);
  }
  return summarize(std::move(rates));
}

// ---------------------------------------------------------------- scenes

struct BenchScene {
  std::string name;
  std::string description;
  std::vector<Shape> shapes;
  render::CameraF camera;
  Vec3f light;
};

class Dice {
 public:
  explicit Dice(std::uint64_t seed) : base_(math::mix64(seed ^ 0x243f6a8885a308d3ULL)) {}
  double uniform(std::uint64_t i, std::uint64_t dim) const {
    return double(math::hash_combine(math::hash_combine(base_, i), dim) >> 11) * 0x1.0p-53;
  }

 private:
  std::uint64_t base_;
};

render::CameraF make_camera(const Vec3d& position, const Vec3d& look_at, const Vec3d& up, double fov_deg) {
  // As RenderScene::build does it.
  render::CameraF c;
  c.position = position;
  c.forward = math::normalize(look_at - position);
  c.right = math::normalize(math::cross(c.forward, up));
  c.up = math::cross(c.right, c.forward);
  c.tan_half_fov = std::tan(fov_deg * std::numbers::pi / 360.0);
  return c;
}

Shape triangle(Vec3f a, Vec3f b, Vec3f c) {
  Shape s;
  s.type = accel::ShapeType::kTriangle;
  s.triangle = {a, b, c};
  return s;
}

// A flat n x n-quad grid of 2 n^2 triangles at y = 0 over [-half, half]^2, normals up.
void add_ground(std::vector<Shape>& shapes, std::uint32_t n, float half) {
  const auto at = [&](std::uint32_t i) { return -half + 2.0f * half * float(i) / float(n); };
  for (std::uint32_t j = 0; j < n; ++j) {
    for (std::uint32_t i = 0; i < n; ++i) {
      const Vec3f a{at(i), 0, at(j)}, b{at(i + 1), 0, at(j)}, c{at(i + 1), 0, at(j + 1)}, d{at(i), 0, at(j + 1)};
      shapes.push_back(triangle(a, c, b));
      shapes.push_back(triangle(a, d, c));
    }
  }
}

// Lat-long sphere: `slices` around, `stacks` from pole to pole; 2 * slices * (stacks - 1) triangles.
void add_tessellated_sphere(std::vector<Shape>& shapes, Vec3f c, float r, std::uint32_t slices, std::uint32_t stacks) {
  const auto p = [&](std::uint32_t st, std::uint32_t sl) {
    const double th = std::numbers::pi * double(st) / double(stacks);
    const double ph = 2.0 * std::numbers::pi * double(sl % slices) / double(slices);
    return c + r * Vec3f(Vec3d(std::sin(th) * std::cos(ph), std::cos(th), std::sin(th) * std::sin(ph)));
  };
  for (std::uint32_t st = 0; st < stacks; ++st) {
    for (std::uint32_t sl = 0; sl < slices; ++sl) {
      const Vec3f a = p(st, sl), b = p(st, sl + 1), cc = p(st + 1, sl + 1), d = p(st + 1, sl);
      if (st != 0) shapes.push_back(triangle(a, b, cc));
      if (st != stacks - 1) shapes.push_back(triangle(a, cc, d));
    }
  }
}

// `ground_quads` per side: 128 for the "spheres" scene; 1 (two big triangles, which stay out of the
// tree like the plane they replace) for the "small" one.
BenchScene make_spheres_scene(std::string name, std::uint32_t count, std::uint32_t ground_quads, std::uint64_t seed) {
  const scene::SceneDesc desc = scene::generate_sphere_field(count, seed);
  BenchScene s;
  s.name = std::move(name);
  for (const scene::Object& o : desc.objects) {
    if (o.type != scene::ObjectType::kSphere) continue;  // the plane becomes the triangle grid below
    Shape sh;
    sh.type = accel::ShapeType::kSphere;
    sh.sphere = {Vec3f(o.sphere.center), float(o.sphere.radius)};
    s.shapes.push_back(sh);
  }
  const std::size_t spheres = s.shapes.size();
  std::uint32_t side = 0;
  while (std::uint64_t(side) * side < count) ++side;
  const float extent = std::max(0.5f * float(side), 2.0f);
  add_ground(s.shapes, ground_quads, 3.0f * extent);
  s.description = fmt::format(
      "{} spheres (scene::generate_sphere_field, seed {}) + {} ground triangles ({}x{} quads over "
      "+-{:.0f}, replacing the generator's infinite plane) = {} primitives",
      spheres, seed, s.shapes.size() - spheres, ground_quads, ground_quads, 3.0f * extent, s.shapes.size());
  const scene::Camera& c = desc.camera;
  s.camera = make_camera(c.position, c.look_at, c.up, c.fov_deg);
  s.light = Vec3f(desc.lights.front().position);
  return s;
}

BenchScene make_mesh_scene(std::uint32_t spheres, std::uint32_t ground_quads, std::uint64_t seed) {
  constexpr std::uint32_t kSlices = 40, kStacks = 31;  // 2 * 40 * 30 = 2,400 triangles per sphere
  const Dice dice(seed);
  BenchScene s;
  s.name = "mesh";
  // Spheres overlap each other and sink a little into the ground, so the tree has overlapping
  // bounds to cope with, as in a real scene.
  const float field = 10.0f * std::sqrt(float(spheres) / 400.0f);
  for (std::uint32_t i = 0; i < spheres; ++i) {
    const float r = float(0.6 + 1.0 * dice.uniform(i, 0));
    const float x = float(-field + 2.0 * field * dice.uniform(i, 1));
    const float z = float(-field + 2.0 * field * dice.uniform(i, 2));
    add_tessellated_sphere(s.shapes, {x, 0.8f * r, z}, r, kSlices, kStacks);
  }
  const std::size_t sphere_tris = s.shapes.size();
  add_ground(s.shapes, ground_quads, 1.5f * field);
  s.description =
      fmt::format("{} triangles: {} lat-long spheres of {} triangles (seed {}) + {}x{}-quad ground of {} triangles",
                  s.shapes.size(), spheres, 2 * kSlices * (kStacks - 1), seed, ground_quads, ground_quads,
                  s.shapes.size() - sphere_tris);
  s.camera = make_camera({0, 0.9 * field, 2.4 * field}, {0, 0, 0}, {0, 1, 0}, 45);
  s.light = {0.6f * field, 2.5f * field, 1.2f * field};
  return s;
}

// ---------------------------------------------------------------- ray sets

// Rays in packets of kLanes; lane i of packet p is rays[p * kLanes + i], traced when bit i of
// valid[p] is set (invalid lanes hold a copy of a valid ray).
struct RaySet {
  std::vector<Ray> rays;
  std::vector<std::uint32_t> source;  // per lane: the shape the ray leaves (kMissId for camera rays)
  std::vector<std::uint32_t> valid;
  std::size_t count = 0;  // valid rays
  std::size_t packets() const { return valid.size(); }
  void push_packet(const Ray* lanes, const std::uint32_t* sources, std::uint32_t mask) {
    if (mask == 0) return;
    const int first = std::countr_zero(mask);
    for (int i = 0; i < kLanes; ++i) {
      rays.push_back(lanes[(mask >> i & 1u) ? i : first]);
      source.push_back(sources ? sources[i] : kMissId);
    }
    valid.push_back(mask);
    count += std::size_t(std::popcount(mask));
  }
};

struct RaySets {
  RaySet camera, shadow, secondary;
  std::size_t camera_hits = 0;
};

// Cosine-weighted direction around unit n from two uniforms (Malley's method).
Vec3f cosine_direction(const Vec3f& n, float u1, float u2) {
  const float r = std::sqrt(u1);
  const float phi = 2.0f * std::numbers::pi_v<float> * u2;
  const float x = r * std::cos(phi), y = r * std::sin(phi), z = std::sqrt(std::max(0.0f, 1.0f - u1));
  // Orthonormal basis (Duff et al. 2017).
  const float sign = std::copysign(1.0f, n.z);
  const float a = -1.0f / (sign + n.z);
  const float b = n.x * n.y * a;
  const Vec3f t{1.0f + sign * n.x * n.x * a, sign * b, -sign * n.x};
  const Vec3f bt{b, sign + n.y * n.y * a, -n.y};
  return math::normalize(t * x + bt * y + n * z);
}

// Generates the three ray sets, tracing the camera rays with the reference geometry.
RaySets make_rays(const BenchScene& s, const Geometry& reference, std::uint32_t w, std::uint32_t h,
                  std::uint64_t seed) {
  RaySets out;
  constexpr std::uint32_t kTile = 16;
  std::vector<Ray> secondary_pending;
  std::vector<std::uint32_t> secondary_source;
  std::uint64_t hit_index = 0;
  for (std::uint32_t ty = 0; ty < h; ty += kTile) {
    for (std::uint32_t tx = 0; tx < w; tx += kTile) {
      // 4x2-pixel packets, two at a time for each 4x4 block (the upper, then the lower half), so
      // that consecutive pairs are the 4x4 blocks of the 16-ray calls.
      for (std::uint32_t qy = ty; qy < std::min(h, ty + kTile); qy += 4) {
        for (std::uint32_t bx = tx; bx < std::min(w, tx + kTile); bx += 4) {
          for (std::uint32_t by = qy; by < std::min(h, qy + 4); by += 2) {
            Ray cam[kLanes], shadow[kLanes];
            std::uint32_t shadow_source[kLanes] = {};
            std::uint32_t cam_mask = 0, shadow_mask = 0;
            for (int i = 0; i < kLanes; ++i) {
              const std::uint32_t x = bx + std::uint32_t(i % 4), y = by + std::uint32_t(i / 4);
              if (x >= w || y >= h) continue;
              cam[i] = s.camera.generate(x + 0.5, y + 0.5, w, h);
              cam_mask |= 1u << i;
              accel::Hit hit;
              if (!reference.intersect(cam[i], hit)) continue;
              ++out.camera_hits;
              // The side of the surface the camera ray came from.
              const Vec3f n = math::dot(hit.n, cam[i].d) < 0 ? hit.n : -hit.n;
              const Vec3f to_light = s.light - hit.p;
              if (math::dot(n, to_light) > 0) {
                Ray& r = shadow[i];
                r.o = accel::offset_ray_origin(hit.p, hit.p_error, n, to_light);
                const Vec3f seg = s.light - r.o;
                const float len = math::length(seg);
                r.d = seg / len;
                r.t_max = len;
                shadow_mask |= 1u << i;
                shadow_source[i] = hit.shape;
              }
              const math::SampleKey key{seed, 0, x, y, 0};
              Ray b;
              b.d = cosine_direction(n, math::sample_uniform(key, 0), math::sample_uniform(key, 1));
              b.o = accel::offset_ray_origin(hit.p, hit.p_error, n, b.d);
              secondary_pending.push_back(b);
              secondary_source.push_back(hit.shape);
              ++hit_index;
            }
            out.camera.push_packet(cam, nullptr, cam_mask);
            out.shadow.push_packet(shadow, shadow_source, shadow_mask);
          }
        }
      }
    }
  }
  for (std::size_t i = 0; i < secondary_pending.size(); i += kLanes) {
    const std::size_t n = std::min<std::size_t>(kLanes, secondary_pending.size() - i);
    Ray lanes[kLanes];
    std::uint32_t sources[kLanes] = {};
    std::copy_n(secondary_pending.begin() + std::ptrdiff_t(i), n, lanes);
    std::copy_n(secondary_source.begin() + std::ptrdiff_t(i), n, sources);
    out.secondary.push_packet(lanes, sources, n == kLanes ? 0xffu : (1u << n) - 1);
  }
  return out;
}

// ---------------------------------------------------------------- tracers

enum class SetKind { kCamera, kShadow, kSecondary };
constexpr SetKind kSets[] = {SetKind::kCamera, SetKind::kShadow, SetKind::kSecondary};
constexpr std::string_view set_name(SetKind k) {
  return k == SetKind::kCamera ? "camera" : k == SetKind::kShadow ? "shadow" : "secondary";
}

// Per-ray answers of one tracer on one set: shape id or kMissId (closest hit), 1/0 (shadow).
using Answers = std::vector<std::uint32_t>;

struct Mismatch {
  std::size_t hit = 0;       // hit/miss (or occluded/free) disagreements
  std::size_t id = 0;        // both hit, different shape
  std::size_t self = 0;      // of those, the tracer hit the very shape the ray leaves (self-intersection)
  std::size_t ref_self = 0;  // of those, the reference hit the very shape the ray leaves
};

// For shadow sets, which shape a tracer's ray k hit (closest), to tell self-intersections apart;
// nullptr when unknown.
using WhatHit = std::function<std::uint32_t(std::size_t)>;

Mismatch compare(const RaySet& set, const Answers& a, const Answers& ref, const WhatHit& what_hit = nullptr,
                 const WhatHit& what_ref_hit = nullptr) {
  Mismatch m;
  for (std::size_t p = 0; p < set.packets(); ++p) {
    for (int i = 0; i < kLanes; ++i) {
      if (!(set.valid[p] >> i & 1u)) continue;
      const std::size_t k = p * kLanes + std::size_t(i);
      if (a[k] == ref[k]) continue;
      if ((a[k] == kMissId) != (ref[k] == kMissId)) {
        ++m.hit;
      } else {
        ++m.id;
      }
      if (set.source[k] == kMissId) continue;
      if (a[k] != kMissId && (what_hit ? what_hit(k) : a[k]) == set.source[k]) ++m.self;
      if (ref[k] != kMissId && (what_ref_hit ? what_ref_hit(k) : ref[k]) == set.source[k]) ++m.ref_self;
    }
  }
  return m;
}

struct Cell {
  bool measured = false;
  std::string method;  // e.g. "intersect8"
  Stat one, all;
  Mismatch mismatch;
};

struct Row {
  std::string tracer;
  Cell cells[3];  // camera, shadow, secondary
};

// Builds a RangeFn for set `set` writing into `out` from a per-packet function.
using PacketFn = std::function<void(const Ray*, std::uint32_t, std::uint32_t*)>;

struct Runner {
  const Options& opt;
  std::uint32_t threads;
  const RaySets& sets;
  // Whether --rays leaves `set` out: its cells stay unmeasured (and its answers all misses).
  bool skipped(const RaySet& set) const {
    const char* name = &set == &sets.camera ? "camera" : &set == &sets.shadow ? "shadow" : "secondary";
    std::stringstream ss(opt.rays);
    std::string item;
    while (std::getline(ss, item, ',')) {
      if (item == name) return false;
    }
    return true;
  }
  Cell run(const std::string& method, const RaySet& set, const PacketFn& per_packet, Answers& out) const {
    out.assign(set.rays.size(), kMissId);
    if (skipped(set)) return Cell{};
    const RangeFn fn = [&](std::size_t b, std::size_t e) {
      for (std::size_t p = b; p < e; ++p) per_packet(&set.rays[p * kLanes], set.valid[p], &out[p * kLanes]);
    };
    Cell c;
    c.measured = true;
    c.method = method;
    c.one = measure(fn, set.packets(), set.count, 1, opt.runs);
    if (threads > 1) c.all = measure(fn, set.packets(), set.count, threads, opt.runs);
    return c;
  }
  // As run, with two consecutive packets per call of 16 rays (`per_pair` gets 16 rays, a 16-bit
  // valid mask and 16 answers): camera packets 2k and 2k + 1 are the two halves of a 4x4-pixel
  // block. A last odd packet is padded with a copy of itself (lanes 8-15 invalid).
  Cell run_pairs(const std::string& method, const RaySet& set, const PacketFn& per_pair, Answers& out) const {
    out.assign(set.rays.size(), kMissId);
    if (skipped(set)) return Cell{};
    const std::size_t n = set.packets();
    const RangeFn fn = [&](std::size_t b, std::size_t e) {
      for (std::size_t p = b; p < e; p += 2) {  // b is even: chunks are kChunkPackets long
        if (p + 1 < e) {
          per_pair(&set.rays[p * kLanes], set.valid[p] | set.valid[p + 1] << kLanes, &out[p * kLanes]);
          continue;
        }
        Ray rays[2 * kLanes];
        std::uint32_t ids[2 * kLanes];
        std::copy_n(&set.rays[p * kLanes], kLanes, rays);
        std::copy_n(&set.rays[p * kLanes], kLanes, rays + kLanes);
        std::fill_n(ids, 2 * kLanes, kMissId);
        per_pair(rays, set.valid[p], ids);
        std::copy_n(ids, kLanes, &out[p * kLanes]);
      }
    };
    Cell c;
    c.measured = true;
    c.method = method;
    c.one = measure(fn, n, set.count, 1, opt.runs);
    if (threads > 1) c.all = measure(fn, n, set.count, threads, opt.runs);
    return c;
  }
};

// Closest shape hit by ray k of a set (for classifying shadow-ray disagreements), outside timing.
WhatHit ours_what_hit(const Geometry& g, const RaySet& set) {
  return [&g, &set](std::size_t k) {
    accel::Hit hit;
    return g.intersect(set.rays[k], hit) ? hit.shape : kMissId;
  };
}

PacketFn ours_single_intersect(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* ids) {
    for (int i = 0; i < kLanes; ++i) {
      if (!(valid >> i & 1u)) continue;
      accel::Hit hit;
      ids[i] = g.intersect(rays[i], hit) ? hit.shape : kMissId;
    }
  };
}
PacketFn ours_single_occluded(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* blocked) {
    for (int i = 0; i < kLanes; ++i) {
      if (valid >> i & 1u) blocked[i] = g.occluded(rays[i]) ? 1u : kMissId;
    }
  };
}
PacketFn ours_intersect8(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* ids) {
    accel::Hit hits[kLanes];
    const std::uint32_t found = g.intersect8(rays, valid, hits);
    for (int i = 0; i < kLanes; ++i) {
      if (valid >> i & 1u) ids[i] = (found >> i & 1u) ? hits[i].shape : kMissId;
    }
  };
}
PacketFn ours_occluded8(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* blocked) {
    const std::uint32_t b = g.occluded8(rays, valid);
    for (int i = 0; i < kLanes; ++i) {
      if (valid >> i & 1u) blocked[i] = (b >> i & 1u) ? 1u : kMissId;
    }
  };
}

// Our 16-ray calls on two consecutive packets (Runner::run_pairs).
PacketFn ours_intersect16(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* ids) {
    accel::Hit hits[2 * kLanes];
    const std::uint32_t found = g.intersect16(rays, valid, hits);
    for (int i = 0; i < 2 * kLanes; ++i) {
      if (valid >> i & 1u) ids[i] = (found >> i & 1u) ? hits[i].shape : kMissId;
    }
  };
}
PacketFn ours_occluded16(const Geometry& g) {
  return [&g](const Ray* rays, std::uint32_t valid, std::uint32_t* blocked) {
    const std::uint32_t b = g.occluded16(rays, valid);
    for (int i = 0; i < 2 * kLanes; ++i) {
      if (valid >> i & 1u) blocked[i] = (b >> i & 1u) ? 1u : kMissId;
    }
  };
}

// ---------------------------------------------------------------- output

std::string fmt_rate(const Stat& s) {
  if (!s.valid) return "-";
  return fmt::format("{:.2f} [{:.2f}-{:.2f}]", s.median, s.min, s.max);
}

std::string with_commas(std::uint64_t v) {
  const std::string digits = std::to_string(v);
  std::string s;
  for (std::size_t i = 0; i < digits.size(); ++i) {
    if (i > 0 && (digits.size() - i) % 3 == 0) s += ',';
    s += digits[i];
  }
  return s;
}

std::string cpu_model() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind("model name", 0) == 0) {
      const auto colon = line.find(':');
      if (colon != std::string::npos) return line.substr(std::min(line.size(), colon + 2));
    }
  }
  return "unknown CPU";
}

class Csv {
 public:
  bool open(const std::string& path) {
    if (path.empty()) return true;
    out_.open(path);
    if (!out_) return false;
    out_ << "scene,tracer,rays,method,threads,count,median_mrays_s,min_mrays_s,max_mrays_s,hit_mismatches,"
            "id_mismatches\n";
    return true;
  }
  void row(const std::string& scene, const std::string& tracer, SetKind set, const Cell& c, std::uint32_t threads,
           std::size_t count, const Stat& s) {
    if (!out_.is_open() || !s.valid) return;
    out_ << fmt::format("{},{},{},{},{},{},{:.4f},{:.4f},{:.4f},{},{}\n", scene, tracer, set_name(set), c.method,
                        threads, count, s.median, s.min, s.max, c.mismatch.hit, c.mismatch.id);
  }
  void render_row(const std::string& isa, std::uint32_t threads, double median, double min, double max) {
    if (!out_.is_open()) return;
    out_ << fmt::format("render,{},image,render_local,{},1,{:.4f},{:.4f},{:.4f},0,0\n", isa, threads, median, min, max);
  }
  bool ok() const { return !out_.is_open() || out_.good(); }

 private:
  std::ofstream out_;
};

void print_table(const std::vector<Row>& rows, bool all, std::uint32_t threads, int runs) {
  if (all) {
    fmt::print("\nMrays/s, {} threads (wall time), median [min-max] of {} runs after 1 warm-up:\n", threads, runs);
  } else {
    fmt::print("\nMrays/s, 1 thread (thread CPU time), median [min-max] of {} runs after 1 warm-up:\n", runs);
  }
  fmt::print("  {:<16} {:>24} {:>24} {:>24}\n", "tracer", "camera", "shadow", "secondary");
  for (const Row& r : rows) {
    fmt::print("  {:<16}", r.tracer);
    for (const Cell& c : r.cells) fmt::print(" {:>24}", c.measured ? fmt_rate(all ? c.all : c.one) : "-");
    fmt::print("\n");
  }
}

void print_methods_and_mismatches(const std::vector<Row>& rows) {
  fmt::print(
      "\nCalls, and disagreements with 'scalar single' (the reference): hit/miss (shape id among hits) [of "
      "all these, how many times this tracer / the reference hit the very surface the ray leaves]:\n");
  fmt::print("  {:<16} {:>30} {:>30} {:>30}\n", "tracer", "camera", "shadow", "secondary");
  for (const Row& r : rows) {
    fmt::print("  {:<16}", r.tracer);
    for (const Cell& c : r.cells) {
      fmt::print(" {:>30}", c.measured ? fmt::format("{} {} ({}) [{}/{}]", c.method, c.mismatch.hit, c.mismatch.id,
                                                     c.mismatch.self, c.mismatch.ref_self)
                                       : "-");
    }
    fmt::print("\n");
  }
}

const Row* find_row(const std::vector<Row>& rows, std::string_view name) {
  for (const Row& r : rows) {
    if (r.tracer == name) return &r;
  }
  return nullptr;
}

void print_ratio(std::string_view label, const Row* num, const Row* den, SetKind set, double target) {
  const std::size_t k = std::size_t(set);
  if (!num || !den || !num->cells[k].measured || !den->cells[k].measured) {
    fmt::print("  {:<68} {:>8}   target >= {:.1f}   (not measured)\n", label, "-", target);
    return;
  }
  const double r1 = num->cells[k].one.median / den->cells[k].one.median;
  std::string all;
  if (num->cells[k].all.valid && den->cells[k].all.valid) {
    all = fmt::format("   (all threads {:.2f}x)", num->cells[k].all.median / den->cells[k].all.median);
  }
  fmt::print("  {:<68} {:>7.2f}x   target >= {:.1f}   {}{}\n", label, r1, target, r1 >= target ? "MET" : "MISSED", all);
}

// ---------------------------------------------------------------- the ray benchmark of one scene

std::vector<Isa> chosen_isas(const Options& opt) {
  const std::vector<Isa> supported = accel::supported_isas();
  if (opt.isas.empty()) return supported;
  std::vector<Isa> out;
  std::stringstream ss(opt.isas);
  std::string name;
  while (std::getline(ss, name, ',')) {
    const std::optional<Isa> isa = accel::parse_isa(name);
    if (!isa) {
      fmt::print("note: unknown isa '{}' skipped\n", name);
      continue;
    }
    if (std::find(supported.begin(), supported.end(), *isa) == supported.end()) {
      fmt::print("note: isa {} skipped: not supported by this build or CPU\n", accel::isa_name(*isa));
      continue;
    }
    if (std::find(out.begin(), out.end(), *isa) == out.end()) out.push_back(*isa);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// What the parts of one scene's ray benchmark share: the scene, its ray sets, the scalar reference
// geometry and its answers, and the rows measured so far.
struct SceneBench {
  const BenchScene& scene;
  const Options& opt;
  Runner runner;
  const Geometry& reference;
  const RaySets& sets;
  Answers ref[3];  // the reference's answers, per set
  std::vector<Row> rows;

  const RaySet& set(std::size_t k) const {
    const RaySet* of[3] = {&sets.camera, &sets.shadow, &sets.secondary};
    return *of[k];
  }
};

// The instruction sets this build or CPU cannot run, as notes.
void note_unsupported_isas() {
  const std::vector<Isa> supported = accel::supported_isas();
  for (Isa isa : {Isa::kSse4, Isa::kAvx2, Isa::kAvx512}) {
    if (std::find(supported.begin(), supported.end(), isa) == supported.end()) {
      fmt::print("note: isa {} skipped: not supported by this build or CPU\n", accel::isa_name(isa));
    }
  }
}

std::string build_line(const Geometry& g) {
  const accel::BuildStats& b = g.stats();
  return fmt::format("  {:<8} {:>9.3f} {:>13.3f} {:>10} {:>11} {:>9} {:>10}", accel::isa_name(g.isa()), b.seconds,
                     b.wide_seconds, b.nodes, b.wide_nodes, b.leaves, b.max_depth);
}

// Our rows: the scalar reference's single rays (whose answers every other row is compared with),
// then packets on each chosen isa. Returns one line of build statistics per geometry.
std::vector<std::string> add_our_rows(SceneBench& b, const std::vector<Isa>& isas) {
  std::vector<std::string> build_lines = {build_line(b.reference)};
  {
    Row r{"scalar single", {}};
    r.cells[0] = b.runner.run("intersect", b.sets.camera, ours_single_intersect(b.reference), b.ref[0]);
    r.cells[1] = b.runner.run("occluded", b.sets.shadow, ours_single_occluded(b.reference), b.ref[1]);
    r.cells[2] = b.runner.run("intersect", b.sets.secondary, ours_single_intersect(b.reference), b.ref[2]);
    b.rows.push_back(r);
  }
  Answers answers;
  const auto packet_row = [&](const std::string& name, const Geometry& g) {
    Row r{name, {}};
    r.cells[0] = b.runner.run("intersect8", b.sets.camera, ours_intersect8(g), answers);
    r.cells[0].mismatch = compare(b.sets.camera, answers, b.ref[0]);
    r.cells[1] = b.runner.run("occluded8", b.sets.shadow, ours_occluded8(g), answers);
    r.cells[1].mismatch = compare(b.sets.shadow, answers, b.ref[1], ours_what_hit(g, b.sets.shadow),
                                  ours_what_hit(b.reference, b.sets.shadow));
    r.cells[2] = b.runner.run("intersect", b.sets.secondary, ours_single_intersect(g), answers);
    r.cells[2].mismatch = compare(b.sets.secondary, answers, b.ref[2]);
    b.rows.push_back(r);
  };
  if (std::find(isas.begin(), isas.end(), Isa::kScalar) != isas.end()) packet_row("scalar packet", b.reference);
  for (Isa isa : isas) {
    if (isa == Isa::kScalar) continue;
    const Geometry g = Geometry::build(b.scene.shapes, isa);  // one SIMD geometry alive at a time
    build_lines.push_back(build_line(g));
    packet_row(std::string(accel::isa_name(isa)), g);
    // Packets of 16 (two of the set's packets per call: 4x4 camera pixels), camera and shadow.
    Row r{fmt::format("{} x16", accel::isa_name(isa)), {}};
    r.cells[0] = b.runner.run_pairs("intersect16", b.sets.camera, ours_intersect16(g), answers);
    r.cells[0].mismatch = compare(b.sets.camera, answers, b.ref[0]);
    r.cells[1] = b.runner.run_pairs("occluded16", b.sets.shadow, ours_occluded16(g), answers);
    r.cells[1].mismatch = compare(b.sets.shadow, answers, b.ref[1], ours_what_hit(g, b.sets.shadow),
                                  ours_what_hit(b.reference, b.sets.shadow));
    // The secondary rays as packets too (their direction signs are mixed): 16 per call here, 8 in
    // a row of their own. The single-ray cell above stays the secondary target's.
    r.cells[2] = b.runner.run_pairs("intersect16", b.sets.secondary, ours_intersect16(g), answers);
    r.cells[2].mismatch = compare(b.sets.secondary, answers, b.ref[2]);
    b.rows.push_back(r);
    Row r8{fmt::format("{} x8", accel::isa_name(isa)), {}};
    r8.cells[2] = b.runner.run("intersect8", b.sets.secondary, ours_intersect8(g), answers);
    r8.cells[2].mismatch = compare(b.sets.secondary, answers, b.ref[2]);
    b.rows.push_back(r8);
  }
  return build_lines;
}

#ifdef DTRACED_BENCH_EMBREE
// Embree's occlusion answers are 0 (free) or 1 (blocked); ours write kMissId for free.
void mark_free_as_miss(std::uint32_t valid, std::uint32_t* out) {
  for (int i = 0; i < kLanes; ++i) {
    if ((valid >> i & 1u) && out[i] == 0) out[i] = kMissId;
  }
}

// Embree's rows on the very same primitives and rays. Returns the note that describes them.
std::string add_embree_rows(SceneBench& b) {
  const Options& opt = b.opt;
  const EmbreeQuality q = opt.embree_quality == "high"  ? EmbreeQuality::kHigh
                          : opt.embree_quality == "low" ? EmbreeQuality::kLow
                                                        : EmbreeQuality::kMedium;
  util::Result<std::unique_ptr<EmbreeTracer>> built = EmbreeTracer::build(b.scene.shapes, q, 0);
  if (!built) return fmt::format("embree: skipped, build failed: {}", built.error().message);
  const std::unique_ptr<EmbreeTracer> e = std::move(built).value();
  const std::string note = fmt::format(
      "embree {}: RTC_BUILD_QUALITY_{}, spheres as RTC_GEOMETRY_TYPE_SPHERE_POINT, triangles as "
      "RTC_GEOMETRY_TYPE_TRIANGLE: the same primitives as ours{}; build {:.3f} s wall on Embree's own threads.\n"
      "  What differs: Embree accepts hits in [tnear, tfar], ours in the open (t_min, t_max); Embree tests "
      "spheres in float, ours in double; our triangle test is watertight, Embree's default build is not. "
      "'embree 1' passes the COHERENT flag for camera and shadow rays, INCOHERENT for secondary ones, as "
      "'embree 8' and 'embree 16' do for the secondary packets",
      EmbreeTracer::version(),
      opt.embree_quality == "high"  ? "HIGH"
      : opt.embree_quality == "low" ? "LOW"
                                    : "MEDIUM",
      e->skipped() ? fmt::format(" ({} boxes/planes left out)", e->skipped()) : std::string(), e->build_seconds());
  const EmbreeTracer& et = *e;
  Answers answers;
  const auto cell = [&](std::size_t k, const std::string& method, const PacketFn& fn, bool pairs = false) {
    Cell c = pairs ? b.runner.run_pairs(method, b.set(k), fn, answers) : b.runner.run(method, b.set(k), fn, answers);
    // An occlusion answer does not say what was hit: ask rtcIntersect1, outside the timing.
    const WhatHit embree_hit = [&](std::size_t i) {
      std::uint32_t id = kMissId;
      et.intersect1(&b.set(k).rays[i], 1u, &id, /*coherent=*/false);
      return id;
    };
    c.mismatch = compare(b.set(k), answers, b.ref[k], k == 1 ? embree_hit : WhatHit(),
                         k == 1 ? ours_what_hit(b.reference, b.sets.shadow) : WhatHit());
    return c;
  };
  // Embree's entry points as packet functions; occlusion answers marked as ours are.
  using Method = void (EmbreeTracer::*)(const Ray*, std::uint32_t, std::uint32_t*, bool) const;
  const auto intersect = [&et](Method m, bool coherent) -> PacketFn {
    return [&et, m, coherent](const Ray* r, std::uint32_t v, std::uint32_t* o) { (et.*m)(r, v, o, coherent); };
  };
  const auto occluded = [&et](Method m) -> PacketFn {
    return [&et, m](const Ray* r, std::uint32_t v, std::uint32_t* o) {
      (et.*m)(r, v, o, /*coherent=*/true);
      mark_free_as_miss(v, o);
      mark_free_as_miss(v >> kLanes, o + kLanes);  // the second packet of a 16-ray call
    };
  };
  Row r1{"embree 1", {}};
  r1.cells[0] = cell(0, "rtcIntersect1", intersect(&EmbreeTracer::intersect1, /*coherent=*/true));
  r1.cells[1] = cell(1, "rtcOccluded1", occluded(&EmbreeTracer::occluded1));
  r1.cells[2] = cell(2, "rtcIntersect1", intersect(&EmbreeTracer::intersect1, /*coherent=*/false));
  b.rows.push_back(r1);
  Row r8{"embree 8", {}};
  r8.cells[0] = cell(0, "rtcIntersect8", intersect(&EmbreeTracer::intersect8, /*coherent=*/true));
  r8.cells[1] = cell(1, "rtcOccluded8", occluded(&EmbreeTracer::occluded8));
  r8.cells[2] = cell(2, "rtcIntersect8", intersect(&EmbreeTracer::intersect8, /*coherent=*/false));
  b.rows.push_back(r8);
  Row r16{"embree 16", {}};
  r16.cells[0] = cell(0, "rtcIntersect16", intersect(&EmbreeTracer::intersect16, /*coherent=*/true), true);
  r16.cells[1] = cell(1, "rtcOccluded16", occluded(&EmbreeTracer::occluded16), true);
  r16.cells[2] = cell(2, "rtcIntersect16", intersect(&EmbreeTracer::intersect16, /*coherent=*/false), true);
  b.rows.push_back(r16);
  return note;
}
#endif

// The targets, from the 1-thread medians. "Best isa" is the highest instruction set measured.
void print_targets(const BenchScene& s, const std::vector<Isa>& isas, const std::vector<Row>& rows) {
  const Row* best_row =
      isas.empty() ? nullptr
                   : find_row(rows, isas.back() == Isa::kScalar ? "scalar packet" : accel::isa_name(isas.back()));
  const std::string best_name = best_row ? best_row->tracer : "-";
  const Row* scalar = find_row(rows, "scalar single");
  const Row* e1 = find_row(rows, "embree 1");
  const Row* e8 = find_row(rows, "embree 8");
  const Row* e16 = find_row(rows, "embree 16");
  const Row* best16 = best_row ? find_row(rows, best_row->tracer + " x16") : nullptr;
  fmt::print("\nTargets (1-thread medians; best isa = {}):\n", best_name);
  const double camera_target = s.name == "mesh" ? 1.0 : 1.5;
  // Our 8- and then 16-ray packets against the same anchors; the issue takes the faster of our
  // calls and the faster of Embree's.
  for (const auto& [ours, width] : {std::pair{best_row, 8}, std::pair{best16, 16}}) {
    print_ratio(fmt::format("camera: {} intersect{} / scalar single-ray intersect", best_name, width), ours, scalar,
                SetKind::kCamera, 3.0);
    for (const auto& [embree, embree_width] : {std::pair{e8, 8}, std::pair{e16, 16}}) {
      print_ratio(
          fmt::format("camera: {} intersect{} / embree rtcIntersect{} (coherent)", best_name, width, embree_width),
          ours, embree, SetKind::kCamera, camera_target);
    }
    for (const auto& [embree, embree_width] : {std::pair{e8, 8}, std::pair{e16, 16}}) {
      print_ratio(
          fmt::format("shadow: {} occluded{} / embree rtcOccluded{} (coherent)", best_name, width, embree_width), ours,
          embree, SetKind::kShadow, 1.0);
    }
    if (width == 8) {
      print_ratio(fmt::format("secondary: {} intersect / embree rtcIntersect1 (incoherent)", best_name), ours, e1,
                  SetKind::kSecondary, 0.8);
    }
  }
  // The secondary rays in packets of 8 and 16 against the same single-ray anchor and against
  // Embree's packet call of the same width on the same packets: met only where both are.
  const Row* best8 = best_row ? find_row(rows, best_row->tracer + " x8") : nullptr;
  for (const auto& [ours, width, embree] : {std::tuple{best8, 8, e8}, std::tuple{best16, 16, e16}}) {
    print_ratio(fmt::format("secondary: {} intersect{} / embree rtcIntersect1 (incoherent)", best_name, width), ours,
                e1, SetKind::kSecondary, 0.8);
    print_ratio(fmt::format("secondary: {} intersect{} / embree rtcIntersect{} (incoherent)", best_name, width, width),
                ours, embree, SetKind::kSecondary, 0.8);
  }
  std::fflush(stdout);
}

void bench_scene(const BenchScene& s, const Options& opt, std::uint32_t threads, Csv& csv) {
  fmt::print("\n==== scene '{}': {}\n", s.name, s.description);
  note_unsupported_isas();
  const std::vector<Isa> isas = chosen_isas(opt);

  // The reference: scalar geometry, single rays. It also generates the shadow and secondary rays.
  const Geometry reference = Geometry::build(s.shapes, Isa::kScalar);
  const RaySets sets = make_rays(s, reference, opt.width, opt.height, opt.seed);
  fmt::print(
      "ray sets: camera {} rays ({}x{}, 1 spp, 4x2-pixel packets, pairs of them 4x4 blocks in 16x16 tiles, {} packets, "
      "{} hit); shadow {} "
      "rays ({} packets, to the point light at ({:g}, {:g}, {:g}), t_max = distance, only where the light is in "
      "front); secondary {} rays (1 cosine-weighted bounce per hit, seed {}, traced one at a time)\n",
      with_commas(sets.camera.count), opt.width, opt.height, with_commas(sets.camera.packets()),
      with_commas(sets.camera_hits), with_commas(sets.shadow.count), with_commas(sets.shadow.packets()), s.light.x,
      s.light.y, s.light.z, with_commas(sets.secondary.count), opt.seed);

  SceneBench b{s, opt, Runner{opt, threads, sets}, reference, sets, {}, {}};
  const std::vector<std::string> build_lines = add_our_rows(b, isas);
  std::string embree_note;
#ifdef DTRACED_BENCH_EMBREE
  embree_note = opt.embree ? add_embree_rows(b) : "embree: off (--no-embree)";
#else
  embree_note = "embree: not compiled in (configure with -DDTRACED_BENCH_EMBREE=ON and libembree-dev)";
#endif

  fmt::print("\nBVH build (ours; Geometry::stats()):\n  {:<8} {:>9} {:>13} {:>10} {:>11} {:>9} {:>10}\n", "isa",
             "seconds", "wide_seconds", "nodes", "wide_nodes", "leaves", "max_depth");
  for (const std::string& l : build_lines) fmt::print("{}\n", l);
  fmt::print("{}\n", embree_note);

  std::fflush(stdout);
  print_table(b.rows, /*all=*/false, 1, opt.runs);
  if (threads > 1) print_table(b.rows, /*all=*/true, threads, opt.runs);
  print_methods_and_mismatches(b.rows);

  for (const Row& r : b.rows) {
    for (SetKind k : kSets) {
      const Cell& c = r.cells[std::size_t(k)];
      if (!c.measured) continue;
      csv.row(s.name, r.tracer, k, c, 1, b.set(std::size_t(k)).count, c.one);
      csv.row(s.name, r.tracer, k, c, threads, b.set(std::size_t(k)).count, c.all);
    }
  }
  print_targets(s, isas, b.rows);
}

// ---------------------------------------------------------------- whole renders

int bench_render(const Options& opt, std::uint32_t threads, Csv& csv) {
  const scene::LoadResult loaded = scene::load_scene_file(opt.render_scene);
  if (!loaded.ok()) {
    fmt::print(stderr, "{}", scene::format_errors(loaded.errors));
    return 1;
  }
  scene::RenderSettings settings = loaded.scene->render;
  settings.width = opt.render_width;
  settings.height = opt.render_height;
  settings.samples = opt.render_spp;
  fmt::print(
      "\n==== whole render: {} at {}x{}, {} spp, max depth {}, {} threads, render::render_local, median "
      "[min-max] of {} runs after a 1-spp warm-up (wall time, scene build excluded)\n",
      opt.render_scene, settings.width, settings.height, settings.samples, settings.max_depth, threads,
      opt.render_runs);
  std::vector<Isa> isas{Isa::kScalar};
  if (accel::best_isa() != Isa::kScalar) isas.push_back(accel::best_isa());
  std::vector<double> medians;
  std::vector<image::ImageRGBf> images;
  for (Isa isa : isas) {
    const render::RenderScene rs = render::RenderScene::build(*loaded.scene, isa);
    render::LocalOptions lo;
    lo.threads = threads;
    std::vector<double> secs;
    std::uint64_t rays = 0;
    // Warm-up at 1 spp: first touches of the scene and the image's pages are not part of a render.
    scene::RenderSettings warm = settings;
    warm.samples = 1;
    (void)render::render_local(rs, warm, lo);
    for (int i = 0; i < opt.render_runs; ++i) {
      render::LocalResult r = render::render_local(rs, settings, lo);
      secs.push_back(r.seconds);
      rays = r.stats.rays;
      if (i == 0) images.push_back(std::move(r.image));
    }
    std::sort(secs.begin(), secs.end());
    const double med =
        secs.size() % 2 ? secs[secs.size() / 2] : 0.5 * (secs[secs.size() / 2 - 1] + secs[secs.size() / 2]);
    medians.push_back(med);
    fmt::print("  {:<8} {:>8.3f} s [{:.3f}-{:.3f}]  {} rays, {:.2f} Mrays/s\n", accel::isa_name(isa), med, secs.front(),
               secs.back(), with_commas(rays), double(rays) / med / 1e6);
    csv.render_row(std::string(accel::isa_name(isa)), threads, med, secs.front(), secs.back());
  }
  if (isas.size() > 1) {
    const bool same =
        images[0].rgb.size() == images[1].rgb.size() &&
        std::memcmp(images[0].rgb.data(), images[1].rgb.data(), images[0].rgb.size() * sizeof(float)) == 0;
    fmt::print("  speed-up {} / scalar: {:.2f}x; images bitwise identical: {}\n", accel::isa_name(isas[1]),
               medians[0] / medians[1], same ? "yes" : "NO");
  } else {
    fmt::print("  speed-up: - (no SIMD isa available; scalar only)\n");
  }
  std::fflush(stdout);
  return 0;
}

int run(int argc, char** argv) {
  Options opt;
  CLI::App app{"dtraced-bench-rays: ray throughput of dtraced's traversal paths vs Embree, and whole-render speed-up"};
  app.add_option("--scene", opt.scene, "Scenes to benchmark")
      ->check(CLI::IsMember({"spheres", "mesh", "small", "all"}));
  app.add_option("--runs", opt.runs, "Timed runs per measurement (after 1 warm-up)")->check(CLI::Range(1, 1000));
  app.add_option("--threads", opt.threads, "Threads of the all-threads columns (0 = every hardware thread)");
  app.add_option("--width", opt.width, "Camera ray set width")->check(CLI::Range(1u, 16384u));
  app.add_option("--height", opt.height, "Camera ray set height")->check(CLI::Range(1u, 16384u));
  app.add_option("--isa", opt.isas,
                 "Comma-separated isas to measure (scalar,sse4,avx2,avx512; default: all supported)");
  app.add_flag("--quick", opt.quick, "Small scenes, rays and renders, 3 runs: a smoke run");
  app.add_option("--csv", opt.csv, "Also write every measurement to this CSV file");
  app.add_option("--seed", opt.seed, "Seed of scenes and bounce directions");
  app.add_option("--spheres", opt.spheres, "Spheres of the 'spheres' scene")->check(CLI::Range(1u, 1'000'000u));
  app.add_option("--small-spheres", opt.small_spheres, "Spheres of the 'small' scene (no tree below 64 shapes)")
      ->check(CLI::Range(1u, 1'000u));
  app.add_option("--mesh-spheres", opt.mesh_spheres, "Tessellated spheres (2,400 triangles each) of the 'mesh' scene")
      ->check(CLI::Range(1u, 100'000u));
  app.add_flag("!--no-embree", opt.embree, "Leave Embree out");
  app.add_option("--rays", opt.rays, "Comma-separated ray sets to time (camera,shadow,secondary; default all)")
      ->check(CLI::Validator(
          [](const std::string& list) -> std::string {
            std::stringstream ss(list);
            std::string item;
            while (std::getline(ss, item, ',')) {
              if (item != "camera" && item != "shadow" && item != "secondary") {
                return "unknown ray set '" + item + "' (camera, shadow or secondary)";
              }
            }
            return {};
          },
          "LIST"));
  app.add_option("--embree-quality", opt.embree_quality, "Embree build quality")
      ->check(CLI::IsMember({"low", "medium", "high"}));
  app.add_flag("--render", opt.render, "Also time whole renders (scalar vs best isa) with render::render_local");
  app.add_flag("--render-only", opt.render_only, "Only the whole-render benchmark");
  app.add_option("--render-scene", opt.render_scene, "Scene of the whole-render benchmark");
  app.add_option("--render-width", opt.render_width, "Whole-render width")->check(CLI::Range(1u, 16384u));
  app.add_option("--render-height", opt.render_height, "Whole-render height")->check(CLI::Range(1u, 16384u));
  app.add_option("--render-spp", opt.render_spp, "Whole-render samples per pixel")->check(CLI::Range(1u, 65536u));
  app.add_option("--render-runs", opt.render_runs, "Whole renders per isa")->check(CLI::Range(1, 100));
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (opt.quick) {
    // Explicit flags still win over the quick defaults.
    if (app.count("--runs") == 0) opt.runs = 3;
    if (app.count("--width") == 0) opt.width = 256;
    if (app.count("--height") == 0) opt.height = 192;
    if (app.count("--spheres") == 0) opt.spheres = 10'000;
    if (app.count("--mesh-spheres") == 0) opt.mesh_spheres = 40;
    opt.ground_quads = 64;
    if (app.count("--render-width") == 0) opt.render_width = 192;
    if (app.count("--render-height") == 0) opt.render_height = 108;
    if (app.count("--render-spp") == 0) opt.render_spp = 2;
    if (app.count("--render-runs") == 0) opt.render_runs = 1;
  }
  const std::uint32_t hw = std::max(1u, std::thread::hardware_concurrency());
  const std::uint32_t threads = opt.threads ? opt.threads : hw;

  Csv csv;
  if (!csv.open(opt.csv)) {
    fmt::print(stderr, "cannot write {}\n", opt.csv);
    return 1;
  }

  std::string isas;
  for (Isa isa : accel::supported_isas()) isas += fmt::format("{}{}", isas.empty() ? "" : " ", accel::isa_name(isa));
  fmt::print(
      "dtraced-bench-rays: {}; {} hardware threads; supported isas: {}; g++ {}; {}; FTZ/DAZ off (as in the "
      "renderer)\n",
      cpu_model(), hw, isas, __VERSION__,
#ifdef DTRACED_BENCH_EMBREE
      fmt::format("Embree {}", EmbreeTracer::version())
#else
      std::string("without Embree")
#endif
  );

  if (!opt.render_only) {
    if (opt.scene == "spheres" || opt.scene == "all")
      bench_scene(make_spheres_scene("spheres", opt.spheres, 128, opt.seed), opt, threads, csv);
    if (opt.scene == "small" || opt.scene == "all")
      bench_scene(make_spheres_scene("small", opt.small_spheres, 1, opt.seed), opt, threads, csv);
    if (opt.scene == "mesh" || opt.scene == "all") {
      bench_scene(make_mesh_scene(opt.mesh_spheres, opt.ground_quads, opt.seed), opt, threads, csv);
    }
  }
  if (opt.render || opt.render_only) {
    if (const int rc = bench_render(opt, threads, csv); rc != 0) return rc;
  }
  if (!csv.ok()) {
    fmt::print(stderr, "error writing {}\n", opt.csv);
    return 1;
  }
  return 0;
}

}  // namespace
}  // namespace dtraced::bench

int main(int argc, char** argv) { return dtraced::bench::run(argc, argv); }
