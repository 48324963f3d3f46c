// dtraced::worker scene cache: prepared scenes by content digest, bounded, least recently used
// evicted; the frames of an animated scene built lately (SceneFrames); and the one step that turns
// a fetched scene body into a verified, prepared scene.
//
// Scenes are immutable and named by the SHA-256 of their canonical form (scene/digest.h), so a
// cached scene never goes stale and a body can be checked against the digest that names it. A
// scene evicted while tiles still render from it stays alive until they finish (shared_ptr); the
// cache bounds what is kept for later, not what is in use.
//
// Thread-safety: SceneCache has none; one owner (the worker's event loop) calls it. SceneFrames is
// thread-safe: the render threads ask it for frames at once.
// prepare_scene is a pure function, thread-safe, and meant for the render pool: parsing a large
// scene and building its BVH take too long for an event loop.
#pragma once

#include <cstddef>
#include <cstdint>
#include <future>
#include <list>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <unordered_map>
#include <utility>

#include "render/render_scene.h"
#include "render/tile.h"
#include "util/result.h"

namespace dtraced::worker {

using ScenePtr = std::shared_ptr<const render::RenderScene>;

// A prepared scene and the render-ready frames built from it lately. The leases of a sequence
// come frame after frame, a few frames in flight at once (one per render thread at worst): those
// are kept, so a frame's moving layer is built once per worker, not once per tile. A static scene
// has one RenderScene for every frame and keeps nothing more.
class SceneFrames {
 public:
  // Frames kept per scene (least recently asked for evicted).
  static constexpr std::size_t kKeptFrames = 4;

  // keep >= 1 (asserted).
  explicit SceneFrames(render::AnimatedScene scene, std::size_t keep = kKeptFrames);

  // Frame n (render::AnimatedScene::frame), built at most once while kept: a thread asking for a
  // frame another is building waits for it. Builds on the calling thread (a render thread).
  ScenePtr frame(std::uint32_t n) const;

  // A lease's tile: `rect` of frame settings.frame, rendered with `settings` (the lease's).
  render::Tile render(const scene::RenderSettings& settings, const render::TileRect& rect) const;

  // How many frames are kept now (built or being built).
  std::size_t kept() const;
  const render::AnimatedScene& scene() const { return scene_; }

 private:
  render::AnimatedScene scene_;
  std::size_t keep_;
  mutable std::mutex mu_;
  // Most recently asked for first; guarded by mu_.
  mutable std::list<std::pair<std::uint32_t, std::shared_future<ScenePtr>>> recent_;
};

using FramesPtr = std::shared_ptr<const SceneFrames>;

class SceneCache {
 public:
  // capacity >= 1 (asserted).
  explicit SceneCache(std::size_t capacity);

  // The scene named `digest`, which becomes the most recently used; null when not cached.
  FramesPtr find(std::string_view digest);

  // Adds (or replaces) `digest` as the most recently used, evicting the least recently used
  // scenes beyond the capacity. `scene` is not null (asserted).
  void insert(const std::string& digest, FramesPtr scene);

  // Whether `digest` is cached, without marking it used.
  bool contains(std::string_view digest) const;

  std::size_t size() const { return entries_.size(); }
  std::size_t capacity() const { return capacity_; }

 private:
  using Entry = std::pair<std::string, FramesPtr>;

  std::size_t capacity_;
  std::list<Entry> entries_;  // most recently used first
  // Keys view the digests held by entries_ (list nodes do not move).
  std::unordered_map<std::string_view, std::list<Entry>::iterator> index_;
};

// A verified, prepared scene, or why the body was refused.
struct PreparedScene {
  FramesPtr scene;      // set on success
  std::string error;    // set on failure
  std::string warning;  // a scene cache file that could not be read or written (the scene is fine)
};

// ---- binary scene cache ------------------------------------------------------------------------
// A static scene in render-ready form (shapes, materials, owners, transparent objects, and the
// description without its objects as canonical JSON), one file per digest, so that a worker that
// meets the digest again skips the JSON parse (a few seconds for a million spheres). The BVH is
// built again from the shapes: the same bits as from the JSON.
//
// Layout (host byte order: the file is this host's, never sent): a fixed header (magic,
// kCacheVersion, a byte-order mark, the sizes of a shape and a material, the digest of the JSON
// the scene came from, each section's length and SHA-256), then the sections. Reading checks
// everything before it trusts a byte: the magic, version, layout and digest, each length against
// its bound and the file's size, each section's SHA-256, and that the parts fit together
// (render::RenderSceneBuilder::from_parts); any failure is an error naming the file.
inline constexpr std::uint32_t kCacheVersion = 1;
inline constexpr std::uint64_t kMaxCachedDescBytes = 16ull << 20;  // camera, settings, up to 10k lights

// DIR/DIGEST.dtscene
std::string cached_scene_path(const std::string& dir, std::string_view digest);

// Keeps at most `keep` cache files (*.dtscene) in `dir`: the least recently used (oldest
// modification time; the worker touches a file it reads) are removed. Other files are left alone.
// Returns how many were removed; a file that cannot be removed is skipped.
std::size_t prune_scene_cache(const std::string& dir, std::size_t keep);

// Writes the objects `builder` holds and `desc` (a static scene's description without objects:
// camera, settings, lights) to `path` under `digest`, through a temporary file renamed over it.
util::Status write_cached_scene(const std::string& path, std::string_view digest, const scene::SceneDesc& desc,
                                const render::RenderSceneBuilder& builder);

// The scene of a cache file written by write_cached_scene under `digest`, prepared with the
// kernels of `isa` on up to `build_threads` threads; an error naming the file when it is
// missing, truncated, corrupt, of another version or layout, or of another digest.
util::Result<FramesPtr> read_cached_scene(const std::string& path, std::string_view digest, accel::Isa isa,
                                          unsigned build_threads = 0);

// Loads `body` (scene JSON as GET /v1/scenes/{digest} answers it), checks that the scene it
// describes has the digest `digest` (scene_digest of the loaded scene, i.e. the SHA-256 of its
// canonical form), and prepares it with the kernels of `isa` (render::AnimatedScene::prepare: a
// static scene is built whole, an animated one its static layer). A body that does
// not load, or that names another scene (tampered, truncated, or from a collector of another
// version), is refused; so is one with a mesh "file": a worker reads nothing from its own disk
// on a scene's behalf (canonical scenes carry their meshes inline).
// The BVH is built on up to `build_threads` threads (0: the CPUs this process may use).
// With a `cache_dir`, a static scene is read from its cache file there when it has one (a file
// that does not read is a warning, and the body is loaded instead), and written there after the
// body's first load (a failure to write is a warning).
PreparedScene prepare_scene(std::string_view body, std::string_view digest, accel::Isa isa, unsigned build_threads = 0,
                            const std::string& cache_dir = {});

}  // namespace dtraced::worker
