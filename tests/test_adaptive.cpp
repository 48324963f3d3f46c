// Adaptive sampling: deterministic across tilings, threads and packets; stops where it should.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <set>
#include <string>

#include <catch2/catch.hpp>

#include "accel/isa.h"
#include "image/metrics.h"
#include "render/local_render.h"
#include "render/reference.h"
#include "render/render_scene.h"
#include "render/tile.h"
#include "render_checks.h"
#include "scene/load.h"
#include "scene_builders.h"

using namespace dtraced;
using math::Vec3d;

namespace {

scene::SceneDesc load_adaptive(const std::string& name, std::uint32_t width, std::uint32_t height) {
  scene::SceneDesc d = testing::bundled_scene(name, width, height);
  d.render.samples = 64;
  d.render.min_samples = 8;
  d.render.error_target = 0.05;
  return d;
}

scene::SceneDesc load_showcase(std::uint32_t width, std::uint32_t height) {
  return load_adaptive("showcase", width, height);
}

// One diffuse sphere in the middle of a flat background, lit by one point light: the background
// pixels see one colour in every sample, the sphere's outline mixes two.
scene::SceneDesc sphere_on_background() {
  scene::SceneDesc d;
  d.camera.position = {0, 0, 5};
  d.camera.look_at = {0, 0, 0};
  d.camera.fov_deg = 40;
  d.objects.push_back(testing::sphere({0, 0, 0}, 1.0, testing::diffuse({0.8, 0.3, 0.2})));
  d.lights.push_back(testing::point_light({3, 4, 5}, 1.0));
  d.render = {
      .width = 32, .height = 24, .samples = 64, .background = {0.2, 0.3, 0.4}, .error_target = 0.02, .min_samples = 8};
  return d;
}

render::LocalResult render_with(const render::RenderScene& rs, const scene::RenderSettings& s, std::uint32_t tile,
                                std::uint32_t threads, bool packets) {
  render::LocalOptions o = testing::local_options(threads, tile, packets);
  o.want_variance = true;
  return render::render_local(rs, s, o);
}

void require_same(const render::LocalResult& want, const render::LocalResult& got) {
  REQUIRE(want.image.rgb.size() == got.image.rgb.size());
  REQUIRE(std::memcmp(want.image.rgb.data(), got.image.rgb.data(), want.image.rgb.size() * sizeof(float)) == 0);
  REQUIRE(want.spp == got.spp);
  REQUIRE(want.variance.rgb.size() == got.variance.rgb.size());
  REQUIRE(std::memcmp(want.variance.rgb.data(), got.variance.rgb.data(), want.variance.rgb.size() * sizeof(float)) ==
          0);
  REQUIRE(want.stats.rays == got.stats.rays);
}

double mean_spp(const std::vector<std::uint32_t>& spp) {
  return double(std::accumulate(spp.begin(), spp.end(), std::uint64_t{0})) / double(spp.size());
}

}  // namespace

TEST_CASE("Adaptive images are the same bits for any tiling, thread count, packet mode and isa", "[adaptive]") {
  // The showcase (point lights: no random numbers but the film's) and the soft-shadow scene
  // (area lights: each lane of a packet draws its own light samples while lanes drop out).
  // min_samples 1: the first checkpoint decides from the neighbourhood alone.
  const std::string name = GENERATE(as<std::string>{}, "showcase", "soft_shadows");
  const std::uint32_t min_samples = GENERATE(8u, 1u);
  INFO("scene " << name << ", min_samples " << min_samples);
  scene::SceneDesc d = load_adaptive(name, 48, 32);
  d.render.min_samples = min_samples;
  const render::RenderScene reference_scene = render::RenderScene::build(d, accel::Isa::kScalar);
  const render::LocalResult reference =
      render_with(reference_scene, d.render, std::max(d.render.width, d.render.height), 1, /* packets = */ false);
  REQUIRE(reference.spp.size() == std::size_t(d.render.width) * d.render.height);
  // The test is only worth something if some pixels stopped early and some did not.
  REQUIRE(std::count(reference.spp.begin(), reference.spp.end(), d.render.samples) > 0);
  REQUIRE(std::count(reference.spp.begin(), reference.spp.end(), d.render.min_samples) > 0);

  // Every tile size with both packet modes, every thread count with both, in 8 renders an isa
  // rather than all 20 combinations (the sanitizer build runs this test at a fifth of the speed).
  // Tile size 1 makes every packet one lane.
  struct Combination {
    std::uint32_t tile, threads;
    bool packets;
  };
  constexpr Combination kCombinations[] = {{1, 2, false}, {1, 2, true},   {7, 1, true},  {7, 3, false},
                                           {32, 2, true}, {32, 1, false}, {64, 3, true}, {64, 2, false}};
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    const render::RenderScene rs = render::RenderScene::build(d, isa);
    for (const Combination& c : kCombinations) {
      INFO("tile " << c.tile << ", threads " << c.threads << (c.packets ? ", packets" : ", per pixel"));
      require_same(reference, render_with(rs, d.render, c.tile, c.threads, c.packets));
    }
  }
}

TEST_CASE("A pixel stops only at a checkpoint or at settings.samples", "[adaptive]") {
  scene::SceneDesc d = load_showcase(40, 30);
  d.render.samples = 100;  // not a checkpoint: the last one below it is 64
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::LocalResult r = render_with(rs, d.render, 16, 2, true);
  const std::set<std::uint32_t> allowed{8, 16, 32, 64, 100};
  std::set<std::uint32_t> seen;
  for (const std::uint32_t n : r.spp) {
    REQUIRE(allowed.count(n) == 1);
    seen.insert(n);
  }
  CHECK(seen.size() >= 2);
}

TEST_CASE("Flat background stops at min_samples, and the sphere's outline takes more", "[adaptive]") {
  const scene::SceneDesc d = sphere_on_background();
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::LocalResult r = render_with(rs, d.render, 8, 2, true);
  const std::uint32_t w = d.render.width;
  // Corners are background: identical samples, zero variance.
  for (const auto& [x, y] : {std::pair{0u, 0u}, std::pair{w - 1, 0u}, std::pair{0u, d.render.height - 1}}) {
    INFO("pixel " << x << ", " << y);
    CHECK(r.spp[std::size_t(y) * w + x] == d.render.min_samples);
    const float* p = r.image.pixel(x, y);
    CHECK(p[0] == 0.2f);
    CHECK(r.variance.pixel(x, y)[0] == 0.0f);
  }
  // Along the middle row, the sphere's outline is where coverage changes: those pixels mix the
  // background with the sphere and need more samples than any background pixel of the row.
  const std::uint32_t y = d.render.height / 2;
  std::uint32_t edge_max = 0;
  for (std::uint32_t x = 1; x < w; ++x) {
    const bool left_bg =
        r.spp[std::size_t(y) * w + x - 1] == d.render.min_samples && r.image.pixel(x - 1, y)[2] == 0.4f;
    if (left_bg) edge_max = std::max(edge_max, r.spp[std::size_t(y) * w + x]);
  }
  CHECK(edge_max > d.render.min_samples);
  CHECK(*std::max_element(r.spp.begin(), r.spp.end()) > d.render.min_samples);
}

TEST_CASE("A smaller error target never stops a pixel sooner", "[adaptive]") {
  // Guaranteed pixel by pixel: a pixel sees the same samples, so the same error estimates at the
  // same checkpoints, whatever the target; one below the smaller target is below the larger.
  scene::SceneDesc d = load_showcase(40, 30);
  const render::RenderScene rs = render::RenderScene::build(d);
  std::vector<std::uint32_t> previous(std::size_t(d.render.width) * d.render.height, 0);
  double previous_mean = 0.0;
  for (const double target : {0.2, 0.05, 0.01}) {
    INFO("target " << target);
    d.render.error_target = target;
    const std::vector<std::uint32_t> spp = render_with(rs, d.render, 16, 2, true).spp;
    REQUIRE(spp.size() == previous.size());
    for (std::size_t i = 0; i < spp.size(); ++i) REQUIRE(spp[i] >= previous[i]);
    const double mean = mean_spp(spp);
    CHECK(mean >= d.render.min_samples);
    CHECK(mean <= d.render.samples);
    CHECK(mean >= previous_mean);
    previous = spp;
    previous_mean = mean;
  }
  // The tightest target costs more than the loosest: the test compares something.
  CHECK(previous_mean > d.render.min_samples);
}

TEST_CASE("Error target 0 renders the same bits as before, with no spp map", "[adaptive]") {
  scene::SceneDesc d = load_showcase(24, 16);
  d.render.error_target = 0.0;
  d.render.samples = 8;
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::Tile plain = render::render_tile(rs, d.render, {0, 0, 24, 16}, {.packets = true});
  CHECK(plain.spp.empty());
  CHECK(plain.variance.empty());
  // min_samples is ignored when not adaptive.
  scene::RenderSettings other = d.render;
  other.min_samples = 2;
  const render::Tile same = render::render_tile(rs, other, {0, 0, 24, 16}, {.packets = false, .want_variance = true});
  REQUIRE(plain.rgb.size() == same.rgb.size());
  CHECK(std::memcmp(plain.rgb.data(), same.rgb.data(), plain.rgb.size() * sizeof(float)) == 0);
  CHECK(same.spp.empty());
  CHECK(same.variance.size() == plain.rgb.size());
  // With min_samples = samples there is no checkpoint below samples: the image is the uniform
  // one and every count is 8.
  scene::RenderSettings none = d.render;
  none.error_target = 0.05;
  none.min_samples = 8;
  const render::Tile all = render::render_tile(rs, none, {0, 0, 24, 16});
  CHECK(std::memcmp(plain.rgb.data(), all.rgb.data(), plain.rgb.size() * sizeof(float)) == 0);
  CHECK(std::all_of(all.spp.begin(), all.spp.end(), [](std::uint32_t n) { return n == 8; }));
  // A target so loose that nearly every pixel stops at the first checkpoint, 8 of at most 64
  // (a dark pixel beside a bright one keeps going: relative to its own value its neighbourhood
  // differs by more than 100 %): each such pixel is the uniform 8-sample one (the same sample
  // indices 0..7, jittered in both).
  scene::RenderSettings loose = d.render;
  loose.samples = 64;
  loose.error_target = 1.0;
  loose.min_samples = 8;
  const render::Tile early = render::render_tile(rs, loose, {0, 0, 24, 16});
  const auto stopped = std::count(early.spp.begin(), early.spp.end(), 8u);
  CHECK(stopped >= std::ptrdiff_t(early.spp.size() * 3 / 4));
  for (std::size_t i = 0; i < early.spp.size(); ++i) {
    if (early.spp[i] != 8) continue;
    for (int c = 0; c < 3; ++c) REQUIRE(early.rgb[i * 3 + c] == plain.rgb[i * 3 + c]);
  }
}

// The variance of the values v[j] at offsets (dx[j], dy[j]) about their least-squares plane, with
// k - 3 degrees of freedom (the test's own formulation: the normal equations, solved directly).
double plane_residual_variance(const std::vector<double>& v, const std::vector<int>& dx, const std::vector<int>& dy) {
  const std::size_t k = v.size();
  double a[3][4] = {};
  for (std::size_t j = 0; j < k; ++j) {
    const double row[3] = {1.0, double(dx[j]), double(dy[j])};
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) a[r][c] += row[r] * row[c];
      a[r][3] += row[r] * v[j];
    }
  }
  for (int r = 0; r < 3; ++r) {  // Gauss-Jordan; the design is never singular for k >= 4 on a grid
    for (int q = 0; q < 3; ++q) {
      if (q == r) continue;
      const double f = a[q][r] / a[r][r];
      for (int c = 0; c < 4; ++c) a[q][c] -= f * a[r][c];
    }
  }
  double ss = 0.0;
  for (std::size_t j = 0; j < k; ++j) {
    const double fit = a[0][3] / a[0][0] + a[1][3] / a[1][1] * dx[j] + a[2][3] / a[2][2] * dy[j];
    ss += (v[j] - fit) * (v[j] - fit);
  }
  return ss / double(k - 3);
}

TEST_CASE("At the first checkpoint below 4 samples a pixel stops when its neighbourhood is flat", "[adaptive]") {
  // Below 4 samples a pixel has no own estimate: it stops at min_samples exactly when the means
  // of its 3x3 neighbourhood (over their first min_samples samples), taken about their plane,
  // vary little relative to its own mean: sqrt(max_c var_c / (mean_c^2 + 0.01)) <= target. The
  // test recomputes that from a uniform render of min_samples (the same samples) and leaves
  // undecided the pixels within 1e-3 of the target.
  const std::uint32_t min_samples = GENERATE(1u, 2u);
  INFO("min_samples " << min_samples);
  scene::SceneDesc d = sphere_on_background();
  d.render.min_samples = min_samples;
  const std::uint32_t w = d.render.width, h = d.render.height;
  const render::RenderScene rs = render::RenderScene::build(d);
  scene::RenderSettings uniform = d.render;
  uniform.error_target = 0.0;
  uniform.samples = min_samples;
  // A uniform render of 1 sample puts it at the pixel centre, where the adaptive one's sample 0
  // is jittered. So for min_samples 1 a loose adaptive render of at most 2 samples stands in:
  // its pixels that stopped at 1 hold sample 0; neighbourhoods with a pixel that took 2 are
  // left out.
  scene::RenderSettings first_only = d.render;
  first_only.error_target = 1.0;
  first_only.samples = 2;
  const render::LocalResult first = render_with(rs, min_samples == 1 ? first_only : uniform, 8, 2, true);
  std::size_t checked = 0, stopped = 0, refined = 0;
  const render::LocalResult r = render_with(rs, d.render, 5, 2, true);  // tiles of 5: borders everywhere
  for (std::uint32_t y = 0; y < h; ++y) {
    for (std::uint32_t x = 0; x < w; ++x) {
      bool usable = true;
      double worst = 0.0;
      for (int c = 0; c < 3; ++c) {
        std::vector<double> v;
        std::vector<int> dx, dy;
        for (std::uint32_t ny = y > 0 ? y - 1 : 0; ny <= std::min(y + 1, h - 1); ++ny) {
          for (std::uint32_t nx = x > 0 ? x - 1 : 0; nx <= std::min(x + 1, w - 1); ++nx) {
            if (min_samples == 1 && !first.spp.empty() && first.spp[std::size_t(ny) * w + nx] != 1) usable = false;
            v.push_back(first.image.pixel(nx, ny)[c]);
            dx.push_back(int(nx) - int(x));
            dy.push_back(int(ny) - int(y));
          }
        }
        const double mean = first.image.pixel(x, y)[c];
        worst = std::max(worst, std::max(0.0, plane_residual_variance(v, dx, dy)) / (mean * mean + 0.01));
      }
      const double err = std::sqrt(worst);
      if (!usable || std::abs(err - d.render.error_target) < 1e-3) continue;
      ++checked;
      INFO("pixel " << x << ", " << y << ": err " << err);
      const std::uint32_t n = r.spp[std::size_t(y) * w + x];
      CHECK((n == min_samples) == (err <= d.render.error_target));
      stopped += n == min_samples;
      refined += n > min_samples;
    }
  }
  CHECK(checked > std::size_t(w) * h / 2);
  CHECK(stopped > 0);
  // With min_samples 1 the pixels near the outline took 2 samples in `first` too, so their
  // neighbourhoods are left out; with 2 they are checked.
  if (min_samples == 2) CHECK(refined > 0);
}

TEST_CASE("A pixel whose neighbourhood differed does not stop on own samples that agree", "[adaptive]") {
  // Along the sphere's outline some pixels' first 4 samples all land on one side and agree
  // exactly (own variance 0 at the checkpoint n = 4). The first checkpoint (min_samples 1) saw
  // the outline in their neighbourhood, and that estimate, carried to n = 4 as a prior, keeps
  // them sampling: no such pixel stops at 4.
  scene::SceneDesc d = sphere_on_background();
  d.render.min_samples = 1;
  const std::uint32_t w = d.render.width, h = d.render.height;
  const render::RenderScene rs = render::RenderScene::build(d);
  scene::RenderSettings four = d.render;
  four.error_target = 0.0;
  four.samples = 4;
  const render::LocalResult uniform4 = render_with(rs, four, 8, 2, true);
  const render::LocalResult r = render_with(rs, d.render, 8, 2, true);
  std::size_t held = 0;
  for (std::uint32_t y = 0; y < h; ++y) {
    for (std::uint32_t x = 0; x < w; ++x) {
      const float* var = uniform4.variance.pixel(x, y);
      const std::uint32_t n = r.spp[std::size_t(y) * w + x];
      if (n == 1 || var[0] != 0.0f || var[1] != 0.0f || var[2] != 0.0f) continue;
      INFO("pixel " << x << ", " << y);
      CHECK(n > 4);
      ++held;
    }
  }
  CHECK(held > 0);
}

TEST_CASE("An early-stopped pixel is the mean of its first n samples", "[adaptive]") {
  // The adaptive value of a pixel that stopped at n equals the uniform render at n samples only
  // when n = samples there; instead compare with a uniform render of n samples, which draws the
  // same sample indices 0..n-1 (the jitter is on whenever samples > 1).
  scene::SceneDesc d = sphere_on_background();
  const render::RenderScene rs = render::RenderScene::build(d);
  const render::Tile adaptive = render::render_tile(rs, d.render, {0, 0, d.render.width, d.render.height});
  scene::RenderSettings uniform = d.render;
  uniform.error_target = 0.0;
  uniform.samples = d.render.min_samples;
  const render::Tile first = render::render_tile(rs, uniform, {0, 0, d.render.width, d.render.height});
  std::size_t compared = 0;
  for (std::size_t i = 0; i < adaptive.spp.size(); ++i) {
    if (adaptive.spp[i] != d.render.min_samples) continue;
    ++compared;
    for (int c = 0; c < 3; ++c) REQUIRE(adaptive.rgb[i * 3 + c] == first.rgb[i * 3 + c]);
  }
  CHECK(compared > 0);
}

// The stop rule judges a pixel's error from the spread of its four quarters' means (each quarter
// a net of the stratified sequence), not from s^2/n, which assumes independent samples and
// overstates a stratified pixel's error (the rule until issue 16 took a mean 38.3 spp here at
// target 0.02 and 80.7 at 0.01). The image must still meet the target against the closed form:
// relMSE at most target^2.
TEST_CASE("Stratified pixels stop once their quarters agree, and the image meets the target", "[adaptive]") {
  scene::SceneDesc d = testing::bundled_scene("lit_plane", 64, 48);
  d.render.samples = 256;
  d.render.min_samples = 8;
  const render::RenderScene rs = render::RenderScene::build(d, accel::best_isa());
  std::string why;
  const std::optional<image::ImageRGBf> ref = render::closed_form_reference(d, rs, render::kReferenceGrid, why);
  REQUIRE(ref);
  for (const auto& [target, most_spp] : {std::pair{0.02, 20.0}, std::pair{0.01, 30.0}}) {
    d.render.error_target = target;
    const render::LocalResult r = render_with(rs, d.render, 16, 2, true);
    const auto diff = image::compare_images(r.image, *ref);
    REQUIRE(diff);
    const double mean = mean_spp(r.spp);
    INFO("target " << target << ": mean " << mean << " spp, relMSE " << diff->rel_mse);
    CHECK(mean > d.render.min_samples);
    CHECK(mean <= most_spp);
    CHECK(diff->rel_mse <= target * target);
  }
}
