// Tests of the two-level geometry (accel/layered.h) of animated scenes (render::StaticPart,
// render::AnimatedScene) and of static scenes split by transparency: over random splits of random
// scenes, two layers answer every query (single rays, 8- and 16-ray packets, every instruction set
// this machine has) exactly as a brute-force search over all the shapes (or one Geometry) does; a
// frame built on a shared static layer renders the same bits as the same frame built whole, alone
// or after other frames; a static scene without a compact glass part keeps its one Geometry.
#include <bit>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "accel/layered.h"
#include "render/render_scene.h"
#include "render_checks.h"
#include "scene/animation.h"
#include "scene_builders.h"
#include "shape_builders.h"

using namespace dtraced;
using namespace dtraced::testing;
using accel::Hit;
using accel::Isa;
using accel::Layer;
using accel::LayeredGeometry;
using accel::Shape;

namespace {

// Spheres, boxes, triangles and a plane in a cube of side 20, with exact copies of some shapes
// (ties in t between the layers, which the smaller id must win).
std::vector<Shape> mixed_shapes(std::uint64_t seed, int count) {
  TestRng rng{seed};
  std::vector<Shape> out;
  out.push_back(testing::plane({0, -10, 0}, {0, 1, 0}));
  while (int(out.size()) < count) {
    const int kind = rng.index(4);
    const Vec3f c = to_f(rng.in_cube(10));
    if (kind == 0) {
      const float r = float(rng.uniform(0.1, 1.5));
      out.push_back(testing::sphere(c, r));
    } else if (kind == 1) {
      const Vec3f h = to_f(Vec3d{rng.uniform(0.1, 1), rng.uniform(0.1, 1), rng.uniform(0.1, 1)});
      out.push_back(testing::box(c - h, c + h));
    } else if (kind == 2) {
      const Vec3f a = c + to_f(rng.unit());
      const Vec3f b = c + to_f(rng.unit());
      out.push_back(testing::triangle(c, a, b));
    } else {
      out.push_back(out[std::size_t(rng.index(int(out.size())))]);  // a copy: same t, another id
    }
  }
  return out;
}

struct Split {
  std::shared_ptr<const Layer> fixed, moving;
};

// The shapes flagged in `moving` go to one layer, the others to the other, ids kept.
Split split(const std::vector<Shape>& shapes, const std::vector<bool>& moving, Isa isa) {
  std::vector<Shape> a, b;
  std::vector<std::uint32_t> ia, ib;
  for (std::uint32_t i = 0; i < shapes.size(); ++i) {
    (moving[i] ? b : a).push_back(shapes[i]);
    (moving[i] ? ib : ia).push_back(i);
  }
  return {Layer::build(std::move(a), std::move(ia), isa), Layer::build(std::move(b), std::move(ib), isa)};
}

Ray random_ray(TestRng& rng) {
  const Vec3f o = to_f(rng.in_cube(12));
  const Vec3f d = unit_f(rng.unit());
  // Now and then a bounded ray (a shadow ray towards a light) or one starting past its origin.
  const float t_max = rng.index(4) == 0 ? float(rng.uniform(0.5, 20)) : kInf;
  const float t_min = rng.index(4) == 0 ? float(rng.uniform(0, 2)) : 0.0f;
  return make_ray(o, d, t_min, t_max);
}

// Every query of `g` on `rays` random rays equals the brute-force answer over `shapes`.
void check_against_brute_force(const LayeredGeometry& g, const std::vector<Shape>& shapes, std::uint64_t seed,
                               int rays) {
  TestRng rng{seed};
  int hits = 0;
  for (int n = 0; n < rays; n += accel::kPacketSize) {
    Ray packet[accel::kPacketSize];
    Hit want[accel::kPacketSize];
    bool found[accel::kPacketSize];
    for (int i = 0; i < accel::kPacketSize; ++i) {
      packet[i] = random_ray(rng);
      found[i] = brute_force(shapes, packet[i], want[i]);
      Hit got;
      INFO(describe(packet[i]));
      REQUIRE(g.intersect(packet[i], got) == found[i]);
      if (found[i]) REQUIRE(same_hit(got, want[i]));
      REQUIRE(g.occluded(packet[i]) == found[i]);
      hits += found[i] ? 1 : 0;
    }
    const std::uint32_t valid = rng.index(3) == 0 ? std::uint32_t(rng.next() & 0xffu) : 0xffu;
    Hit got[accel::kPacketSize];
    const std::uint32_t hit_mask = g.intersect8(packet, valid, got) & valid;
    const std::uint32_t blocked = g.occluded8(packet, valid);
    for (int i = 0; i < accel::kPacketSize; ++i) {
      if (!(valid >> i & 1u)) continue;
      INFO("lane " << i << ": " << describe(packet[i]));
      REQUIRE(bool(hit_mask >> i & 1u) == found[i]);
      if (found[i]) REQUIRE(same_hit(got[i], want[i]));
      REQUIRE(bool(blocked >> i & 1u) == found[i]);
    }
  }
  // The rays must meet the shapes often enough for the comparison to mean something.
  CHECK(hits > rays / 4);
}

}  // namespace

TEST_CASE("two layers answer every ray as a brute-force search over all the shapes", "[accel][layers]") {
  // 400 shapes: both layers large enough for the 8-wide BVH in some splits, small in others.
  const std::vector<Shape> shapes = mixed_shapes(11, 400);
  for (const Isa isa : accel::supported_isas()) {
    for (const int every : {2, 7, 50}) {
      CAPTURE(accel::isa_name(isa), every);
      std::vector<bool> moving(shapes.size());
      TestRng rng{std::uint64_t(every)};
      for (std::size_t i = 0; i < shapes.size(); ++i) moving[i] = rng.index(every) == 0;
      const Split s = split(shapes, moving, isa);
      const LayeredGeometry g(s.fixed, s.moving, shapes.size());
      REQUIRE(g.fixed() != nullptr);
      REQUIRE(g.moving() != nullptr);
      for (std::uint32_t id = 0; id < shapes.size(); ++id) {
        REQUIRE(g.shape(id).type == shapes[id].type);
      }
      check_against_brute_force(g, shapes, 100 + std::uint64_t(every), 4000);
    }
  }
}

namespace {

// `g` holds two copies of one sphere, ids 0 and 1, one in each layer: every query, single and 8
// and 16 rays at a time, must hit id 0.
void check_tie_to_smaller_id(const LayeredGeometry& g) {
  Hit hit;
  REQUIRE(g.intersect(make_ray({0, 0, 0}, {0, 0, 1}), hit));
  CHECK(hit.shape == 0);
  Ray rays[accel::kPacketSize16];
  for (Ray& r : rays) r = make_ray({0, 0, 0}, {0, 0, 1});
  Hit hits[accel::kPacketSize16];
  REQUIRE(g.intersect16(rays, 0xffffu, hits) == 0xffffu);
  for (const Hit& h : hits) CHECK(h.shape == 0);
  REQUIRE(g.intersect8(rays, 0xffu, hits) == 0xffu);
  for (int i = 0; i < accel::kPacketSize; ++i) CHECK(hits[i].shape == 0);
}

}  // namespace

TEST_CASE("a hit at the same t in both layers goes to the smaller scene-wide id", "[accel][layers]") {
  const std::vector<Shape> shapes = {testing::sphere({0, 0, 5}, 1), testing::sphere({0, 0, 5}, 1)};
  for (const bool first_moves : {false, true}) {
    const Split s = split(shapes, {first_moves, !first_moves}, Isa::kScalar);
    check_tie_to_smaller_id(LayeredGeometry(s.fixed, s.moving, shapes.size()));
  }
}

TEST_CASE("a layered geometry with one empty layer answers as the other alone", "[accel][layers]") {
  const std::vector<Shape> shapes = mixed_shapes(5, 120);
  for (const Isa isa : accel::supported_isas()) {
    for (const bool all_moving : {false, true}) {
      CAPTURE(accel::isa_name(isa), all_moving);
      const Split s = split(shapes, std::vector<bool>(shapes.size(), all_moving), isa);
      const LayeredGeometry g(s.fixed, s.moving, shapes.size());
      check_against_brute_force(g, shapes, 7, 800);
    }
  }
}

namespace {

// A static scene split by transparency (LayeredGeometry's third constructor): the opaque layer
// holds every shape at its id with the transparent ones holes, the transparent layer those with
// their ids. `clear` flags the transparent shapes.
LayeredGeometry split_by(const std::vector<Shape>& shapes, const std::vector<bool>& clear, Isa isa) {
  std::vector<Shape> opaque = shapes, glass;
  std::vector<std::uint32_t> ids;
  for (std::uint32_t i = 0; i < shapes.size(); ++i) {
    if (!clear[i]) continue;
    glass.push_back(shapes[i]);
    ids.push_back(i);
    opaque[i] = LayeredGeometry::hole();
  }
  return LayeredGeometry(accel::Geometry::build(std::move(opaque), isa),
                         Layer::build(std::move(glass), std::move(ids), isa));
}

// Every query of a split geometry, 1, 8 and 16 rays at a time, against brute force: the queries
// over both layers against all the shapes, occluded_opaque against the opaque ones and
// intersect_transparent against the transparent ones (ids scene-wide). Rays start near the
// transparent part or anywhere, so that its bounding sphere both culls rays and lets rays through
// that pass just inside it. Returns how many rays the transparent layer's queries hit.
int check_split(const LayeredGeometry& g, const std::vector<Shape>& shapes, const std::vector<bool>& clear,
                const Vec3f& near, std::uint64_t seed, int rays) {
  std::vector<Shape> opaque = shapes, glass = shapes;
  for (std::size_t i = 0; i < shapes.size(); ++i) (clear[i] ? opaque : glass)[i] = LayeredGeometry::hole();
  TestRng rng{seed};
  int hits = 0, glass_hits = 0;
  for (int n = 0; n < rays; n += accel::kPacketSize16) {
    Ray packet[accel::kPacketSize16];
    Hit want[accel::kPacketSize16], want_glass[accel::kPacketSize16];
    bool found[accel::kPacketSize16], blocked[accel::kPacketSize16], crossed[accel::kPacketSize16];
    for (int i = 0; i < accel::kPacketSize16; ++i) {
      packet[i] = random_ray(rng);
      if (rng.index(2) == 0) {  // aimed at the transparent part, now and then off by a little
        packet[i].d = unit_f(Vec3d(near - packet[i].o) + rng.in_cube(rng.index(2) == 0 ? 0.05 : 2.0));
      }
      found[i] = brute_force(shapes, packet[i], want[i]);
      Hit unused;
      blocked[i] = brute_force(opaque, packet[i], unused);
      crossed[i] = brute_force(glass, packet[i], want_glass[i]);
      INFO(describe(packet[i]));
      Hit got;
      REQUIRE(g.intersect(packet[i], got) == found[i]);
      if (found[i]) REQUIRE(same_hit(got, want[i]));
      REQUIRE(g.occluded(packet[i]) == found[i]);
      REQUIRE(g.occluded_opaque(packet[i]) == blocked[i]);
      REQUIRE(g.intersect_transparent(packet[i], got) == crossed[i]);
      if (crossed[i]) REQUIRE(same_hit(got, want_glass[i]));
      hits += found[i] ? 1 : 0;
      glass_hits += crossed[i] ? 1 : 0;
    }
    const std::uint32_t valid = rng.index(3) == 0 ? std::uint32_t(rng.next() & 0xffffu) : 0xffffu;
    for (const int width : {accel::kPacketSize, accel::kPacketSize16}) {
      for (int base = 0; base < accel::kPacketSize16; base += width) {
        const std::uint32_t lanes = (valid >> base) & ((1u << width) - 1);
        const Ray* r = packet + base;
        Hit got[accel::kPacketSize16], got_glass[accel::kPacketSize16];
        std::uint32_t hit_mask, occluded, opaque_mask, glass_mask;
        if (width == accel::kPacketSize) {
          hit_mask = g.intersect8(r, lanes, got) & lanes;
          occluded = g.occluded8(r, lanes);
          opaque_mask = g.occluded_opaque<accel::kPacketSize>(r, lanes);
          glass_mask = g.intersect_transparent<accel::kPacketSize>(r, lanes, got_glass);
        } else {
          hit_mask = g.intersect16(r, lanes, got) & lanes;
          occluded = g.occluded16(r, lanes);
          opaque_mask = g.occluded_opaque<accel::kPacketSize16>(r, lanes);
          glass_mask = g.intersect_transparent<accel::kPacketSize16>(r, lanes, got_glass);
        }
        for (int i = 0; i < width; ++i) {
          const int k = base + i;
          if (!(lanes >> i & 1u)) continue;
          INFO(width << "-ray packet, lane " << i << ": " << describe(packet[k]));
          REQUIRE(bool(hit_mask >> i & 1u) == found[k]);
          if (found[k]) REQUIRE(same_hit(got[i], want[k]));
          REQUIRE(bool(occluded >> i & 1u) == found[k]);
          REQUIRE(bool(opaque_mask >> i & 1u) == blocked[k]);
          REQUIRE(bool(glass_mask >> i & 1u) == crossed[k]);
          if (crossed[k]) REQUIRE(same_hit(got_glass[i], want_glass[k]));
        }
      }
    }
  }
  CHECK(hits > rays / 4);
  return glass_hits;
}

}  // namespace

TEST_CASE("a static scene split by transparency answers every query as one Geometry over all shapes",
          "[accel][layers]") {
  // 400 shapes with copies (ties in t, across the layers too); the transparent ones those within
  // 4.5 of a point (a compact part, so its bounding sphere culls), or every fifth shape with the
  // plane among them (the bounds unbounded: nothing culled).
  const std::vector<Shape> shapes = mixed_shapes(23, 400);
  const Vec3f near{1.5f, -2.0f, 0.5f};
  for (const Isa isa : accel::supported_isas()) {
    for (const bool compact : {true, false}) {
      CAPTURE(accel::isa_name(isa), compact);
      std::vector<bool> clear(shapes.size());
      int count = 0;
      for (std::size_t i = 0; i < shapes.size(); ++i) {
        const math::Bounds3f b = accel::shape_bounds(shapes[i]);
        clear[i] = compact ? !b.empty() && math::length(b.centroid() - near) < 4.5f : i % 5 == 0;
        count += clear[i] ? 1 : 0;
      }
      REQUIRE(count > 4);
      const LayeredGeometry g = split_by(shapes, clear, isa);
      REQUIRE(g.transparent() != nullptr);
      REQUIRE(g.moving() == nullptr);
      REQUIRE(g.fixed()->ids.empty());
      REQUIRE(g.fixed()->geometry.shapes().size() == shapes.size());
      for (std::uint32_t id = 0; id < shapes.size(); ++id) {
        REQUIRE(std::memcmp(&g.shape(id), &shapes[id], sizeof(Shape)) == 0);
      }
      const int glass_hits = check_split(g, shapes, clear, near, compact ? 31 : 37, 4000);
      CHECK(glass_hits > 100);
    }
  }
}

// The transparent part one glass box (and a triangle across its diagonal): its bounding sphere
// is tightest at the box's corners, where the rays aimed at them graze it.
TEST_CASE("a split scene's culled transparent layer keeps the rays that graze its corners", "[accel][layers]") {
  std::vector<Shape> shapes = mixed_shapes(29, 200);
  const Vec3f lo{1.0f, -1.0f, 0.5f}, hi{2.5f, 0.25f, 3.0f};
  shapes.push_back(testing::box(lo, hi));
  shapes.push_back(testing::triangle(lo, hi, Vec3f{lo.x, hi.y, lo.z}));
  shapes.push_back(testing::box(lo, hi));  // an opaque copy: ties across the layers
  std::vector<bool> clear(shapes.size(), false);
  clear[200] = clear[201] = true;
  for (const Isa isa : accel::supported_isas()) {
    CAPTURE(accel::isa_name(isa));
    const LayeredGeometry g = split_by(shapes, clear, isa);
    int glass_hits = 0;
    for (int c = 0; c < 8; ++c) {
      const Vec3f corner{c & 1 ? hi.x : lo.x, c & 2 ? hi.y : lo.y, c & 4 ? hi.z : lo.z};
      glass_hits += check_split(g, shapes, clear, corner, 50 + std::uint64_t(c), 800);
    }
    CHECK(glass_hits > 200);
  }
}

// Past the size where the build sets a sphere scene's shapes aside (bvh.cpp): the opaque layer's
// holes are invalid spheres among 40,000 valid ones.
TEST_CASE("a large split sphere scene answers every query as one Geometry over all shapes", "[accel][layers]") {
  std::vector<Shape> shapes;
  for (int i = 0; i < 34; ++i) {
    for (int j = 0; j < 34; ++j) {
      for (int k = 0; k < 35; ++k) {
        shapes.push_back(testing::sphere(Vec3f{-10.0f + 0.6f * i, -10.0f + 0.6f * j, -10.0f + 0.6f * k}, 0.2f));
      }
    }
  }
  REQUIRE(shapes.size() == 40460);
  const Vec3f near{2.0f, -1.0f, 3.0f};
  std::vector<bool> clear(shapes.size());
  int count = 0;
  for (std::size_t i = 0; i < shapes.size(); ++i) {
    clear[i] = math::length(shapes[i].sphere.center - near) < 2.0f;
    count += clear[i] ? 1 : 0;
  }
  REQUIRE(count > 50);
  const Isa isa = accel::best_isa();
  CAPTURE(accel::isa_name(isa));
  const LayeredGeometry g = split_by(shapes, clear, isa);
  REQUIRE(g.fixed()->geometry.stats().wide_nodes > 1);
  CHECK(check_split(g, shapes, clear, near, 61, 480) > 20);
}

// Directions far from unit length, down to where their squares are subnormal: the transparent
// layer's bounding-sphere cull must keep every ray that one Geometry over all shapes would send
// into it (a cull that trusted a subnormal dd dropped rays aimed straight at the glass).
TEST_CASE("a split scene answers rays with tiny and huge directions as one Geometry", "[accel][layers]") {
  const std::vector<Shape> shapes = mixed_shapes(23, 400);
  const Vec3f near{1.5f, -2.0f, 0.5f};
  std::vector<bool> clear(shapes.size());
  for (std::size_t i = 0; i < shapes.size(); ++i) {
    const math::Bounds3f b = accel::shape_bounds(shapes[i]);
    clear[i] = !b.empty() && math::length(b.centroid() - near) < 4.5f;
  }
  for (const Isa isa : accel::supported_isas()) {
    CAPTURE(accel::isa_name(isa));
    const accel::Geometry whole = accel::Geometry::build(shapes, isa);
    const LayeredGeometry g = split_by(shapes, clear, isa);
    REQUIRE(g.transparent() != nullptr);
    TestRng rng{71};
    int hits = 0;
    for (const float scale : {1e-21f, 3e-23f, 1e-30f, 1e-12f, 1e12f}) {
      INFO("direction scale " << scale);
      for (int n = 0; n < 400; n += accel::kPacketSize16) {
        Ray packet[accel::kPacketSize16];
        for (Ray& r : packet) {
          const Vec3f o = to_f(rng.in_cube(12));
          const Vec3f d = unit_f(Vec3d(near - o) + rng.in_cube(rng.index(2) == 0 ? 0.05 : 2.0));
          r = make_ray(o, d * scale, 0.0f, kInf);
        }
        Hit want[accel::kPacketSize16], got[accel::kPacketSize16];
        const std::uint32_t found = whole.intersect16(packet, 0xffffu, want) & 0xffffu;
        REQUIRE((g.intersect16(packet, 0xffffu, got) & 0xffffu) == found);
        for (int i = 0; i < accel::kPacketSize16; ++i) {
          INFO("lane " << i << ": " << describe(packet[i]));
          if (found >> i & 1u) REQUIRE(same_hit(got[i], want[i]));
          Hit one, all;
          REQUIRE(g.intersect(packet[i], one) == whole.intersect(packet[i], all));
          if (found >> i & 1u) REQUIRE(same_hit(one, all));
        }
        hits += std::popcount(found);
      }
    }
    CHECK(hits > 1000);
  }
  // A direction of 2^50 from 16,383 away: ww dd overflows to infinity while wd^2 stays finite.
  std::vector<Shape> big;
  for (int i = 0; i < 70; ++i) big.push_back(testing::sphere(Vec3f{-3000.0f + 80.0f * i, 4000.0f, 0.0f}, 5.0f));
  big.push_back(testing::box(Vec3f{-250, -250, -250}, Vec3f{250, 250, 250}));
  std::vector<bool> glass(big.size(), false);
  glass.back() = true;
  for (const Isa isa : accel::supported_isas()) {
    CAPTURE(accel::isa_name(isa));
    const accel::Geometry whole = accel::Geometry::build(big, isa);
    const LayeredGeometry g = split_by(big, glass, isa);
    REQUIRE(g.transparent() != nullptr);
    Ray rays[accel::kPacketSize16];
    for (Ray& r : rays) r = make_ray({-200, 0, -16383}, Vec3f{0, 0, 0x1p50f}, 0.0f, kInf);
    Hit want, got, hits[accel::kPacketSize16];
    REQUIRE(whole.intersect(rays[0], want));
    REQUIRE(want.shape == 70);
    REQUIRE(g.intersect(rays[0], got));
    CHECK(same_hit(got, want));
    REQUIRE(g.intersect16(rays, 0xffffu, hits) == 0xffffu);
    for (const Hit& h : hits) CHECK(same_hit(h, want));
  }
}

TEST_CASE("a split scene's hit at the same t in both layers goes to the smaller scene-wide id", "[accel][layers]") {
  const std::vector<Shape> shapes = {testing::sphere({0, 0, 5}, 1), testing::sphere({0, 0, 5}, 1)};
  for (const Isa isa : accel::supported_isas()) {
    for (const bool first_clear : {false, true})
      check_tie_to_smaller_id(split_by(shapes, {first_clear, !first_clear}, isa));
  }
}

// ---- render scenes ---------------------------------------------------------------------------

namespace {

// A scene of every kind of object: the bundled mesh scene (a triangle mesh, boxes, spheres, a
// plane), plus 70 small spheres (so the static layer gets the 8-wide BVH) and a glass sphere
// around the camera (so camera_media walks the layers).
scene::SceneDesc busy_scene() {
  scene::SceneDesc d = bundled_scene("mesh", 40, 30);
  d.render.samples = 2;
  TestRng rng{3};
  for (int i = 0; i < 70; ++i) {
    d.objects.push_back(testing::sphere(rng.in_cube(3) + d.camera.look_at, 0.15, diffuse({0.3, 0.6, 0.9})));
  }
  d.objects.push_back(testing::sphere(d.camera.position, 0.5, glass(1.3)));
  return d;
}

// Which objects move: every third one that is not a mesh (the test moves them itself).
std::vector<bool> every_third(const scene::SceneDesc& d) {
  std::vector<bool> moving(d.objects.size());
  for (std::size_t i = 0; i < d.objects.size(); ++i) {
    moving[i] = i % 3 == 1 && d.objects[i].type != scene::ObjectType::kMesh;
  }
  return moving;
}

// Frame k by hand (until scenes animate): the moving spheres and boxes shifted by k / 4 along x.
scene::SceneDesc frame_of(const scene::SceneDesc& d, const std::vector<bool>& moving, std::uint32_t k) {
  scene::SceneDesc f = d;
  f.render.frame = k;
  const math::Vec3d shift{0.25 * k, 0, 0};
  for (std::size_t i = 0; i < f.objects.size(); ++i) {
    if (!moving[i]) continue;
    scene::Object& o = f.objects[i];
    if (o.type == scene::ObjectType::kSphere) o.sphere.center = o.sphere.center + shift;
    if (o.type == scene::ObjectType::kBox) {
      o.box.min = o.box.min + shift;
      o.box.max = o.box.max + shift;
    }
  }
  return f;
}

}  // namespace

TEST_CASE("a frame built on a shared static layer renders the bits of the frame built whole", "[render][layers]") {
  const scene::SceneDesc base = busy_scene();
  const std::vector<bool> moving = every_third(base);
  for (const Isa isa : accel::supported_isas()) {
    CAPTURE(accel::isa_name(isa));
    const std::shared_ptr<const render::StaticPart> part = render::StaticPart::build(base, moving, isa);
    for (const std::uint32_t k : {0u, 3u, 7u}) {
      CAPTURE(k);
      const scene::SceneDesc f = frame_of(base, moving, k);
      const render::RenderScene layered = render::RenderScene::build_frame(f, *part);
      const render::RenderScene whole = render::RenderScene::build(f, isa);
      REQUIRE(layered.geometry().moving() != nullptr);
      REQUIRE(layered.geometry().fixed() == part->layer.get());  // shared, not rebuilt
      REQUIRE(layered.camera_media() == whole.camera_media());
      REQUIRE_FALSE(whole.camera_media().empty());
      require_identical(render_tiled(whole, f.render, 16, 8, true), render_tiled(layered, f.render, 16, 8, true));
      require_identical(render_tiled(whole, f.render, 7, 5, false), render_tiled(layered, f.render, 7, 5, false));
    }
  }
}

TEST_CASE("frame k built alone renders the bits of frame k built after other frames", "[render][layers]") {
  const scene::SceneDesc base = busy_scene();
  const std::vector<bool> moving = every_third(base);
  const scene::SceneDesc f5 = frame_of(base, moving, 5);
  const auto alone_part = render::StaticPart::build(base, moving, accel::best_isa());
  const render::RenderScene alone = render::RenderScene::build_frame(f5, *alone_part);

  const auto part = render::StaticPart::build(base, moving, accel::best_isa());
  for (const std::uint32_t k : {0u, 1u, 2u, 9u})
    (void)render::RenderScene::build_frame(frame_of(base, moving, k), *part);
  const render::RenderScene after = render::RenderScene::build_frame(f5, *part);
  require_identical(render_tiled(alone, f5.render, 16, 16, true), render_tiled(after, f5.render, 16, 16, true));
  // And the motion shows: frame 0 is another image.
  const scene::SceneDesc f0 = frame_of(base, moving, 0);
  const render::RenderScene zero = render::RenderScene::build_frame(f0, *part);
  CHECK(render_tiled(zero, f5.render, 16, 16, true).rgb != render_tiled(after, f5.render, 16, 16, true).rgb);
}

TEST_CASE("a static scene keeps its one Geometry and renders as before", "[render][layers]") {
  const scene::SceneDesc d = busy_scene();
  REQUIRE_FALSE(scene::is_animated(d));
  const render::AnimatedScene prepared = render::AnimatedScene::prepare(d);
  CHECK_FALSE(prepared.animated());
  const std::shared_ptr<const render::RenderScene> f0 = prepared.frame(0), f3 = prepared.frame(3);
  CHECK(f0 == f3);  // one RenderScene for every frame
  CHECK(f0->geometry().moving() == nullptr);
  CHECK(f0->geometry().fixed()->ids.empty());  // ids as given: the one Geometry of today
  CHECK(f0->geometry().shape_count() == f0->geometry().fixed()->geometry.shapes().size());
  const render::RenderScene built = render::RenderScene::build(d);
  require_identical(render_tiled(built, d.render, 16, 16, true), render_tiled(*f3, d.render, 16, 16, true));
}

TEST_CASE("an animated scene moves its tracked objects and shares the layer of the others", "[render][layers]") {
  // Loc tracks on every tenth of the small spheres: they fly 2 units along x over one second.
  scene::SceneDesc d = busy_scene();
  auto animation = std::make_shared<scene::Animation>();
  const std::size_t first_small = d.objects.size() - 71;
  std::vector<bool> want(d.objects.size(), false);
  for (std::size_t i = first_small; i < d.objects.size() - 1; i += 10) {
    scene::Track track;
    track.target = scene::Target::kObjectLoc;
    track.index = static_cast<std::uint32_t>(i);
    const math::Vec3d c = d.objects[i].sphere.center;
    track.keys = {{0.0, c}, {1.0, c + math::Vec3d{2, 0, 0}}};
    animation->tracks.push_back(track);
    want[i] = true;
  }
  d.animation = animation;
  REQUIRE(scene::moving_objects(d) == want);
  const render::AnimatedScene prepared = render::AnimatedScene::prepare(d);
  REQUIRE(prepared.animated());
  CHECK(prepared.static_part()->moving == want);
  for (const std::uint32_t k : {12u, 0u, 24u}) {
    CAPTURE(k);
    const std::shared_ptr<const render::RenderScene> f = prepared.frame(k);
    CHECK(f->geometry().fixed() == prepared.static_part()->layer.get());
    CHECK(f->geometry().moving()->geometry.shapes().size() == 7);
    const scene::SceneDesc at = scene::scene_at_frame(d, k);
    require_identical(render_tiled(render::RenderScene::build(at), at.render, 16, 16, true),
                      render_tiled(*f, at.render, 16, 16, true));
  }
  // The spheres do move: frame 24's sphere is 2 units from frame 0's.
  const math::Vec3d c0 = scene::scene_at_frame(d, 0).objects[first_small].sphere.center;
  const math::Vec3d c24 = scene::scene_at_frame(d, 24).objects[first_small].sphere.center;
  CHECK(c24.x - c0.x == Approx(2.0));
}

TEST_CASE("an animated scene's frame n is scene_at_frame(n) with the static layer shared", "[render][layers]") {
  scene::SceneDesc d = busy_scene();
  d.animation = std::make_shared<const scene::Animation>();
  const std::vector<bool> moving = every_third(d);
  const render::AnimatedScene prepared = render::AnimatedScene::prepare(d, moving);
  REQUIRE(prepared.animated());
  REQUIRE(prepared.static_part() != nullptr);
  const std::shared_ptr<const render::RenderScene> a = prepared.frame(4), b = prepared.frame(6);
  CHECK(a != b);
  CHECK(a->geometry().fixed() == prepared.static_part()->layer.get());
  CHECK(b->geometry().fixed() == prepared.static_part()->layer.get());
  const scene::SceneDesc f4 = scene::scene_at_frame(d, 4);
  require_identical(render_tiled(render::RenderScene::build(f4), f4.render, 16, 16, true),
                    render_tiled(*a, f4.render, 16, 16, true));
}
