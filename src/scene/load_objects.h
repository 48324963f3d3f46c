// dtraced::scene loading, internal: what load.cpp (the document, camera and render block) and
// load_objects.cpp (objects, their materials and meshes, lights) share. Not for other modules:
// they call load.h.
//
// One SceneReader per load: not thread-safe; loads share nothing.
#pragma once

#include <array>
#include <cstddef>
#include <optional>
#include <string>
#include <utility>

#include <boost/json/value.hpp>

#include "jsonio/parse.h"
#include "jsonio/reader.h"
#include "scene/animation.h"
#include "scene/description.h"
#include "scene/load.h"

namespace dtraced::scene::detail {

// Names other renderers and the seed project's users reach for, mapped to ours (jsonio::KeyAlias).
inline constexpr std::array<jsonio::KeyAlias, 9> kKeyAliases = {{
    {"center", "loc"},
    {"centre", "loc"},
    {"position", "loc"},
    {"pos", "loc"},
    {"fov_deg", "fov"},
    {"spp", "samples"},
    {"objects", "scene_objects"},
    {"lights", "scene_lights"},
    {"eye", "position"},
}};

// The state of one load: the located reader, the options, the meshes' triangle budget, the tracks
// of animated values read so far and the warnings (legal but probably unintended; they never stop
// a load).
struct SceneReader {
  SceneReader(std::string file, const LoadOptions& options_)
      : r(std::move(file), options_.max_errors), options(options_) {}

  void warning(const jsonio::Path& at, std::string message) {
    warnings.push_back({std::move(message), at.str(), r.file()});
  }

  jsonio::Reader r;
  const LoadOptions& options;
  std::size_t triangles = 0;  // of the meshes read so far, against options.max_triangles
  Animation animation;        // every track read so far, in file order
  std::uint32_t index = 0;    // the object or light being read: the owner of its tracks
  util::Errors warnings;
};

// One element of "scene_objects" / "scene_lights", or nullopt after reporting its problems.
std::optional<Object> read_object(SceneReader& s, const boost::json::value& v, const jsonio::Path& at);
std::optional<Light> read_light(SceneReader& s, const boost::json::value& v, const jsonio::Path& at);

// The object read_object would read, without a word, from the element of "scene_objects" whose
// parse events are `from` to `to` in `log`, when it is a sphere of the common shape: the keys
// "type" ("sphere"), "loc" and "radius" and maybe "material", each once, with plain numbers (no
// animation) and nothing else, every value valid. Nullopt for anything else, a problem included:
// then read_object reads the element's value and reports it. Reports nothing; the sphere's bits
// are read_object's (the same conversion, the same -0 to +0).
std::optional<Object> read_plain_sphere(const jsonio::EventLog& log, jsonio::EventLog::Mark from,
                                        jsonio::EventLog::Mark to);

}  // namespace dtraced::scene::detail
