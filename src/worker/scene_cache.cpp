#include "worker/scene_cache.h"

#include <cassert>
#include <utility>

#include <fmt/format.h>

#include "scene/digest.h"
#include "scene/load.h"

namespace dtraced::worker {
namespace {

// Load errors quoted in a refusal: the first few say enough, and the message stays one log line.
constexpr std::size_t kMaxQuotedErrors = 3;

}  // namespace

SceneCache::SceneCache(std::size_t capacity) : capacity_(capacity) { assert(capacity >= 1); }

ScenePtr SceneCache::find(std::string_view digest) {
  const auto it = index_.find(digest);
  if (it == index_.end()) return nullptr;
  entries_.splice(entries_.begin(), entries_, it->second);
  return it->second->second;
}

void SceneCache::insert(const std::string& digest, ScenePtr scene) {
  assert(scene != nullptr);
  if (const auto it = index_.find(digest); it != index_.end()) {
    it->second->second = std::move(scene);
    entries_.splice(entries_.begin(), entries_, it->second);
    return;
  }
  entries_.emplace_front(digest, std::move(scene));
  index_.emplace(entries_.front().first, entries_.begin());
  while (entries_.size() > capacity_) {
    index_.erase(entries_.back().first);
    entries_.pop_back();
  }
}

bool SceneCache::contains(std::string_view digest) const { return index_.contains(digest); }

PreparedScene prepare_scene(std::string_view body, std::string_view digest, accel::Isa isa) {
  PreparedScene prepared;
  const std::string label = fmt::format("scene {}", digest);
  scene::LoadOptions options;
  options.allow_mesh_files = false;
  scene::LoadResult loaded = scene::load_scene_string(body, label, options);
  if (!loaded.ok()) {
    std::string reasons;
    for (std::size_t i = 0; i < loaded.errors.size() && i < kMaxQuotedErrors; ++i) {
      reasons += (i == 0 ? "" : "; ") + loaded.errors[i].to_string();
    }
    if (loaded.errors.size() > kMaxQuotedErrors) {
      reasons += fmt::format("; and {} more", loaded.errors.size() - kMaxQuotedErrors);
    }
    prepared.error = fmt::format("the body sent as {} does not load: {}", label, reasons);
    return prepared;
  }
  const std::string actual = scene::scene_digest(*loaded.scene);
  if (actual != digest) {
    prepared.error = fmt::format("the body sent as {} is another scene (its digest is {})", label, actual);
    return prepared;
  }
  prepared.scene = std::make_shared<const render::RenderScene>(render::RenderScene::build(*loaded.scene, isa));
  return prepared;
}

}  // namespace dtraced::worker
