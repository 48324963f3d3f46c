// dtraced::scene canonical form and content digest.
//
// Owns: the one serialisation of a SceneDesc that names it. Scenes travel by digest (a lease
// names the digest, a worker fetches and caches the scene), so two files that mean the same
// scene must get the same digest and any change that can alter a pixel must change it.
//
// The canonical JSON is a valid scene file: fixed key order, no whitespace, every field written
// (defaults included), boxes as "min"/"max" corners, numbers as the shortest text that reads back
// to the same double (integral values as integers). For any scene produced by the loader,
// load_scene_string(canonical_json(d)) gives back a SceneDesc equal to d, bit for bit.
//
// Meshes are written with their OBJ text inline ("obj", byte for byte as read) and their
// transform spelled out ("translate", "rotate", "scale" as [x, y, z]), never as a "file": the
// canonical form loads on any host, and a mesh read from a file has the same digest as the same
// text given inline. Any byte of the OBJ text (even a comment) is part of the digest.
//
// Pure functions: thread-safe.
#pragma once

#include <string>

#include "scene/description.h"

namespace dtraced::scene {

std::string canonical_json(const SceneDesc& desc);

// Lower-case hex SHA-256 of canonical_json(desc).
std::string scene_digest(const SceneDesc& desc);

}  // namespace dtraced::scene
