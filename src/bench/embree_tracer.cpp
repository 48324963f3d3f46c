#include "bench/embree_tracer.h"

#include <chrono>
#include <cmath>
#include <limits>

#include <embree3/rtcore.h>
#include <fmt/format.h>

namespace dtraced::bench {

struct EmbreeTracer::Impl {
  RTCDevice device = nullptr;
  RTCScene scene = nullptr;
  // Embree geometry id -> (primID -> our shape index).
  std::vector<std::vector<std::uint32_t>> shape_of;

  ~Impl() {
    if (scene) rtcReleaseScene(scene);
    if (device) rtcReleaseDevice(device);
  }
  std::uint32_t id(unsigned geom, unsigned prim) const {
    if (geom == RTC_INVALID_GEOMETRY_ID) return kMissId;
    return shape_of[geom][prim];
  }
  // Commits geometry g at quality q into the scene; its primitive k is our shape shapes[k].
  void attach(RTCGeometry g, RTCBuildQuality q, std::vector<std::uint32_t> shapes) {
    rtcSetGeometryBuildQuality(g, q);
    rtcCommitGeometry(g);
    const unsigned geom = rtcAttachGeometry(scene, g);
    rtcReleaseGeometry(g);
    if (shape_of.size() <= geom) shape_of.resize(geom + 1);
    shape_of[geom] = std::move(shapes);
  }
};

namespace {

void on_error(void* user, RTCError code, const char* message) {
  auto* last = static_cast<std::string*>(user);
  *last = fmt::format("embree error {}: {}", static_cast<int>(code), message ? message : "");
}

RTCIntersectContext context(bool coherent) {
  RTCIntersectContext ctx;
  rtcInitIntersectContext(&ctx);
  ctx.flags = coherent ? RTC_INTERSECT_CONTEXT_FLAG_COHERENT : RTC_INTERSECT_CONTEXT_FLAG_INCOHERENT;
  return ctx;
}

void fill1(const math::Ray& r, RTCRay& e) {
  e.org_x = r.o.x;
  e.org_y = r.o.y;
  e.org_z = r.o.z;
  e.tnear = r.t_min;
  e.dir_x = r.d.x;
  e.dir_y = r.d.y;
  e.dir_z = r.d.z;
  e.time = 0.0f;
  e.tfar = r.t_max;
  e.mask = 0xffffffffu;
  e.id = 0;
  e.flags = 0;
}

// RTCRay8 or RTCRay16 from N rays; v[i] is -1 for the lanes of `valid`, else 0.
template <int N, class Packet>
void fill_n(const math::Ray* rays, std::uint32_t valid, Packet& e, int* v) {
  for (int i = 0; i < N; ++i) {
    const math::Ray& r = rays[i];
    v[i] = (valid >> i & 1u) ? -1 : 0;
    e.org_x[i] = r.o.x;
    e.org_y[i] = r.o.y;
    e.org_z[i] = r.o.z;
    e.tnear[i] = r.t_min;
    e.dir_x[i] = r.d.x;
    e.dir_y[i] = r.d.y;
    e.dir_z[i] = r.d.z;
    e.time[i] = 0.0f;
    e.tfar[i] = r.t_max;
    e.mask[i] = 0xffffffffu;
    e.id[i] = 0;
    e.flags[i] = 0;
  }
}

// One N-ray packet through rtcIntersectN: the shape id of each lane of `valid` into ids.
template <int N, class RayHit, class IntersectN, class Id>
void intersect_packet(IntersectN intersect, RTCScene scene, RTCIntersectContext& ctx, const math::Ray* rays,
                      std::uint32_t valid, std::uint32_t* ids, const Id& id) {
  alignas(64) RayHit rh;
  alignas(64) int v[N];
  fill_n<N>(rays, valid, rh.ray, v);
  for (int i = 0; i < N; ++i) {
    rh.hit.geomID[i] = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0][i] = RTC_INVALID_GEOMETRY_ID;
  }
  intersect(v, scene, &ctx, &rh);
  for (int i = 0; i < N; ++i) {
    if (valid >> i & 1u) ids[i] = id(rh.hit.geomID[i], rh.hit.primID[i]);
  }
}

// One N-ray packet through rtcOccludedN: 1 for each lane of `valid` that is blocked.
template <int N, class Ray, class OccludedN>
void occluded_packet(OccludedN occluded, RTCScene scene, RTCIntersectContext& ctx, const math::Ray* rays,
                     std::uint32_t valid, std::uint32_t* blocked) {
  alignas(64) Ray r;
  alignas(64) int v[N];
  fill_n<N>(rays, valid, r, v);
  occluded(v, scene, &ctx, &r);
  for (int i = 0; i < N; ++i) {
    if (valid >> i & 1u) blocked[i] = r.tfar[i] < 0.0f ? 1u : 0u;  // Embree sets tfar = -inf on a hit
  }
}

}  // namespace

std::string_view embree_quality_name(EmbreeQuality q) {
  switch (q) {
    case EmbreeQuality::kLow:
      return "low";
    case EmbreeQuality::kMedium:
      return "medium";
    case EmbreeQuality::kHigh:
      return "high";
  }
  return "unknown";
}

std::string EmbreeTracer::version() { return RTC_VERSION_STRING; }

EmbreeTracer::~EmbreeTracer() = default;

util::Result<std::unique_ptr<EmbreeTracer>> EmbreeTracer::build(const std::vector<accel::Shape>& shapes,
                                                                EmbreeQuality quality, std::uint32_t build_threads) {
  std::unique_ptr<EmbreeTracer> t(new EmbreeTracer);
  t->impl_ = std::make_unique<Impl>();
  Impl& im = *t->impl_;
  const std::string config = build_threads ? fmt::format("threads={}", build_threads) : std::string();
  im.device = rtcNewDevice(config.empty() ? nullptr : config.c_str());
  if (!im.device) {
    return util::Error(fmt::format("rtcNewDevice failed (error {})", static_cast<int>(rtcGetDeviceError(nullptr))));
  }
  std::string last_error;
  rtcSetDeviceErrorFunction(im.device, on_error, &last_error);

  std::vector<std::uint32_t> spheres, triangles;
  for (std::uint32_t i = 0; i < shapes.size(); ++i) {
    switch (shapes[i].type) {
      case accel::ShapeType::kSphere:
        spheres.push_back(i);
        break;
      case accel::ShapeType::kTriangle:
        triangles.push_back(i);
        break;
      default:
        ++t->skipped_;
    }
  }

  im.scene = rtcNewScene(im.device);
  const RTCBuildQuality q = quality == EmbreeQuality::kHigh  ? RTC_BUILD_QUALITY_HIGH
                            : quality == EmbreeQuality::kLow ? RTC_BUILD_QUALITY_LOW
                                                             : RTC_BUILD_QUALITY_MEDIUM;
  rtcSetSceneBuildQuality(im.scene, q);

  if (!spheres.empty()) {
    RTCGeometry g = rtcNewGeometry(im.device, RTC_GEOMETRY_TYPE_SPHERE_POINT);
    auto* v = static_cast<float*>(
        rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT4, 4 * sizeof(float), spheres.size()));
    for (std::size_t k = 0; k < spheres.size(); ++k) {
      const accel::SphereShape& s = shapes[spheres[k]].sphere;
      v[4 * k + 0] = s.center.x;
      v[4 * k + 1] = s.center.y;
      v[4 * k + 2] = s.center.z;
      v[4 * k + 3] = s.radius;
    }
    im.attach(g, q, std::move(spheres));
  }
  if (!triangles.empty()) {
    RTCGeometry g = rtcNewGeometry(im.device, RTC_GEOMETRY_TYPE_TRIANGLE);
    const std::size_t n = triangles.size();
    auto* v = static_cast<float*>(
        rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3, 3 * sizeof(float), 3 * n));
    auto* idx = static_cast<std::uint32_t*>(
        rtcSetNewGeometryBuffer(g, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3, 3 * sizeof(std::uint32_t), n));
    for (std::size_t k = 0; k < n; ++k) {
      const accel::TriangleShape& tri = shapes[triangles[k]].triangle;
      const math::Vec3f* corners[3] = {&tri.v0, &tri.v1, &tri.v2};
      for (int c = 0; c < 3; ++c) {
        v[9 * k + 3 * c + 0] = corners[c]->x;
        v[9 * k + 3 * c + 1] = corners[c]->y;
        v[9 * k + 3 * c + 2] = corners[c]->z;
        idx[3 * k + c] = static_cast<std::uint32_t>(3 * k + c);
      }
    }
    im.attach(g, q, std::move(triangles));
  }

  const auto start = std::chrono::steady_clock::now();
  rtcCommitScene(im.scene);
  t->build_seconds_ = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (!last_error.empty()) return util::Error(last_error);
  rtcSetDeviceErrorFunction(im.device, nullptr, nullptr);  // `last_error` dies with this frame
  return t;
}

void EmbreeTracer::intersect1(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  for (int i = 0; i < 8; ++i) {
    if (!(valid >> i & 1u)) continue;
    RTCRayHit rh;
    fill1(rays[i], rh.ray);
    rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(impl_->scene, &ctx, &rh);
    ids[i] = impl_->id(rh.hit.geomID, rh.hit.primID);
  }
}

void EmbreeTracer::intersect8(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  intersect_packet<8, RTCRayHit8>(rtcIntersect8, impl_->scene, ctx, rays, valid, ids,
                                  [this](unsigned g, unsigned p) { return impl_->id(g, p); });
}

void EmbreeTracer::occluded1(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  for (int i = 0; i < 8; ++i) {
    if (!(valid >> i & 1u)) continue;
    RTCRay r;
    fill1(rays[i], r);
    rtcOccluded1(impl_->scene, &ctx, &r);
    blocked[i] = r.tfar < 0.0f ? 1u : 0u;  // Embree sets tfar = -inf on a hit
  }
}

void EmbreeTracer::occluded8(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  occluded_packet<8, RTCRay8>(rtcOccluded8, impl_->scene, ctx, rays, valid, blocked);
}

void EmbreeTracer::intersect16(const math::Ray* rays, std::uint32_t valid, std::uint32_t* ids, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  intersect_packet<16, RTCRayHit16>(rtcIntersect16, impl_->scene, ctx, rays, valid, ids,
                                    [this](unsigned g, unsigned p) { return impl_->id(g, p); });
}

void EmbreeTracer::occluded16(const math::Ray* rays, std::uint32_t valid, std::uint32_t* blocked, bool coherent) const {
  RTCIntersectContext ctx = context(coherent);
  occluded_packet<16, RTCRay16>(rtcOccluded16, impl_->scene, ctx, rays, valid, blocked);
}

}  // namespace dtraced::bench
