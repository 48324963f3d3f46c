// What the worker tests share: the tiny scene they render and what they compare its tiles with,
// and a valid configuration that points a worker at a collector on 127.0.0.1.
#pragma once

#include <chrono>
#include <cstdint>
#include <cstring>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>
#include <fmt/format.h>

#include "render/render_scene.h"
#include "scene/description.h"
#include "scene/load.h"
#include "worker/config.h"
#include "worker/scene_cache.h"

namespace dtraced::testing {

using namespace std::chrono_literals;

// The longest any single wait in the worker tests may take, in real time, before the test fails
// instead of hanging: a bound on events over loopback sockets, never a delay the worker needs.
inline constexpr auto kBound = 30s;
inline constexpr std::string_view kToken = "test-token-0123456789";
inline constexpr std::uint64_t kJob = 7;
inline constexpr std::uint32_t kTileSize = 16;

// 32 x 32 pixels in 16-pixel tiles: four tiles. Two samples and a reflective sphere, so the
// sampling hash and the secondary rays are both exercised.
inline constexpr std::string_view kTinyScene = R"({
  "camera": {"position": [0, 0.5, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 40},
  "render": {"width": 32, "height": 32, "samples": 2, "max_depth": 3, "background": [0.1, 0.2, 0.3], "seed": 11},
  "scene_objects": [
    {"type": "plane", "loc": [0, -1, 0], "normal": [0, 1, 0], "material": {"color": [0.8, 0.8, 0.8]}},
    {"type": "sphere", "loc": [0, 0, 0], "radius": 1,
     "material": {"color": [0.9, 0.3, 0.2], "specular": 0.3, "reflectivity": 0.2}}
  ],
  "scene_lights": [{"type": "point", "loc": [4, 5, 5], "intensity": 60}]
})";

inline scene::SceneDesc load_tiny_scene() {
  scene::LoadResult loaded = scene::load_scene_string(kTinyScene, "tiny");
  REQUIRE(loaded.ok());
  return *loaded.scene;
}

// The same scene with the sphere's radius changed: another digest.
inline scene::SceneDesc other_scene(double radius) {
  scene::SceneDesc desc = load_tiny_scene();
  desc.objects.at(1).sphere.radius = radius;
  return desc;
}

inline worker::ScenePtr build(const scene::SceneDesc& desc) {
  return std::make_shared<const render::RenderScene>(render::RenderScene::build(desc));
}

inline bool same_bits(const std::vector<float>& a, const std::vector<float>& b) {
  return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(float)) == 0;
}

// Two threads, four tiles in hand, a fixed jitter seed, and backoffs of a few milliseconds (which
// pass on the test's clock, not in real time). Socket timeouts are kBound: real time, as they are
// for a real worker.
inline worker::WorkerConfig test_config(std::uint16_t port) {
  worker::WorkerConfig config;
  config.collector_url = fmt::format("http://127.0.0.1:{}", port);
  config.token = std::string(kToken);
  config.name = "test-worker";
  config.threads = 2;
  config.scene_cache = 2;
  config.grace = 60s;
  config.timeouts = {kBound, kBound, kBound};
  config.backoff_initial = 2ms;
  config.backoff_max = 40ms;
  config.max_unacknowledged = 4;
  config.jitter_seed = 42;
  return config;
}

}  // namespace dtraced::testing
