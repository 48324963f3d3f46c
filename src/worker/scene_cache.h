// dtraced::worker scene cache: render-ready scenes by content digest, bounded, least recently used
// evicted; and the one step that turns a fetched scene body into a verified, built scene.
//
// Scenes are immutable and named by the SHA-256 of their canonical form (scene/digest.h), so a
// cached scene never goes stale and a body can be checked against the digest that names it. A
// scene evicted while tiles still render from it stays alive until they finish (shared_ptr); the
// cache bounds what is kept for later, not what is in use.
//
// Thread-safety: SceneCache has none; one owner (the worker's event loop) calls it.
// prepare_scene is a pure function, thread-safe, and meant for the render pool: parsing a large
// scene and building its BVH take too long for an event loop.
#pragma once

#include <cstddef>
#include <list>
#include <memory>
#include <string>
#include <string_view>
#include <unordered_map>

#include "render/render_scene.h"

namespace dtraced::worker {

using ScenePtr = std::shared_ptr<const render::RenderScene>;

class SceneCache {
 public:
  // capacity >= 1 (asserted).
  explicit SceneCache(std::size_t capacity);

  // The scene named `digest`, which becomes the most recently used; null when not cached.
  ScenePtr find(std::string_view digest);

  // Adds (or replaces) `digest` as the most recently used, evicting the least recently used
  // scenes beyond the capacity. `scene` is not null (asserted).
  void insert(const std::string& digest, ScenePtr scene);

  // Whether `digest` is cached, without marking it used.
  bool contains(std::string_view digest) const;

  std::size_t size() const { return entries_.size(); }
  std::size_t capacity() const { return capacity_; }

 private:
  using Entry = std::pair<std::string, ScenePtr>;

  std::size_t capacity_;
  std::list<Entry> entries_;  // most recently used first
  // Keys view the digests held by entries_ (list nodes do not move).
  std::unordered_map<std::string_view, std::list<Entry>::iterator> index_;
};

// A verified, built scene, or why the body was refused.
struct PreparedScene {
  ScenePtr scene;     // set on success
  std::string error;  // set on failure
};

// Loads `body` (scene JSON as GET /v1/scenes/{digest} answers it), checks that the scene it
// describes has the digest `digest` (scene_digest of the loaded scene, i.e. the SHA-256 of its
// canonical form), and builds the render-ready scene with the kernels of `isa`. A body that does
// not load, or that names another scene (tampered, truncated, or from a collector of another
// version), is refused; so is one with a mesh "file": a worker reads nothing from its own disk
// on a scene's behalf (canonical scenes carry their meshes inline).
PreparedScene prepare_scene(std::string_view body, std::string_view digest, accel::Isa isa);

}  // namespace dtraced::worker
