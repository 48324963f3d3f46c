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
// even after conversion to float, and `up` is not parallel to the view direction.
//
// Stateless functions: thread-safe; concurrent loads share nothing.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "scene/description.h"

namespace dtraced::scene {

inline constexpr std::uint64_t kMaxSceneBytes = 256ull << 20;  // 256 MiB
inline constexpr std::size_t kMaxJsonDepth = 64;               // nesting levels
inline constexpr std::size_t kMaxObjects = 10'000'000;
inline constexpr std::size_t kMaxLights = 10'000;
inline constexpr std::uint64_t kMaxSeed = (1ull << 53) - 1;  // seeds survive a trip through a JS double
inline constexpr std::size_t kMaxReportedErrors = 1000;      // a broken 10M-object file stays readable

// One problem, located. `path` is a JSON Pointer into the file ("/scene_objects/3/radius"),
// empty for problems with the file as a whole.
struct SceneError {
  std::string file;
  std::string path;
  std::string message;

  // "FILE: /scene_objects/3/radius: must be > 0 (got -1)"; "FILE: message" when path is empty.
  std::string to_string() const;
  bool operator==(const SceneError&) const = default;
};

struct LoadOptions {
  std::uint64_t max_bytes = kMaxSceneBytes;
  // Past this many errors the rest are counted in one final error; tests lower it.
  std::size_t max_errors = kMaxReportedErrors;
};

struct LoadResult {
  std::optional<SceneDesc> scene;  // set exactly when errors is empty
  std::vector<SceneError> errors;
  // Legal but probably unintended (no lights, no objects). Never stop a load.
  std::vector<SceneError> warnings;

  bool ok() const { return scene.has_value() && errors.empty(); }
};

// Reads and validates a scene file. A file that cannot be read, or is larger than
// options.max_bytes, gives one error naming the file.
LoadResult load_scene_file(const std::string& path, const LoadOptions& options = {});

// Validates scene JSON held in memory (an upload, a fetched scene). `file_name` only labels errors.
LoadResult load_scene_string(std::string_view json, const std::string& file_name, const LoadOptions& options = {});

// One error per line, each formatted by SceneError::to_string; for stderr and HTTP bodies.
std::string format_errors(const std::vector<SceneError>& errors);

}  // namespace dtraced::scene
