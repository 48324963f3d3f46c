// dtraced::cli partial renders: the file that keeps a local render's finished tiles when it is
// interrupted (Ctrl-C), so that `render --resume` continues it (as POV-Ray's +C does).
//
// Owns: the partial file's format, its writer and its reader. The file sits next to the output,
// OUT.partial, and is append-only, which is why it is a small binary file and not a database:
//
//   header  "dtraced-partial-v2\n" KEY "\n"        (KEY: partial_key, 64 hex digits)
//   record  "TILE" index:u32 bytes:u32 payload[bytes] crc32c:u32   (repeated; little-endian)
//           payload = the tile's rgb floats (width*height*3), then its spp counts (width*height
//           u32, adaptive renders only); crc32c (Castagnoli) is over index, bytes and payload.
//
// Version 1 files (an earlier dtraced's: "dtraced-partial-v1\n", and a SHA-256 of 32 bytes where
// v2 has its CRC) are still read, and a resume appends to them in version 1. v2's CRC-32C finds
// any error of up to 3 bits and any burst of up to 32 in a record, and misses other damage once in
// 2^32; a torn last record is found by its length either way. It costs about a quarter of SHA-256
// (1.6 against 5.9 ms over the 11 MB of a 1280x720 image here, with SSE4.2): time that the
// calling thread took from the render threads on 2 cores.
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
#include <string>
#include <utility>
#include <vector>

#include "render/tile.h"
#include "scene/description.h"
#include "util/file.h"
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
  std::uint32_t version = 0;        // of the file's format (1 or 2): PartialWriter::reopen appends in it
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
  // An existing partial of format `version` (read_partial's), cut to `good_bytes` (read_partial's),
  // appended to from there in its own format.
  static util::Result<PartialWriter> reopen(const std::string& path, std::uint64_t good_bytes, std::uint32_t version);

  // Appends a tile's record in one write(2) (a killed process keeps it; fsync is for sync()),
  // straight from the tile's vectors (no copy). `tile_index` is its index in the grid.
  util::Status append(std::uint32_t tile_index, const render::Tile& tile);
  // fsync: what was appended survives a crash of the machine too.
  util::Status sync();
  const std::string& path() const { return path_; }

 private:
  PartialWriter(std::string path, int fd, std::uint32_t version)
      : path_(std::move(path)), file_(fd), version_(version) {}
  std::string path_;
  util::FileHandle file_;
  std::uint32_t version_ = 2;
};

}  // namespace dtraced::cli
