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
