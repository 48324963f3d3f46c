// The packets' any-hit (occluded8 / occluded16) triangle test on rays aimed exactly at a mesh's
// vertices and edge midpoints: there the float edge functions come out zero and the lanes are
// redone in double, and a blocked lane must be blocked whatever else the packet's lanes do. Every
// isa's answers must equal the scalar path's ray by ray, and the mesh must block every such ray
// whose t_max lies beyond it and none whose t_max lies before it.
#include <cstdint>
#include <vector>

#include <catch2/catch.hpp>

#include "accel/geometry.h"
#include "accel/isa.h"
#include "shape_builders.h"

using namespace dtraced::accel;
using namespace dtraced::testing;
using dtraced::math::Ray;
using dtraced::math::Vec3f;

namespace {

// An n x n grid of quads (2 triangles each) on y = 0, cells of side 1 from (-n/2, 0, -n/2).
std::vector<Shape> grid(int n) {
  std::vector<Shape> out;
  auto at = [&](int i, int j) { return Vec3f{float(i - n / 2), 0.0f, float(j - n / 2)}; };
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      out.push_back(triangle(at(i, j), at(i + 1, j), at(i + 1, j + 1)));
      out.push_back(triangle(at(i, j), at(i + 1, j + 1), at(i, j + 1)));
    }
  }
  return out;
}

// Rays from points above the grid to its inner vertices and edge midpoints (exact in float),
// direction not normalised, so t = 1 at the target: t_max 2 passes the grid, 0.5 stops short.
// Origins alternate between two points (packets of mixed and of shared direction signs).
std::vector<Ray> edge_rays(int n, float t_max) {
  std::vector<Ray> rays;
  const Vec3f origins[2] = {{0.25f, 3.0f, -0.75f}, {-2.5f, 5.0f, 1.5f}};
  int k = 0;
  for (int i = 1; i < n; ++i) {
    for (int j = 1; j < n; ++j) {
      for (const Vec3f& target :
           {Vec3f{float(i - n / 2), 0.0f, float(j - n / 2)}, Vec3f{float(i - n / 2) + 0.5f, 0.0f, float(j - n / 2)},
            Vec3f{float(i - n / 2) + 0.5f, 0.0f, float(j - n / 2) + 0.5f}}) {
        Ray r;
        r.o = origins[k++ % 2];
        r.d = target - r.o;
        r.t_max = t_max;
        rays.push_back(r);
      }
    }
  }
  return rays;
}

}  // namespace

TEST_CASE("packet any-hit tests block rays through a mesh's edges and vertices as the scalar path", "[simd]") {
  const int n = 12;
  const std::vector<Shape> shapes = grid(n);
  const Geometry ref = Geometry::build(shapes, Isa::kScalar);
  for (const float t_max : {2.0f, 0.5f}) {
    const std::vector<Ray> rays = edge_rays(n, t_max);
    for (const Isa isa : supported_isas()) {
      const Geometry geo = Geometry::build(shapes, isa);
      int wrong = 0, wrong8 = 0, wrong16 = 0, blocked = 0;
      for (std::size_t base = 0; base + kPacketSize16 <= rays.size(); base += kPacketSize16) {
        const std::uint32_t b16 = geo.occluded16(&rays[base], 0xffffu);
        const std::uint32_t b8 = geo.occluded8(&rays[base], 0xffu) | geo.occluded8(&rays[base + 8], 0xffu) << 8;
        // Every other lane only: a blocked lane's answer must not depend on its neighbours.
        const std::uint32_t b16_half = geo.occluded16(&rays[base], 0x5555u);
        for (int i = 0; i < kPacketSize16; ++i) {
          const bool want = ref.occluded(rays[base + std::size_t(i)]);
          blocked += want;
          wrong += want != (t_max > 1.0f);
          wrong8 += want != bool(b8 >> i & 1u);
          wrong16 += want != bool(b16 >> i & 1u);
          if (i % 2 == 0) wrong16 += want != bool(b16_half >> i & 1u);
          if (i % 2 == 1) wrong16 += (b16_half >> i & 1u) != 0;
        }
      }
      INFO("isa " << isa_name(isa) << ", t_max " << t_max << ", " << rays.size() << " rays, " << blocked << " blocked");
      CHECK(wrong == 0);
      CHECK(wrong8 == 0);
      CHECK(wrong16 == 0);
    }
  }
}

// Packets whose lanes share their direction signs but each lie in a plane x, y or z = const (a
// direction component +0): every axis has a lane with an infinite inverse, so the coherent walk's
// frustum constrains no axis and passes every slot of a node, empty ones (child kEmptyChild)
// included; only the lane tests keep the walk out of those. The answers must be the scalar
// path's, for nearest and any hits, on a field of small triangles (a tree of several levels
// whose nodes have empty slots).
TEST_CASE("packets with a zero direction component on every axis walk the tree as the scalar path", "[simd]") {
  std::vector<Shape> shapes;
  for (int i = 0; i < 12; ++i) {
    for (int j = 0; j < 12; ++j) {
      for (int k = 0; k < 6; ++k) {
        const Vec3f c{float(i), float(j), float(2 * k) + 0.25f * float((i + j) % 3)};
        shapes.push_back(triangle(c, c + Vec3f{0.8f, 0.1f, 0.3f}, c + Vec3f{0.2f, 0.9f, -0.4f}));
      }
    }
  }
  const Geometry ref = Geometry::build(shapes, Isa::kScalar);
  std::vector<Ray> rays;
  for (int q = 0; q < 16 * 24; ++q) {
    const float s = 0.37f * float(q % 16), u = 0.11f * float(q / 16);
    const Vec3f o{-1.0f + s, -1.0f + u, -2.0f + 0.5f * s};
    Vec3f d{1.0f + 0.01f * s, 0.7f + 0.02f * u, 0.9f};
    // Lanes 0-2 of every 4 zero one axis each (+0: the sign stays that of the other lanes).
    if (q % 4 == 0) d.x = 0.0f;
    if (q % 4 == 1) d.y = 0.0f;
    if (q % 4 == 2) d.z = 0.0f;
    rays.push_back(make_ray(o, d, 0.0f, q % 3 == 0 ? 8.0f : kInf));
  }
  for (const Isa isa : supported_isas()) {
    const Geometry geo = Geometry::build(shapes, isa);
    int wrong = 0, hits = 0;
    for (std::size_t base = 0; base + kPacketSize16 <= rays.size(); base += kPacketSize16) {
      Hit h16[kPacketSize16], h8[kPacketSize16];
      const std::uint32_t f16 = geo.intersect16(&rays[base], 0xffffu, h16);
      const std::uint32_t f8 = geo.intersect8(&rays[base], 0xffu, h8) | geo.intersect8(&rays[base + 8], 0xffu, h8 + 8)
                                                                            << 8;
      const std::uint32_t b16 = geo.occluded16(&rays[base], 0xffffu);
      const std::uint32_t b8 = geo.occluded8(&rays[base], 0xffu) | geo.occluded8(&rays[base + 8], 0xffu) << 8;
      for (int i = 0; i < kPacketSize16; ++i) {
        Hit want;
        const bool found = ref.intersect(rays[base + std::size_t(i)], want);
        hits += found;
        wrong += found != bool(f16 >> i & 1u) || found != bool(f8 >> i & 1u);
        if (found && (f16 >> i & 1u)) wrong += h16[i].shape != want.shape || h16[i].t != want.t;
        if (found && (f8 >> i & 1u)) wrong += h8[i].shape != want.shape || h8[i].t != want.t;
        const bool blocked = ref.occluded(rays[base + std::size_t(i)]);
        wrong += blocked != bool(b16 >> i & 1u) || blocked != bool(b8 >> i & 1u);
      }
    }
    INFO("isa " << isa_name(isa) << ", " << rays.size() << " rays, " << hits << " hit");
    CHECK(hits > 0);
    CHECK(wrong == 0);
  }
}
