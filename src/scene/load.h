// dtraced::scene loading: JSON scene files into SceneDesc (description.h), with strict
// validation that reports every problem with its file and JSON Pointer path.
//
// Owns: the scene file format (documented in README.md, "Scene files") and its limits. A scene
// either loads completely and satisfies every invariant stated in description.h, or no scene is
// returned and `errors` says why; there is no partially loaded scene. Problems are collected, not
// thrown, and the loader keeps going after the first one so a user fixes a file in one pass.
//
// Beyond the invariants in description.h, a loaded scene also guarantees: every number fits a
// float (|x| <= FLT_MAX), plane normals have unit length, the camera position and look_at differ
// even after conversion to float, and `up` is not parallel to the view direction. A mesh object
// holds its OBJ text (valid UTF-8, so the canonical form can carry it inline) and its finite,
// transformed triangles; the scene's meshes hold at most LoadOptions::max_triangles in all.
//
// Mesh files ("file": a Wavefront OBJ) are the one thing a scene reads besides itself: relative
// to the scene file's directory (load_scene_file) or to LoadOptions::base_dir (load_scene_string).
// Scenes that arrive over the network are loaded with allow_mesh_files = false, so a scene can
// never make a collector or a worker read a file of its host.
//
// Stateless functions: thread-safe; concurrent loads share nothing. A load may start one thread of
// its own (LoadOptions::parallel_min_bytes, off by default) and joins it before returning.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "scene/description.h"
#include "util/result.h"

namespace dtraced::scene {

// Scenes that travel (uploads, a worker's fetch) are held to kMaxSceneBytes by the HTTP layer; a
// local scene file may be larger, up to kMaxSceneFileBytes: 10M spheres in canonical form are
// about 3 GB.
inline constexpr std::uint64_t kMaxSceneBytes = 256ull << 20;    // 256 MiB
inline constexpr std::uint64_t kMaxSceneFileBytes = 4ull << 30;  // 4 GiB
inline constexpr std::size_t kMaxJsonDepth = 64;                 // nesting levels
inline constexpr std::size_t kMaxObjects = 10'000'000;
inline constexpr std::size_t kMaxLights = 10'000;
inline constexpr std::size_t kMaxReportedErrors = 1000;      // a broken 10M-object file stays readable
inline constexpr std::uint64_t kMaxObjBytes = 512ull << 20;  // one OBJ file, 512 MiB
// Triangles of all the meshes of one scene: 20M triangles are about 720 MB of float vertices in
// the description, and as many again once built for rendering.
inline constexpr std::size_t kMaxTriangles = 20'000'000;
// From this size on a scene's objects are read on a second thread (LoadOptions::parallel_min_bytes):
// never, by default. On the 2-core machine the figures come from, the 1M-sphere load (323 MB) on
// the calling thread alone took 0.82 of the threaded wall time, 0.72 of its CPU and 10 MiB less
// peak (7 alternated runs, load average 1.4-2): run at once, the two threads each ran at about
// half speed (the parser's events are read on the other core), so the threaded load cost 1.4-1.5 s
// of CPU against 0.8-0.95 s with both threads pinned to one core. A machine whose cores share a
// cache may find otherwise; the pipeline stays, and tests keep both paths equal.
inline constexpr std::uint64_t kParallelLoadBytes = UINT64_MAX;

// Problems are util::Error{message, path, file}: `path` a JSON Pointer into the file
// ("/scene_objects/3/radius"), empty for problems with the file as a whole; to_string() gives
// "FILE: /scene_objects/3/radius: must be > 0 (got -1)".

// Where the objects of "scene_objects" can go instead of SceneDesc::objects (LoadOptions::object_sink):
// a consumer that keeps only what it needs of each (render::RenderSceneBuilder keeps the render-
// ready shape and material, 84 bytes a sphere where the description holds 144), so the
// description of millions of objects is never held whole.
class ObjectSink {
 public:
  virtual ~ObjectSink() = default;
  // Room for about `objects` objects in all (a prediction from the objects per byte so far; it
  // may be off either way). Called before add() needs it, a few times per load.
  virtual void reserve(std::size_t objects) = 0;
  // The next valid object of "scene_objects" (`index` its place there), in file order. One call
  // at a time, on one thread (the load's reader thread for a large text), all before the load
  // returns. After the load an object's problems may still fail it: then discard what was added.
  virtual void add(std::size_t index, const Object& object) = 0;
};

struct LoadOptions {
  std::uint64_t max_bytes = kMaxSceneFileBytes;
  // Past this many errors the rest are counted in one final error; tests lower it.
  std::size_t max_errors = kMaxReportedErrors;
  // Whether meshes may name a "file". False for scenes from the network (the collector decoding
  // a submission, a worker loading a fetched scene): each such mesh is then an error.
  bool allow_mesh_files = true;
  // Directory that relative mesh "file" paths are resolved against, for load_scene_string ("":
  // the current directory). load_scene_file always uses the scene file's own directory.
  std::string base_dir;
  std::uint64_t max_obj_bytes = kMaxObjBytes;  // per OBJ file
  std::size_t max_triangles = kMaxTriangles;   // per scene, all meshes together
  // A text of at least this many bytes has its objects read on a second thread while the first
  // parses on (same scene, same errors, in the same order, either way); tests lower it.
  std::uint64_t parallel_min_bytes = kParallelLoadBytes;
  // Not null: every object goes to the sink as it is read, and the loaded SceneDesc::objects is
  // empty (camera, render settings, lights and animation tracks are loaded as usual). For a
  // static scene: the objects of an animated one (is_animated) went to the sink with their
  // base values, so load such a scene again without a sink. Errors and warnings are the same.
  ObjectSink* object_sink = nullptr;
};

struct LoadResult {
  std::optional<SceneDesc> scene;  // set exactly when errors is empty
  util::Errors errors;
  // Legal but probably unintended (no lights, no objects). Never stop a load.
  util::Errors warnings;

  bool ok() const { return scene.has_value() && errors.empty(); }
};

// Reads and validates a scene file. A file that cannot be read, or is larger than
// options.max_bytes, gives one error naming the file.
LoadResult load_scene_file(const std::string& path, const LoadOptions& options = {});

// Validates scene JSON held in memory (an upload, a fetched scene). `file_name` only labels errors;
// mesh files are found through options.base_dir.
LoadResult load_scene_string(std::string_view json, const std::string& file_name, const LoadOptions& options = {});

// One error per line, each Error::to_string and a newline; for stderr.
std::string format_errors(const util::Errors& errors);

}  // namespace dtraced::scene
