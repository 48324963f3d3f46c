#include "worker/scene_cache.h"

#include <algorithm>
#include <cassert>
#include <utility>

#include <fmt/format.h>

#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "util/sha256.h"

namespace dtraced::worker {
namespace {

// Load errors quoted in a refusal: the first few say enough, and the message stays one log line.
constexpr std::size_t kMaxQuotedErrors = 3;

// Why a body that does not load is refused: its first few errors.
std::string refusal(const std::string& label, const scene::LoadResult& loaded) {
  std::string reasons;
  for (std::size_t i = 0; i < loaded.errors.size() && i < kMaxQuotedErrors; ++i) {
    reasons += (i == 0 ? "" : "; ") + loaded.errors[i].to_string();
  }
  if (loaded.errors.size() > kMaxQuotedErrors) {
    reasons += fmt::format("; and {} more", loaded.errors.size() - kMaxQuotedErrors);
  }
  return fmt::format("the body sent as {} does not load: {}", label, reasons);
}

}  // namespace

SceneFrames::SceneFrames(render::AnimatedScene scene, std::size_t keep) : scene_(std::move(scene)), keep_(keep) {
  assert(keep >= 1);
}

ScenePtr SceneFrames::frame(std::uint32_t n) const {
  if (!scene_.animated()) return scene_.frame(n);
  std::shared_future<ScenePtr> kept;
  std::promise<ScenePtr> building;
  {
    std::lock_guard lock(mu_);
    const auto it = std::find_if(recent_.begin(), recent_.end(), [n](const auto& entry) { return entry.first == n; });
    if (it != recent_.end()) {
      recent_.splice(recent_.begin(), recent_, it);
      kept = it->second;
    } else {
      recent_.emplace_front(n, building.get_future().share());
      // A frame evicted while it builds stays alive for the threads waiting for it.
      while (recent_.size() > keep_) recent_.pop_back();
    }
  }
  if (kept.valid()) return kept.get();  // built, or being built by another thread: waited for
  try {
    ScenePtr scene = scene_.frame(n);
    building.set_value(scene);
    return scene;
  } catch (...) {
    // Not kept: the next lease of this frame tries again.
    {
      std::lock_guard lock(mu_);
      std::erase_if(recent_, [n](const auto& entry) { return entry.first == n; });
    }
    building.set_exception(std::current_exception());
    throw;
  }
}

render::Tile SceneFrames::render(const scene::RenderSettings& settings, const render::TileRect& rect) const {
  const ScenePtr scene = frame(settings.frame);
  return render::render_tile(*scene, settings, rect);
}

std::size_t SceneFrames::kept() const {
  std::lock_guard lock(mu_);
  return recent_.size();
}

SceneCache::SceneCache(std::size_t capacity) : capacity_(capacity) { assert(capacity >= 1); }

FramesPtr SceneCache::find(std::string_view digest) {
  const auto it = index_.find(digest);
  if (it == index_.end()) return nullptr;
  entries_.splice(entries_.begin(), entries_, it->second);
  return it->second->second;
}

void SceneCache::insert(const std::string& digest, FramesPtr scene) {
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

PreparedScene prepare_scene(std::string_view body, std::string_view digest, accel::Isa isa, unsigned build_threads) {
  PreparedScene prepared;
  const std::string label = fmt::format("scene {}", digest);
  scene::LoadOptions options;
  options.allow_mesh_files = false;
  // A body that is the canonical text itself (what a collector serves) has the digest's SHA-256,
  // and no other text can have it: then the scene needs no second serialisation to be checked,
  // and a static one's objects go straight into the render-ready scene as they are read (the
  // description of a large scene is never held whole).
  if (util::sha256_hex(body) == digest) {
    render::RenderSceneBuilder builder;
    scene::LoadOptions streamed = options;
    streamed.object_sink = &builder;
    scene::LoadResult loaded = scene::load_scene_string(body, label, streamed);
    if (!loaded.ok()) {
      prepared.error = refusal(label, loaded);
      return prepared;
    }
    if (!scene::is_animated(*loaded.scene)) {
      prepared.scene = std::make_shared<const SceneFrames>(
          render::AnimatedScene::still(std::move(builder).build(*loaded.scene, isa, build_threads)));
      return prepared;
    }
    // Animated: its frames are built from the description, loaded again below with its objects.
  }
  scene::LoadResult loaded = scene::load_scene_string(body, label, options);
  if (!loaded.ok()) {
    prepared.error = refusal(label, loaded);
    return prepared;
  }
  const std::string actual = scene::scene_digest(*loaded.scene);
  if (actual != digest) {
    prepared.error = fmt::format("the body sent as {} is another scene (its digest is {})", label, actual);
    return prepared;
  }
  prepared.scene =
      std::make_shared<const SceneFrames>(render::AnimatedScene::prepare(*loaded.scene, isa, build_threads));
  return prepared;
}

}  // namespace dtraced::worker
