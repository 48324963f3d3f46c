// dtraced::cli partial renders: the file that keeps a local render's finished tiles when it is
// interrupted (Ctrl-C), so that `render --resume` continues it (as POV-Ray's +C does).
//
// Owns: the partial file's format, its writer and its reader. The file sits next to the output,
// OUT.partial, and is append-only, which is why it is a small binary file and not a database:
//
//   header  "dtraced-partial-v1\n" KEY "\n"        (KEY: partial_key, 64 hex digits)
//   record  "TILE" index:u32 bytes:u32 payload[bytes] sha256[32]   (repeated; little-endian)
//           payload = the tile's rgb floats (width*height*3), then its spp counts (width*height
//           u32, adaptive renders only); sha256 is over index, bytes and payload.
//
// Appending a tile costs its own size (rewriting a whole image per tile would not), survives a
// kill at any instant (a torn last record fails its checksum and is dropped, with the tiles
// before it kept), and a tile's floats go to the file and come back bit for bit. The KEY is the
// SHA-256 of the scene's digest (the canonical scene, render settings included) and the tile
// size: the only inputs of the pixels, so a partial from another scene or other settings is
// refused rather than mixed in.
//
// Thread safety: PartialWriter is not thread-safe (render_local serialises its tile_done calls);
// the functions are stateless.
#pragma once

#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <vector>

#include "render/tile.h"
#include "scene/description.h"
#include "util/result.h"

namespace dtraced::cli {

// What names a render's pixels: SHA-256 hex of the scene digest (settings applied) and tile size.
std::string partial_key(const scene::SceneDesc& desc, std::uint32_t tile_size);

// OUT.partial.
std::string partial_path(const std::string& output);

struct PartialContents {
  std::vector<render::Tile> tiles;  // distinct, checked against the grid
  std::uint64_t good_bytes = 0;     // the file's length up to the last whole record
  std::uint64_t dropped_bytes = 0;  // a torn tail after it (a kill mid-append), 0 normally
};

// Reads a partial file of a render of `settings` in tiles of `tile_size`. Errors name the file:
// not a partial file, or one whose key is not `key` ("from another scene or other settings"), or a
// record that does not fit the grid. A record cut short or failing its checksum ends the reading.
util::Result<PartialContents> read_partial(const std::string& path, const std::string& key,
                                           const scene::RenderSettings& settings, std::uint32_t tile_size);

class PartialWriter {
 public:
  // A new file (replacing none: the caller checked) with the header of `key`.
  static util::Result<PartialWriter> create(const std::string& path, const std::string& key);
  // An existing partial, cut to `good_bytes` (read_partial's), appended to from there.
  static util::Result<PartialWriter> reopen(const std::string& path, std::uint64_t good_bytes);

  // Appends a tile's record and flushes it to the kernel (a killed process keeps it; fsync is
  // for sync()). `tile_index` is its index in the grid.
  util::Status append(std::uint32_t tile_index, const render::Tile& tile);
  // fsync: what was appended survives a crash of the machine too.
  util::Status sync();
  const std::string& path() const { return path_; }

 private:
  struct Closer {
    void operator()(std::FILE* f) const { std::fclose(f); }
  };
  PartialWriter(std::string path, std::FILE* f) : path_(std::move(path)), file_(f) {}
  std::string path_;
  std::unique_ptr<std::FILE, Closer> file_;
};

}  // namespace dtraced::cli
