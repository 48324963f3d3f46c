// The pixel version (protocol::kPixelVersion) names the renderer's output: the collector leases
// only to workers of its own version, so that a farm in the middle of an upgrade never mixes two
// renderers' pixels in one image. That only works if every change to the pixels bumps it. This
// test renders a small set of scenes that between them use every feature (reflection,
// refraction, specular, point and area lights, soft shadows, meshes, adaptive sampling) and
// compares a SHA-256 of their pixels with the digest recorded for the current version. A change
// that alters any pixel fails here until the version is bumped and its digest recorded: the
// failure prints the digest to add. The digest is the same on every instruction set and thread
// count and on every little-endian host (the float bits are hashed as they are in memory).
#include <cstdint>
#include <cstring>
#include <map>
#include <string>
#include <string_view>

#include <catch2/catch.hpp>

#include "accel/isa.h"
#include "protocol/worker_messages.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "render_checks.h"
#include "scene/load.h"
#include "util/sha256.h"

namespace dtraced {
namespace {

// Every pixel version and the digest of its reference renders. A new version adds a line; the
// old lines stay as the record of what each version rendered.
const std::map<std::uint32_t, std::string_view> kDigests = {
    {1, "7dab6890d679f41040299b03aadfe3810e0dbb8a13a518908bd78adf3c4d494b"},
    // Issue 16: adaptive sampling's neighbourhood rule and prior (render/tile.cpp); the
    // min_samples 1 reference was added with it.
    {2, "fd06bc473e623cc02dff0acf76e3dbdc574d907f1cca2b787c990b74a7236679"},
    // Issue 16: pow, sin, cos, tan and exp2 from math/det_math.h instead of the C library (whose
    // results depend on the host's libc and on its CPU: glibc picks an FMA variant at run time).
    {3, "9889f122b5736f9f0b97caaed0c60bc9ef502994c597fd1663d8a2fbbd86889a"},
    // math::det::pow_fast from tables (the specular lobe and sRGB encoding): the references render
    // the same bits, but version 3 rounded about 1 in 5,000 powf results to the other neighbouring
    // float, so two versions in one farm could still differ in a rare pixel.
    {4, "9889f122b5736f9f0b97caaed0c60bc9ef502994c597fd1663d8a2fbbd86889a"},
    // Static scenes with glass split into an opaque and a transparent layer (render_scene.cpp): the
    // references render the same bits, but where a shadow ray meets an opaque and a transparent
    // surface at exactly the same t and the transparent one has the smaller shape id (a glass face
    // level with an opaque plane), version 4 let light through and version 5 blocks it.
    {5, "9889f122b5736f9f0b97caaed0c60bc9ef502994c597fd1663d8a2fbbd86889a"},
};

struct Reference {
  const char* scene;
  double error_target;            // 0: uniform sampling
  std::uint32_t min_samples = 4;  // adaptive sampling's first checkpoint
};

// Small and few, so that the test stays cheap: 48x32 pixels, 4 samples (adaptive: up to 16).
constexpr Reference kReferences[] = {
    {"showcase.json", 0},    {"soft_shadows.json", 0},       {"mesh.json", 0}, {"room.json", 0}, {"snowman.json", 0},
    {"showcase.json", 0.05}, {"soft_shadows.json", 0.08, 1},
};

std::string reference_bytes(const Reference& ref, accel::Isa isa) {
  scene::LoadResult loaded = scene::load_scene_file(std::string(DTRACED_SOURCE_DIR) + "/scenes/" + ref.scene);
  INFO(ref.scene);
  REQUIRE(loaded.ok());
  scene::SceneDesc d = *loaded.scene;
  d.render.width = 48;
  d.render.height = 32;
  d.render.samples = ref.error_target > 0 ? 16 : 4;
  d.render.error_target = ref.error_target;
  if (ref.error_target > 0) d.render.min_samples = ref.min_samples;
  const render::RenderScene rs = render::RenderScene::build(d, isa);
  const render::LocalResult r = render::render_local(rs, d.render, testing::local_options(0, 16));
  REQUIRE(r.complete);
  std::string bytes(reinterpret_cast<const char*>(r.image.rgb.data()), r.image.rgb.size() * sizeof(float));
  bytes.append(reinterpret_cast<const char*>(r.spp.data()), r.spp.size() * sizeof(std::uint32_t));
  return bytes;
}

}  // namespace

TEST_CASE("the reference renders match the digest recorded for this pixel version", "[render][pixel_version]") {
  // Rendered on every instruction set this machine has: one digest for all of them.
  std::string digest;
  for (const accel::Isa isa : accel::supported_isas()) {
    INFO("isa " << accel::isa_name(isa));
    std::string all;
    for (const Reference& ref : kReferences) {
      const std::string bytes = reference_bytes(ref, isa);
      REQUIRE(!bytes.empty());
      all += util::sha256_hex(bytes);
    }
    const std::string this_isa = util::sha256_hex(all);
    if (digest.empty()) digest = this_isa;
    REQUIRE(this_isa == digest);
  }
  const auto recorded = kDigests.find(protocol::kPixelVersion);
  INFO("pixel version " << protocol::kPixelVersion << " renders the references to " << digest
                        << "; if the renderer's output was meant to change, bump protocol::kPixelVersion "
                           "(src/protocol/worker_messages.h) and add this digest for it in kDigests");
  REQUIRE(recorded != kDigests.end());
  CHECK(recorded->second == digest);
}

TEST_CASE("a different seed changes the reference digest, so the check above can fail", "[render][pixel_version]") {
  scene::LoadResult loaded = scene::load_scene_file(std::string(DTRACED_SOURCE_DIR) + "/scenes/showcase.json");
  REQUIRE(loaded.ok());
  scene::SceneDesc d = *loaded.scene;
  d.render.width = 16;
  d.render.height = 16;
  d.render.samples = 2;
  const render::RenderScene rs = render::RenderScene::build(d);
  const auto a = render::render_local(rs, d.render, testing::local_options(1, 16));
  scene::RenderSettings other = d.render;
  other.seed += 1;
  const auto b = render::render_local(rs, other, testing::local_options(1, 16));
  const auto hash = [](const render::LocalResult& r) {
    return util::sha256_hex(
        std::string_view(reinterpret_cast<const char*>(r.image.rgb.data()), r.image.rgb.size() * sizeof(float)));
  };
  CHECK(hash(a) != hash(b));
}

}  // namespace dtraced
