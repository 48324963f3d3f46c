// dtraced::accel single-shape entry points: validity, bounds, the full hit record (point, normal,
// error bound) of the final nearest hit, and the pbrt-v4 origin offset. The kernels that decide
// hit or miss live in kernels.h so the BVH traversal inlines them.
#include "accel/geometry.h"

#include <algorithm>
#include <bit>
#include <cassert>
#include <cmath>
#include <cstdint>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "accel/kernels.h"
#include "math/float_util.h"

namespace dtraced::accel {

using math::gamma;
using math::next_float_down;
using math::next_float_up;

namespace detail {

bool shape_is_valid(const Shape& shape) {
  switch (shape.type) {
    case ShapeType::kSphere:
      return sphere_is_valid(shape.sphere);
    case ShapeType::kBox: {
      const BoxShape& b = shape.box;
      return math::is_finite(b.lo) && math::is_finite(b.hi) && b.lo.x <= b.hi.x && b.lo.y <= b.hi.y && b.lo.z <= b.hi.z;
    }
    case ShapeType::kPlane: {
      const PlaneShape& p = shape.plane;
      return math::is_finite(p.point) && math::is_finite(p.normal) && !(p.normal == Vec3f{0, 0, 0});
    }
    case ShapeType::kTriangle: {
      const TriangleShape& t = shape.triangle;
      if (!math::is_finite(t.v0) || !math::is_finite(t.v1) || !math::is_finite(t.v2)) return false;
      // Zero area in double (collinear or repeated vertices): never hit, so no NaN normal.
      const math::Vec3d n = triangle_normal_d(t);
      return std::isfinite(n.x) && (n.x != 0.0 || n.y != 0.0 || n.z != 0.0);
    }
  }
  return false;
}

math::Vec3d triangle_normal_d(const TriangleShape& t) {
  const math::Vec3d a(t.v0), b(t.v1), c(t.v2);
  return math::cross(b - a, c - a);
}

namespace {

// One leaf of the flat layout holding the shapes `ids`, whose bounds it extends into `bounds`.
std::uint32_t flat_leaf(const std::vector<Shape>& shapes, const std::vector<std::uint32_t>& ids, WideBvh& w,
                        Bounds3f& bounds) {
  WideLeaf leaf;
  leaf.sphere_begin = std::uint32_t(w.spheres.size());
  leaf.triangle_begin = std::uint32_t(w.triangles.size());
  leaf.box_begin = std::uint32_t(w.boxes.size());
  std::uint32_t ns = 0, nt = 0;
  for (const std::uint32_t id : ids) {
    const Shape& shape = shapes[id];
    bounds.extend(shape_bounds(shape));
    switch (shape.type) {
      case ShapeType::kSphere: {
        if (ns % kWidth == 0) {
          SphereBlock b;
          for (int i = 0; i < kWidth; ++i) {
            b.cx[i] = b.cy[i] = b.cz[i] = b.r[i] = kNaN;  // never hit
            b.id[i] = kEmptyChild;
          }
          w.spheres.push_back(b);
        }
        SphereBlock& b = w.spheres.back();
        const std::uint32_t lane = ns++ % kWidth;
        b.cx[lane] = shape.sphere.center.x;
        b.cy[lane] = shape.sphere.center.y;
        b.cz[lane] = shape.sphere.center.z;
        b.r[lane] = shape.sphere.radius;
        b.id[lane] = id;
        break;
      }
      case ShapeType::kTriangle: {
        w.has_triangles = true;
        if (nt % kWidth == 0) {
          TriangleBlock b;
          for (auto& vertex : b.v)
            for (auto& axis : vertex)
              for (float& x : axis) x = kNaN;
          for (std::uint32_t& i : b.id) i = kEmptyChild;
          w.triangles.push_back(b);
        }
        TriangleBlock& b = w.triangles.back();
        const std::uint32_t lane = nt++ % kWidth;
        const Vec3f* v[3] = {&shape.triangle.v0, &shape.triangle.v1, &shape.triangle.v2};
        for (int vert = 0; vert < 3; ++vert)
          for (int axis = 0; axis < 3; ++axis) b.v[vert][axis][lane] = (*v[vert])[axis];
        b.id[lane] = id;
        break;
      }
      case ShapeType::kBox: {
        const BoxShape& bs = shape.box;
        w.boxes.push_back({{bs.lo.x, bs.lo.y, bs.lo.z, bs.hi.x, bs.hi.y, bs.hi.z}, id});
        ++leaf.box_count;
        break;
      }
      case ShapeType::kPlane:
        assert(false && "planes are tested beside the tree");
        break;
    }
  }
  leaf.sphere_blocks = std::uint16_t(w.spheres.size() - leaf.sphere_begin);
  leaf.triangle_blocks = std::uint16_t(w.triangles.size() - leaf.triangle_begin);
  w.leaves.push_back(leaf);
  return kLeafBit | std::uint32_t(w.leaves.size() - 1);
}

}  // namespace

WideBvh flat_wide(const std::vector<Shape>& shapes, const std::vector<std::vector<std::uint32_t>>& groups) {
  assert(groups.size() <= std::size_t(kNodeWidth));
  WideBvh w;
  WideNode root;
  int n = 0;
  for (const std::vector<std::uint32_t>& ids : groups) {
    if (ids.empty()) continue;
    Bounds3f b;
    root.child[n] = flat_leaf(shapes, ids, w, b);
    for (int axis = 0; axis < 3; ++axis) {
      root.lo[axis][n] = b.lo[axis];
      root.hi[axis][n] = b.hi[axis];
    }
    ++n;
  }
  if (n == 0) return w;
  for (int i = 0; i < kNodeWidth; ++i) {
    root.pad[i] = 0;
    if (i < n) continue;
    root.child[i] = kEmptyChild;
    for (int axis = 0; axis < 3; ++axis) {
      root.lo[axis][i] = kInf;
      root.hi[axis][i] = -kInf;
    }
  }
  w.nodes.push_back(root);
  return w;
}

void finish_hit(const Shape& shape, std::uint32_t id, const Ray& ray, const RayPre& r, float t, Hit& hit) {
  hit.t = t;
  hit.shape = id;
  switch (shape.type) {
    case ShapeType::kSphere: {
      // Recompute the roots (the same arithmetic as the query, so the same root is chosen) and
      // take the hit point in the sphere's frame from the double root: f + t d, then projected
      // back onto the sphere. Using the float t instead would move the point along the ray by
      // half an ulp of t, which near the silhouette of a far sphere tilts the normal visibly.
      const SphereShape& s = shape.sphere;
      const float sd[4] = {s.center.x, s.center.y, s.center.z, s.radius};
      detail::SphereRoots sr{};
      int root = 0;
      [[maybe_unused]] const float t_again = sphere_t(sd, r, ray.t_min, &sr, &root);
      assert(t_again == t);
      const double td = root == 0 ? sr.t0 : sr.t1;
      double pl[3];
      for (int i = 0; i < 3; ++i) pl[i] = sr.f[i] + td * double(r.d[i]);
      const double len = std::sqrt(pl[0] * pl[0] + pl[1] * pl[1] + pl[2] * pl[2]);
      const double rad = s.radius;
      const double scale = rad / len;
      for (int i = 0; i < 3; ++i) {
        pl[i] *= scale;
        hit.n[i] = float(pl[i] / rad);
        hit.p[i] = float(double(s.center[i]) + pl[i]);
        hit.p_error[i] = float(kSphereDoubleError * (std::abs(pl[i]) + std::abs(double(s.center[i])))) +
                         gamma(1) * std::abs(hit.p[i]);
      }
      return;
    }
    case ShapeType::kBox: {
      // The coordinate on the hit axis is the face coordinate itself (exact); the others are
      // o_j + t d_j clamped to the face, which can only move them closer to the true point.
      // Error on the other axes: t = (face - o_i) * inv_d_i carries three roundings,
      // t = t*(1 + th3); fl(t d_j) = t* d_j (1 + th4); fl(o_j + x) adds eps |o_j + x|. Hence
      // |p_j - p*_j| <= gamma(4)|t* d_j| + eps (|o_j| + |x|) <= gamma(6) (|o_j| + |t d_j|) in
      // terms of the computed x = t d_j, with one gamma to spare for rounding the bound itself.
      const BoxShape& b = shape.box;
      const float bd[6] = {b.lo.x, b.lo.y, b.lo.z, b.hi.x, b.hi.y, b.hi.z};
      BoxFace face;
      [[maybe_unused]] const float t_again = box_t(bd, r, ray.t_min, &face);
      assert(t_again == t);
      for (std::uint32_t j = 0; j < 3; ++j) {
        if (j == face.axis) {
          hit.p[j] = face.hi ? b.hi[j] : b.lo[j];
          hit.p_error[j] = 0.0f;
          hit.n[j] = face.hi ? 1.0f : -1.0f;
        } else {
          const float td = t * r.d[j];
          const float raw = r.o[j] + td;
          // Keep the point strictly inside the face when it has interior floats: an inward
          // (refracted) ray from a point rounded onto an edge would otherwise leave through the
          // adjacent face at t = 0 and be lost. The nudge is at most one ulp past the true point,
          // and is added to the bound (which offsetting never reads: n_j = 0).
          float lo = b.lo[j], hi = b.hi[j];
          const float lo_in = next_float_up(lo), hi_in = next_float_down(hi);
          if (lo_in <= hi_in) {
            lo = lo_in;
            hi = hi_in;
          }
          hit.p[j] = std::clamp(raw, lo, hi);
          hit.p_error[j] = gamma(6) * (std::abs(r.o[j]) + std::abs(td)) + std::abs(hit.p[j] - raw);
          hit.n[j] = 0.0f;
        }
      }
      return;
    }
    case ShapeType::kTriangle: {
      const TriangleShape& tri = shape.triangle;
      const float vd[9] = {tri.v0.x, tri.v0.y, tri.v0.z, tri.v1.x, tri.v1.y, tri.v1.z, tri.v2.x, tri.v2.y, tri.v2.z};
      TriangleUvw uvw{};
      [[maybe_unused]] const float t_again = triangle_t(vd, r, ray.t_min, &uvw);
      assert(t_again == t);
      finish_triangle_hit(tri, id, t, uvw, hit);
      return;
    }
    case ShapeType::kPlane: {
      // p = o + t d in float. What matters for offsetting is the distance of p from the plane
      // along n. With v = point - o, num = dot(v, n) and dn = dot(d, n) each carry gamma(4) and
      // gamma(3) relative error in the sums of absolute terms, so the point on the ray at the
      // computed t lies within gamma(4) sum|v_i n_i| + gamma(4) sum|t d_i n_i| of the plane, and
      // forming o + t d adds gamma(2)(|o_i| + |t d_i|) per axis. |v_i| <= |point_i| + |o_i|, so
      // gamma(7)(|o| + |t d| + |point|) per axis bounds it: the box p +- p_error meets the plane
      // iff |n . (p - point)| <= sum |n_i| p_error_i. The point term matters: a plane given by a
      // far-away point has a far larger error than gamma(7)(|o| + |t d|) near the origin.
      // We use gamma(11): the new ray's own numerator dot(point - o', n) is rounded too (another
      // gamma(4) of the same sums), and the offset must exceed both for the sign of t to be
      // right when the ray leaves the plane.
      const PlaneShape& pl = shape.plane;
      for (int i = 0; i < 3; ++i) {
        const float td = t * r.d[i];
        hit.p[i] = r.o[i] + td;
        hit.p_error[i] = gamma(11) * (std::abs(r.o[i]) + std::abs(td) + std::abs(pl.point[i]));
      }
      hit.n = pl.normal;
      return;
    }
  }
}

void finish_triangle_hit(const TriangleShape& tri, std::uint32_t id, float t, const TriangleUvw& uvw, Hit& hit) {
  // pbrt-v4's triangle hit point: barycentric blend of the vertices, here with the barycentrics
  // in double; the bound gamma(7) sum |b_i v_i| covers it with room to spare. A float bound is the
  // right kind here, unlike a sphere's: the barycentrics come from the float edge functions
  // (double only in the rare zero-edge fallback), so they sum to 1 only to float precision and
  // the point leaves the triangle's plane by float-sized amounts. The packet kernels repeat this
  // operation for operation (simd_kernels.cpp, finish_triangles).
  hit.t = t;
  hit.shape = id;
  // u weighs a, v weighs b, w weighs c (each is the edge function opposite its vertex).
  const double b0 = uvw.u / uvw.det, b1 = uvw.v / uvw.det, b2 = uvw.w / uvw.det;
  for (int i = 0; i < 3; ++i) {
    const double x0 = b0 * tri.v0[i], x1 = b1 * tri.v1[i], x2 = b2 * tri.v2[i];
    hit.p[i] = float(x0 + x1 + x2);
    hit.p_error[i] = gamma(7) * float(std::abs(x0) + std::abs(x1) + std::abs(x2));
  }
  const math::Vec3d n = math::normalize(triangle_normal_d(tri));
  hit.n = Vec3f(n);
}

void finish_sphere_hits(const Shape* const* shapes, const std::uint32_t* ids, const Ray* const* rays, const float* ts,
                        Hit* const* hits, int n) {
  // finish_hit's sphere case, stage by stage over the lanes: the same operations in the same
  // order (so the same bits), but the lanes' independent square roots and divisions overlap
  // instead of each waiting for the previous lane's chain. The packet kernels repeat this too
  // (simd_kernels.cpp, finish_spheres).
  constexpr int kMax = kPacketSize;
  double f[3][kMax], d[3][kMax], c[3][kMax], rad[kMax], disc[kMax], a[kMax], bq[kMax], cc[kMax], td[kMax];
  n = std::min(n, kMax);
  for (int k = 0; k < n; ++k) {
    const SphereShape& s = shapes[k]->sphere;
    for (int i = 0; i < 3; ++i) {
      c[i][k] = double(s.center[i]);
      f[i][k] = double(rays[k]->o[i]) - c[i][k];
      d[i][k] = rays[k]->d[i];
    }
    rad[k] = s.radius;
  }
  for (int k = 0; k < n; ++k) {  // sphere_roots
    const double fx = f[0][k], fy = f[1][k], fz = f[2][k], dx = d[0][k], dy = d[1][k], dz = d[2][k];
    const double rr = rad[k] * rad[k];
    const double cx = fy * dz - fz * dy;
    const double cy = fz * dx - fx * dz;
    const double cz = fx * dy - fy * dx;
    a[k] = dx * dx + dy * dy + dz * dz;
    disc[k] = a[k] * rr - (cx * cx + cy * cy + cz * cz);
    bq[k] = fx * dx + fy * dy + fz * dz;
    cc[k] = (fx * fx + fy * fy + fz * fz) - rr;
  }
  for (int k = 0; k < n; ++k) {  // sphere_t's choice of root
    const double q = -(bq[k] + std::copysign(std::sqrt(disc[k]), bq[k]));
    double t0 = cc[k] / q;
    double t1 = q / a[k];
    if (t0 > t1) std::swap(t0, t1);
    const float t0f = float(t0);
    td[k] = (t0f > rays[k]->t_min && t0f < kInf) ? t0 : t1;
  }
  for (int k = 0; k < n; ++k) {
    Hit& hit = *hits[k];
    hit.t = ts[k];
    hit.shape = ids[k];
    double pl[3];
    for (int i = 0; i < 3; ++i) pl[i] = f[i][k] + td[k] * d[i][k];
    const double len = std::sqrt(pl[0] * pl[0] + pl[1] * pl[1] + pl[2] * pl[2]);
    const double scale = rad[k] / len;
    for (int i = 0; i < 3; ++i) {
      pl[i] *= scale;
      hit.n[i] = float(pl[i] / rad[k]);
      hit.p[i] = float(c[i][k] + pl[i]);
      hit.p_error[i] =
          float(kSphereDoubleError * (std::abs(pl[i]) + std::abs(c[i][k]))) + gamma(1) * std::abs(hit.p[i]);
    }
  }
}

}  // namespace detail

bool intersect_shape(const Shape& shape, std::uint32_t id, const Ray& ray, Hit& hit) {
  if (!(ray.t_min < ray.t_max) || !math::is_finite(ray.o) || !math::is_finite(ray.d)) return false;
  if (!detail::shape_is_valid(shape)) return false;
  const detail::RayPre r = detail::precompute(ray);
  float t = detail::kNaN;
  switch (shape.type) {
    case ShapeType::kSphere: {
      const float s[4] = {shape.sphere.center.x, shape.sphere.center.y, shape.sphere.center.z, shape.sphere.radius};
      t = detail::sphere_t(s, r, ray.t_min);
      break;
    }
    case ShapeType::kBox: {
      const BoxShape& b = shape.box;
      const float bd[6] = {b.lo.x, b.lo.y, b.lo.z, b.hi.x, b.hi.y, b.hi.z};
      t = detail::box_t(bd, r, ray.t_min);
      break;
    }
    case ShapeType::kPlane:
      t = detail::plane_t(shape.plane, r, ray.t_min);
      break;
    case ShapeType::kTriangle: {
      const TriangleShape& tr = shape.triangle;
      const float v[9] = {tr.v0.x, tr.v0.y, tr.v0.z, tr.v1.x, tr.v1.y, tr.v1.z, tr.v2.x, tr.v2.y, tr.v2.z};
      t = detail::triangle_t(v, r, ray.t_min);
      break;
    }
  }
  if (!(t < ray.t_max)) return false;
  detail::finish_hit(shape, id, ray, r, t, hit);
  return true;
}

Bounds3f shape_bounds(const Shape& shape) {
  Bounds3f b;
  if (!detail::shape_is_valid(shape)) return b;
  switch (shape.type) {
    case ShapeType::kSphere:
      return sphere_bounds(shape.sphere);
    case ShapeType::kBox:
      b.lo = shape.box.lo;
      b.hi = shape.box.hi;
      return b;
    case ShapeType::kTriangle: {
      const TriangleShape& t = shape.triangle;
      b.lo = math::min(math::min(t.v0, t.v1), t.v2);
      b.hi = math::max(math::max(t.v0, t.v1), t.v2);
      return b;
    }
    case ShapeType::kPlane:
      b.lo = Vec3f{-detail::kInf, -detail::kInf, -detail::kInf};
      b.hi = Vec3f{detail::kInf, detail::kInf, detail::kInf};
      return b;
  }
  return b;
}

template <int N>
std::uint32_t Geometry::outside_planes(const Ray* rays, std::uint32_t live, float* best_t,
                                       std::uint32_t* best_id) const {
  // Read where the rays are: detail::plane_t and outside_hit's comparison, operation for
  // operation, for each plane in turn (the lanes are independent, so the order of lanes does not
  // matter). Copying the rays into arrays first, for loops across the lanes, cost more than the
  // tests themselves: a scene has a plane or two, and the copies' wide loads waited on the narrow
  // stores that wrote the rays.
  const bool flat = detail::is_flat(wide_);
  std::uint32_t mask = 0;
#if defined(__SSE2__)
  // Four lanes at a time, each lane's values loaded one by one (a wide load of the rays' narrow
  // stores would wait for them), so that the lanes' divisions go four to an instruction, and
  // without a branch per lane (whitted10's render phase went down by 1.8 %, against the lane by
  // lane loop of the #else branch). divps rounds as divss does and the sums go in the same order,
  // so every lane gets that loop's bits, ties to the smaller id included.
  static_assert(N % 4 == 0);
  const __m128 zero = _mm_setzero_ps(), inf = _mm_set1_ps(detail::kInf);
  const __m128i sign = _mm_set1_epi32(std::int32_t(0x80000000u));
  const __m128i lane_bits = _mm_setr_epi32(1, 2, 4, 8);
  for (int g = 0; g < N; g += 4) {
    const std::uint32_t lanes = live >> g & 0xfu;
    if (lanes == 0) continue;
    const Ray &r0 = rays[g], &r1 = rays[g + 1], &r2 = rays[g + 2], &r3 = rays[g + 3];
    const __m128 ox = _mm_setr_ps(r0.o.x, r1.o.x, r2.o.x, r3.o.x);
    const __m128 oy = _mm_setr_ps(r0.o.y, r1.o.y, r2.o.y, r3.o.y);
    const __m128 oz = _mm_setr_ps(r0.o.z, r1.o.z, r2.o.z, r3.o.z);
    const __m128 dx = _mm_setr_ps(r0.d.x, r1.d.x, r2.d.x, r3.d.x);
    const __m128 dy = _mm_setr_ps(r0.d.y, r1.d.y, r2.d.y, r3.d.y);
    const __m128 dz = _mm_setr_ps(r0.d.z, r1.d.z, r2.d.z, r3.d.z);
    const __m128 t_min = _mm_setr_ps(r0.t_min, r1.t_min, r2.t_min, r3.t_min);
    __m128 bt = _mm_setr_ps(best_t[g], best_t[g + 1], best_t[g + 2], best_t[g + 3]);
    __m128i bid = _mm_setr_epi32(std::int32_t(best_id[g]), std::int32_t(best_id[g + 1]), std::int32_t(best_id[g + 2]),
                                 std::int32_t(best_id[g + 3]));
    const __m128i in = _mm_cmpeq_epi32(_mm_and_si128(_mm_set1_epi32(std::int32_t(lanes)), lane_bits), lane_bits);
    __m128i found = _mm_setzero_si128();
    for (const std::uint32_t id : outside_) {
      if (flat && shapes_[id].type != ShapeType::kPlane) continue;
      assert(shapes_[id].type == ShapeType::kPlane);
      const PlaneShape& pl = shapes_[id].plane;
      const __m128 nx = _mm_set1_ps(pl.normal.x), ny = _mm_set1_ps(pl.normal.y), nz = _mm_set1_ps(pl.normal.z);
      const __m128 dn = _mm_add_ps(_mm_add_ps(_mm_mul_ps(dx, nx), _mm_mul_ps(dy, ny)), _mm_mul_ps(dz, nz));
      const __m128 num = _mm_add_ps(_mm_add_ps(_mm_mul_ps(_mm_sub_ps(_mm_set1_ps(pl.point.x), ox), nx),
                                               _mm_mul_ps(_mm_sub_ps(_mm_set1_ps(pl.point.y), oy), ny)),
                                    _mm_mul_ps(_mm_sub_ps(_mm_set1_ps(pl.point.z), oz), nz));
      const __m128 t = _mm_div_ps(num, dn);
      const __m128 ok = _mm_and_ps(_mm_and_ps(_mm_cmpneq_ps(dn, zero), _mm_cmpgt_ps(t, t_min)), _mm_cmplt_ps(t, inf));
      const __m128i vid = _mm_set1_epi32(std::int32_t(id));
      const __m128i id_less = _mm_cmpgt_epi32(_mm_xor_si128(bid, sign), _mm_xor_si128(vid, sign));
      const __m128i tie = _mm_and_si128(_mm_and_si128(found, _mm_castps_si128(_mm_cmpeq_ps(t, bt))), id_less);
      const __m128i take = _mm_and_si128(_mm_and_si128(_mm_castps_si128(ok), in),
                                         _mm_or_si128(_mm_castps_si128(_mm_cmplt_ps(t, bt)), tie));
      bt = _mm_or_ps(_mm_and_ps(_mm_castsi128_ps(take), t), _mm_andnot_ps(_mm_castsi128_ps(take), bt));
      bid = _mm_or_si128(_mm_and_si128(take, vid), _mm_andnot_si128(take, bid));
      found = _mm_or_si128(found, take);
    }
    _mm_storeu_ps(best_t + g, bt);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(best_id + g), bid);
    mask |= std::uint32_t(_mm_movemask_ps(_mm_castsi128_ps(found))) << g;
  }
#else
  for (std::uint32_t s = live; s != 0; s &= s - 1) {
    const int i = std::countr_zero(s);
    const Ray& r = rays[i];
    const float ox = r.o.x, oy = r.o.y, oz = r.o.z, dx = r.d.x, dy = r.d.y, dz = r.d.z, t_min = r.t_min;
    float bt = best_t[i];
    std::uint32_t bid = best_id[i];
    bool found = false;
    for (const std::uint32_t id : outside_) {
      if (flat && shapes_[id].type != ShapeType::kPlane) continue;
      assert(shapes_[id].type == ShapeType::kPlane);
      const PlaneShape& pl = shapes_[id].plane;
      const float nx = pl.normal.x, ny = pl.normal.y, nz = pl.normal.z;
      const float dn = dx * nx + dy * ny + dz * nz;
      const float num = (pl.point.x - ox) * nx + (pl.point.y - oy) * ny + (pl.point.z - oz) * nz;
      const float t = num / dn;
      // plane_t's NaN cases (dn == 0, t outside (t_min, inf)) never pass outside_hit's test.
      const bool ok = dn != 0.0f && t > t_min && t < detail::kInf;
      if (ok && (t < bt || (found && t == bt && id < bid))) {
        bt = t;
        bid = id;
        found = true;
      }
    }
    best_t[i] = bt;
    best_id[i] = bid;
    mask |= std::uint32_t(found) << i;
  }
#endif
  return mask;
}

template std::uint32_t Geometry::outside_planes<kPacketSize>(const Ray*, std::uint32_t, float*, std::uint32_t*) const;
template std::uint32_t Geometry::outside_planes<kPacketSize16>(const Ray*, std::uint32_t, float*, std::uint32_t*) const;

void offset_ray_origin_to(const Vec3f& p, const Vec3f& p_error, const Vec3f& n, const Vec3f& w, Vec3f& out) {
  const float d = dot(math::abs(n), p_error);
  const bool flip = dot(w, n) < 0.0f;
#if defined(__SSE2__)
  // The three components at once and without a branch: the scalar form's six data-dependent
  // branches (the offset's sign, then next_float_up/down's cases) mispredicted; this function
  // had 3.6 % of whitted10's samples. The same float operations (d * n, an exact negation, one
  // addition), then next_float_up/down's integer steps chosen by masks, so the same bits.
  const __m128 sign = _mm_set1_ps(-0.0f);
  __m128 off = _mm_mul_ps(_mm_setr_ps(n.x, n.y, n.z, 0.0f), _mm_set1_ps(d));
  if (flip) off = _mm_xor_ps(off, sign);  // -offset
  const __m128 v = _mm_add_ps(_mm_setr_ps(p.x, p.y, p.z, 0.0f), off);
  const __m128 o = math::step_away4(v, off);
  // x and y in one 8-byte store, z in a 4-byte one: the callers copy the origin 8 and 4 bytes at
  // a time, and an 8-byte load of two 4-byte stores waited for them to retire (16 % of
  // trace_ahead's samples were on the load after the call).
  static_assert(sizeof(Vec3f) == 12);
  _mm_storel_epi64(reinterpret_cast<__m128i*>(&out), _mm_castps_si128(o));
  _mm_store_ss(&out.z, _mm_shuffle_ps(o, o, _MM_SHUFFLE(2, 2, 2, 2)));
#else
  Vec3f offset = d * n;
  if (flip) offset = -offset;
  // p + offset, rounded away from p so that the offset survives the rounding. Component by
  // component in registers: a Vec3f indexed in a loop lived on the stack, and its components'
  // 4-byte stores were reloaded 8 bytes at a time (a load that waits for the stores to retire).
  const auto away = [](float v, float off) {
    if (off > 0.0f) return next_float_up(v);
    if (off < 0.0f) return next_float_down(v);
    return v;
  };
  out.x = away(p.x + offset.x, offset.x);
  out.y = away(p.y + offset.y, offset.y);
  out.z = away(p.z + offset.z, offset.z);
#endif
}

Vec3f offset_ray_origin(const Vec3f& p, const Vec3f& p_error, const Vec3f& n, const Vec3f& w) {
  Vec3f o;
  offset_ray_origin_to(p, p_error, n, w, o);
  return o;
}

}  // namespace dtraced::accel
