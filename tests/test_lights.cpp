// Area lights against closed forms, and the scene-specialised integrator against the generic one.
//
// The closed-form cases look, through a 1x1 image with a very narrow field of view, at the origin
// of a white Lambertian plane (diffuse 1, colour 1) facing +y, so the pixel is L = E / pi for the
// irradiance E there. The camera stands off the light's axis, so its ray never meets the light.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <numbers>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "render/local_render.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "render_checks.h"
#include "scene/load.h"
#include "scene_builders.h"

using namespace dtraced;
using math::Vec3d;
using math::Vec3f;
using testing::box;
using testing::disk_light;
using testing::local_options;
using testing::pixel;
using testing::plane;
using testing::rect_light_down;
using testing::render_tiled;
using testing::Rendered;
using testing::require_identical;
using testing::sphere;
using testing::sphere_light;

namespace {

constexpr double kPi = std::numbers::pi;

scene::Material white() { return testing::diffuse({1, 1, 1}); }

// The white plane at y = 0 and a 1x1 camera looking at its origin from the side.
scene::SceneDesc receiver_scene() {
  scene::SceneDesc d;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, white()));
  d.camera = {{2.0, 0.7, 1.4}, {0, 0, 0}, {0, 1, 0}, 1e-4};
  d.render.width = 1;
  d.render.height = 1;
  d.render.samples = 1;
  return d;
}

render::Tile render_all(const render::RenderScene& rs, const scene::RenderSettings& s, bool packets = true,
                        bool specialise = true) {
  return render::render_tile(rs, s, {0, 0, s.width, s.height}, {.packets = packets, .specialise = specialise});
}

// The 1x1 receiver pixel (red channel) at `samples` pixel samples and seed `seed`.
double receiver_value(const scene::SceneDesc& base, std::uint32_t samples, std::uint64_t seed) {
  scene::SceneDesc d = base;
  d.render.samples = samples;
  d.render.seed = seed;
  const render::RenderScene rs = render::RenderScene::build(d);
  return double(pixel(render_all(rs, d.render), 0, 0).x);
}

// E at the centre of a plane facing a parallel a x b rectangle of radiance le at height h, on its
// axis: four corner rectangles of (a/2) x (b/2), each with the differential-area-to-parallel-
// rectangle form factor F(X, Y) = 1/(2 pi) [X/sqrt(1+X^2) atan(Y/sqrt(1+X^2)) + (X <-> Y)],
// and E = pi Le F_total.
double rect_on_axis_irradiance(double le, double a, double b, double h) {
  const double x = a / (2 * h), y = b / (2 * h);
  const double sx = std::sqrt(1 + x * x), sy = std::sqrt(1 + y * y);
  const double f = (x / sx * std::atan(y / sx) + y / sy * std::atan(x / sy)) / (2 * kPi);
  return kPi * le * 4 * f;
}

struct ClosedFormCase {
  const char* name;
  scene::Light light;
  double irradiance;
};

std::vector<ClosedFormCase> closed_form_cases() {
  const double le = 3.0;
  std::vector<ClosedFormCase> cases;
  {
    // Centre straight above at d = 2.5, R = 0.6: wholly above the horizon.
    const double r = 0.6, d = 2.5;
    cases.push_back({"sphere", sphere_light({0, d, 0}, r, le), kPi * le * (r / d) * (r / d)});
  }
  {
    // Off the normal: the formula holds for any centre direction while the sphere stays above
    // the horizon, scaled by the cosine of the centre's direction.
    const double r = 0.5;
    const Vec3d c{1.2, 2.0, -0.7};
    const double d = math::length(c);
    cases.push_back({"sphere-oblique", sphere_light(c, r, le), kPi * le * (r / d) * (r / d) * (c.y / d)});
  }
  {
    const double a = 0.8, h = 1.5;
    cases.push_back({"disk", disk_light({0, h, 0}, a, {0, -1, 0}, le), kPi * le * a * a / (h * h + a * a)});
  }
  {
    const double a = 1.6, b = 0.9, h = 1.2;
    cases.push_back({"rect", rect_light_down({0, h, 0}, a, b, le), rect_on_axis_irradiance(le, a, b, h)});
  }
  return cases;
}

// Renders `d` on every supported isa, per pixel and in packets, specialised and generic, in
// tilings with partial 4x2 blocks, and requires every image and ray count to equal the generic
// per-pixel render on the scalar isa. Returns that reference.
Rendered check_all_paths_match(const scene::SceneDesc& d) {
  const std::uint32_t w = d.render.width, h = d.render.height;
  const render::RenderScene reference_scene = render::RenderScene::build(d, accel::Isa::kScalar);
  const Rendered reference =
      render_tiled(reference_scene, d.render, w, h, /* packets = */ false, /* specialise = */ false);
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene rs = render::RenderScene::build(d, isa);
    struct Path {
      std::uint32_t tw, th;
      bool packets, specialise;
    };
    for (const Path p : {Path{w, h, false, true}, Path{w, h, true, true}, Path{w, h, true, false},
                         Path{13, 7, true, true}, Path{6, 5, true, false}, Path{13, 7, false, true}}) {
      INFO("tiles " << p.tw << "x" << p.th << (p.packets ? " packets" : " per pixel")
                    << (p.specialise ? " specialised" : " generic"));
      require_identical(reference, render_tiled(rs, d.render, p.tw, p.th, p.packets, p.specialise));
    }
  }
  return reference;
}

// A small scene with every light type and material kind, and lights in view: a sphere light and
// a rect light in front of geometry, a disk seen from behind, a mirror and a glass sphere.
scene::SceneDesc mixed_scene() {
  scene::SceneDesc d;
  scene::Material shiny = white();
  shiny.color = {0.8, 0.5, 0.3};
  shiny.specular = 0.5;
  shiny.shininess = 30;
  scene::Material mirror = white();
  mirror.diffuse = 0.1;
  mirror.reflectivity = 0.8;
  scene::Material glass;
  glass.diffuse = 0;
  glass.specular = 0.5;
  glass.transparency = 0.9;
  glass.ior = 1.5;
  d.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, white()));
  d.objects.push_back(plane({0, 0, -3}, {0, 0, 1}, shiny));
  d.objects.push_back(sphere({-1.2, 0.6, 0}, 0.6, shiny));
  d.objects.push_back(sphere({1.2, 0.7, -0.5}, 0.7, mirror));
  d.objects.push_back(sphere({0.1, 0.4, 1.0}, 0.4, glass));
  d.objects.push_back(box({-0.3, 0, -1.5}, {0.5, 0.8, -0.9}, white()));
  scene::Light rect = rect_light_down({0, 2.4, 0}, 1.2, 0.6, 4);
  rect.samples = 3;
  d.lights.push_back(rect);
  scene::Light ball = sphere_light({1.5, 1.6, 0.8}, 0.35, 20);
  ball.samples = 2;
  d.lights.push_back(ball);
  scene::Light back = disk_light({-1.6, 1.7, 1.0}, 0.3, {0, 0, -1}, 10);  // faces away from the camera
  back.cast_shadows = false;
  d.lights.push_back(back);
  d.lights.push_back(scene::Light{{-2, 3, 3}, {1, 0.9, 0.8}, 6});  // a point light too
  d.camera = {{0, 1.2, 4.5}, {0, 0.8, 0}, {0, 1, 0}, 50};
  d.render = {.width = 29, .height = 19, .samples = 2, .max_depth = 4, .background = {0.1, 0.2, 0.3}};
  return d;
}

}  // namespace

TEST_CASE("Area lights match the closed-form irradiance of sphere, disk and rect", "[lights][closed-form]") {
  for (const ClosedFormCase& c : closed_form_cases()) {
    INFO(c.name << ": E = " << c.irradiance);
    scene::SceneDesc d = receiver_scene();
    d.lights.push_back(c.light);
    d.lights.back().samples = 256;
    const double want = c.irradiance / kPi;
    // 256 light samples per pixel sample and 64 pixel samples: 16384 samples in all, so the
    // relative standard error is below 0.2% for each case (see the convergence test's figures).
    const double got = receiver_value(d, 64, 1);
    REQUIRE(std::abs(got - want) <= 0.01 * want);
  }
}

// Light samples are stratified across a pixel's samples (render/sampler.h: Owen-scrambled Sobol'
// nets). For these smooth, unoccluded integrands that gives an RMS error falling about as N^-1.5,
// where independent samples gave Monte Carlo's N^-0.5 (the test asserted that until issue 16).
TEST_CASE("Area-light estimates converge faster than 1/sqrt(samples)", "[lights][convergence]") {
  constexpr int kSeeds = 32;
  const std::uint32_t counts[] = {16, 64, 256, 1024};
  for (const ClosedFormCase& c : closed_form_cases()) {
    INFO(c.name);
    scene::SceneDesc d = receiver_scene();
    d.lights.push_back(c.light);  // one light sample per pixel sample
    const double want = c.irradiance / kPi;
    std::vector<double> log_n, log_rms;
    double last_rms = 0;
    for (const std::uint32_t n : counts) {
      double sq = 0;
      for (int seed = 0; seed < kSeeds; ++seed) {
        const double e = receiver_value(d, n, 1000 + seed) - want;
        sq += e * e;
      }
      last_rms = std::sqrt(sq / kSeeds) / want;
      INFO("N " << n << " relative RMS error " << last_rms);
      CHECK(last_rms > 0);  // it is a Monte Carlo estimate: some noise
      log_n.push_back(std::log(double(n)));
      log_rms.push_back(std::log(last_rms));
    }
    // Least-squares slope of log(RMS) against log(N).
    double mx = 0, my = 0;
    for (std::size_t i = 0; i < log_n.size(); ++i) {
      mx += log_n[i] / double(log_n.size());
      my += log_rms[i] / double(log_n.size());
    }
    double sxy = 0, sxx = 0;
    for (std::size_t i = 0; i < log_n.size(); ++i) {
      sxy += (log_n[i] - mx) * (log_rms[i] - my);
      sxx += (log_n[i] - mx) * (log_n[i] - mx);
    }
    const double slope = sxy / sxx;
    INFO("slope " << slope << ", relative RMS at N = 1024: " << last_rms);
    REQUIRE(slope <= -1.1);
    REQUIRE(slope >= -2.0);
    REQUIRE(last_rms < 0.015);
  }
}

TEST_CASE("A camera ray sees an area light's emitting side as Le, and not the back of a disk or rect",
          "[lights][emission]") {
  scene::SceneDesc d;
  d.render.width = 1;
  d.render.height = 1;
  d.render.background = {0.25, 0.5, 0.75};
  d.camera = {{0, 0, 5}, {0, 0, 0}, {0, 1, 0}, 1e-3};
  const Vec3f le{2.0f * 1.0f, 2.0f * 0.5f, 2.0f * 0.25f};
  const auto with = [&](scene::Light l) {
    scene::SceneDesc s = d;
    l.color = {1, 0.5, 0.25};
    l.intensity = 2;
    s.lights.push_back(l);
    const render::RenderScene rs = render::RenderScene::build(s);
    const Vec3f per_pixel = pixel(render_all(rs, s.render, /* packets = */ false), 0, 0);
    const Vec3f packets = pixel(render_all(rs, s.render, /* packets = */ true), 0, 0);
    REQUIRE(per_pixel == packets);
    return per_pixel;
  };
  SECTION("sphere") { REQUIRE(with(sphere_light({0, 0, 0}, 0.5, 1)) == le); }
  SECTION("disk, front and back") {
    REQUIRE(with(disk_light({0, 0, 0}, 0.5, {0, 0, 1}, 1)) == le);
    REQUIRE(with(disk_light({0, 0, 0}, 0.5, {0, 0, -1}, 1)) == Vec3f(d.render.background));
  }
  SECTION("rect, front and back") {
    scene::Light r;
    r.type = scene::LightType::kRect;
    r.edge_u = {1, 0, 0};
    r.edge_v = {0, 1, 0};
    r.normal = {0, 0, 1};
    REQUIRE(with(r) == le);
    r.normal = {0, 0, -1};
    REQUIRE(with(r) == Vec3f(d.render.background));
  }
  SECTION("a sphere light behind an opaque object is hidden") {
    d.objects.push_back(sphere({0, 0, 2}, 0.3, white()));
    const Vec3f v = with(sphere_light({0, 0, 0}, 0.5, 1));
    REQUIRE(v != le);
    REQUIRE(v.x < 0.01f);  // the occluder's front, lit by nothing but the light behind it
  }
  SECTION("a mirror reflects the light") {
    scene::Material m;
    m.diffuse = 0;
    m.reflectivity = 1;
    m.color = {1, 1, 1};
    d.objects.push_back(plane({0, 0, -1}, {0, 0, 1}, m));
    // Seen only in the mirror: the camera ray passes its back first.
    REQUIRE(with(disk_light({0, 0, 0}, 0.5, {0, 0, -1}, 1)) == le);
  }
}

TEST_CASE("A point inside a sphere light gets no light from it, and a ray from inside does not see it",
          "[lights][emission]") {
  scene::SceneDesc d = receiver_scene();
  d.camera = {{0.1, 0.3, 0.1}, {0, 0, 0}, {0, 1, 0}, 1e-3};  // inside the light too
  d.lights.push_back(sphere_light({0, 0.2, 0}, 1.0, 5));
  d.lights.back().samples = 16;
  const render::RenderScene rs = render::RenderScene::build(d);
  REQUIRE(pixel(render_all(rs, d.render), 0, 0) == Vec3f{0, 0, 0});
  // Moved so that the receiver point is outside (the camera still inside): lit.
  d.lights.back().position = {0, 1.05, 0};
  d.camera.position = {0.1, 1.2, 0.1};
  const render::RenderScene outside = render::RenderScene::build(d);
  REQUIRE(pixel(render_all(outside, d.render), 0, 0).x > 1.0f);
}

TEST_CASE("Occluders cast soft shadows, and cast_shadows false lets the light through", "[lights][shadows]") {
  scene::SceneDesc d = receiver_scene();
  scene::Light l = disk_light({0, 2, 0}, 0.8, {0, -1, 0}, 3);
  l.samples = 64;
  d.lights.push_back(l);
  d.render.samples = 16;
  const render::RenderScene open_rs = render::RenderScene::build(d);
  const render::Tile open = render_all(open_rs, d.render);
  const double open_value = pixel(open, 0, 0).x;
  REQUIRE(open_value > 0.1);

  SECTION("a full occluder blocks it, unless the light casts no shadows") {
    scene::SceneDesc blocked = d;
    blocked.objects.push_back(box({-2, 1, -2}, {2, 1.2, 2}, white()));
    REQUIRE(pixel(render_all(render::RenderScene::build(blocked), blocked.render), 0, 0).x == 0.0f);
    blocked.lights[0].cast_shadows = false;
    const render::RenderScene rs = render::RenderScene::build(blocked);
    CHECK(!rs.features().shadows);
    const render::Tile t = render_all(rs, blocked.render);
    // The same random numbers and no shadow rays: the very value of the open scene.
    REQUIRE(pixel(t, 0, 0) == pixel(open, 0, 0));
    REQUIRE(t.stats.rays == d.render.samples);  // camera rays only
  }
  SECTION("a half occluder gives a penumbra") {
    scene::SceneDesc half = d;
    // Covers the half x < 0 of the disk as seen from the origin.
    half.objects.push_back(box({-2, 1, -2}, {0, 1.2, 2}, white()));
    const double v = pixel(render_all(render::RenderScene::build(half), half.render), 0, 0).x;
    INFO("open " << open_value << ", half-occluded " << v);
    REQUIRE(v > 0.35 * open_value);
    REQUIRE(v < 0.65 * open_value);
  }
}

TEST_CASE("A light mounted flush on a ceiling is not shadowed by the ceiling", "[lights][shadows]") {
  // A floor lit by a rect and a disk light that lie in the plane of a ceiling facing down. The
  // ceiling's hit is at the light's distance up to float error: a shadow ray that ran all the way
  // to the light would find it at random. With the ceiling or without it, every floor pixel must
  // be the same bits (the camera sees only the floor; the same samples either way).
  scene::SceneDesc open;
  open.objects.push_back(plane({0, 0, 0}, {0, 1, 0}, white()));
  scene::Light rect = rect_light_down({-0.8, 3, 0}, 1.0, 1.4, 5);
  rect.samples = 4;
  open.lights.push_back(rect);
  scene::Light disk = disk_light({0.9, 3, 0.3}, 0.5, {0, -1, 0}, 5);
  disk.samples = 4;
  open.lights.push_back(disk);
  open.camera = {{0, 2, 3}, {0, 0, 0}, {0, 1, 0}, 40};
  open.render.width = 40;
  open.render.height = 30;
  open.render.samples = 4;
  scene::SceneDesc ceiling = open;
  ceiling.objects.push_back(plane({0, 3, 0}, {0, -1, 0}, white()));
  const render::Tile want = render_all(render::RenderScene::build(open), open.render);
  const render::Tile got = render_all(render::RenderScene::build(ceiling), ceiling.render);
  REQUIRE(want.rgb.size() == got.rgb.size());
  std::size_t darker = 0;
  for (std::size_t i = 0; i < want.rgb.size(); ++i) darker += got.rgb[i] != want.rgb[i];
  REQUIRE(std::all_of(want.rgb.begin(), want.rgb.end(), [](float v) { return v > 0.0f; }));
  CHECK(darker == 0);
}

TEST_CASE("Area lights render the same bits per pixel and in packets, specialised or not, on every isa",
          "[lights][packets][specialise]") {
  scene::SceneDesc d = mixed_scene();
  const Rendered r = check_all_paths_match(d);
  REQUIRE(r.stats.nan_samples == 0);
  REQUIRE(r.stats.inf_samples == 0);
  // The lights in view show Le somewhere in the image.
  bool saw_light = false;
  for (std::size_t i = 0; i + 2 < r.rgb.size(); i += 3) saw_light = saw_light || r.rgb[i] == 20.0f;
  REQUIRE(saw_light);
  d.render.samples = 1;
  check_all_paths_match(d);
}

TEST_CASE("The specialised path renders the bundled scenes like the generic one", "[specialise]") {
  for (const char* name : {"showcase.json", "diffuse.json", "soft_shadows.json", "hard/nested_glass.json"}) {
    INFO(name);
    scene::SceneDesc d = testing::load_bundled(name);
    d.render.width = 37;
    d.render.height = 23;
    d.render.samples = 2;
    check_all_paths_match(d);
  }
}

TEST_CASE("Scene features are derived from what the scene uses", "[specialise]") {
  const render::SceneFeatures diffuse = render::RenderScene::build(testing::load_bundled("diffuse.json")).features();
  CHECK(diffuse == render::SceneFeatures{.shadows = true, .point_lights = true});
  CHECK(render::feature_names(diffuse) == "shadows point-lights");
  const render::SceneFeatures showcase = render::RenderScene::build(testing::load_bundled("showcase.json")).features();
  CHECK(render::feature_names(showcase) == "reflection refraction specular shadows point-lights");
  const render::SceneFeatures soft = render::RenderScene::build(testing::load_bundled("soft_shadows.json")).features();
  CHECK(render::feature_names(soft) == "reflection refraction specular shadows area-lights");
  CHECK(render::feature_names(render::SceneFeatures{}) == "none");
  CHECK(render::feature_names(render::SceneFeatures::all()) ==
        "reflection refraction specular shadows area-lights point-lights");
}

TEST_CASE("A scene with only point lights has no noise beyond antialiasing", "[specialise][determinism]") {
  scene::SceneDesc d = testing::load_bundled("showcase.json");
  d.render.width = 48;
  d.render.height = 27;
  d.render.samples = 1;  // pixel centres: no random number is drawn at all
  const render::RenderScene rs = render::RenderScene::build(d);
  scene::RenderSettings other = d.render;
  other.seed = d.render.seed + 12345;
  const render::Tile a = render_all(rs, d.render);
  const render::Tile b = render_all(rs, other);
  REQUIRE(std::memcmp(a.rgb.data(), b.rgb.data(), a.rgb.size() * sizeof(float)) == 0);

  // With an area light the seed does matter: the check above could fail.
  scene::SceneDesc soft = testing::load_bundled("soft_shadows.json");
  soft.render.width = 48;
  soft.render.height = 27;
  soft.render.samples = 1;
  const render::RenderScene soft_rs = render::RenderScene::build(soft);
  scene::RenderSettings soft_other = soft.render;
  soft_other.seed = soft.render.seed + 12345;
  const render::Tile c = render_all(soft_rs, soft.render);
  const render::Tile e = render_all(soft_rs, soft_other);
  REQUIRE(std::memcmp(c.rgb.data(), e.rgb.data(), c.rgb.size() * sizeof(float)) != 0);
}

TEST_CASE("render_local renders area lights identically for any thread count and tile size", "[lights][local]") {
  scene::SceneDesc d = mixed_scene();
  d.render.width = 41;
  d.render.height = 27;
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::LocalOptions one = local_options(/* threads = */ 1, /* tile_size = */ 64);
  const render::LocalOptions two = local_options(/* threads = */ 2, /* tile_size = */ 5);
  const render::LocalResult a = render::render_local(rs, d.render, one);
  const render::LocalResult b = render::render_local(rs, d.render, two);
  REQUIRE(std::memcmp(a.image.rgb.data(), b.image.rgb.data(), a.image.rgb.size() * sizeof(float)) == 0);
  REQUIRE(a.stats.rays == b.stats.rays);
}
