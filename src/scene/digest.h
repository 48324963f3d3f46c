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
// Pure functions: thread-safe. ObjectsDigest: one per load, used by one thread at a time.
#pragma once

#include <cstddef>
#include <string>

#include "scene/description.h"
#include "scene/load.h"
#include "util/sha256.h"

namespace dtraced::scene {

std::string canonical_json(const SceneDesc& desc);

// Lower-case hex SHA-256 of canonical_json(desc).
std::string scene_digest(const SceneDesc& desc);

// A digest of the objects of a load that streams them (LoadOptions::object_sink), for a key that
// must change with anything of an object that can change a pixel while the objects are never held
// whole: `dtraced render` names its partial files by it and the description without objects. It
// passes every object on to `next` (may be null) after taking it in.
//
// Not the scene digest (that needs the canonical text in its order, camera first): its bytes are
// each object's fields in binary, host byte order (a key for this host's files, not one that
// travels), hashed in chunks of kChunkBytes whose SHA-256s are hashed again at the end.
class ObjectsDigest final : public ObjectSink {
 public:
  static constexpr std::size_t kChunkBytes = 1 << 20;

  explicit ObjectsDigest(ObjectSink* next = nullptr) : next_(next) {}
  void reserve(std::size_t objects) override;
  void add(std::size_t index, const Object& object) override;
  // Lower-case hex SHA-256 over the objects added so far (their count included).
  std::string hex() const;
  std::size_t count() const { return count_; }

 private:
  void flush();

  ObjectSink* next_;
  std::string chunk_;      // the bytes of the objects since the last full chunk
  std::string digests_;    // the SHA-256 of every full chunk, 32 bytes each
  std::size_t count_ = 0;  // objects added
};

}  // namespace dtraced::scene
