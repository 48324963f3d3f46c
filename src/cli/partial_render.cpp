#include "cli/partial_render.h"

#include <unistd.h>

#include <bit>
#include <cerrno>
#include <cstring>
#include <string_view>

#include <fmt/format.h>

#include "scene/digest.h"
#include "scene/tiling.h"
#include "util/sha256.h"

namespace dtraced::cli {

namespace {

// The records hold the host's floats and integers as they are in memory.
static_assert(std::endian::native == std::endian::little, "the partial file format is little-endian");

constexpr std::string_view kMagic = "dtraced-partial-v1\n";
constexpr std::string_view kRecordTag = "TILE";
constexpr std::size_t kKeyChars = 64;

template <typename T>
void put(std::string& out, const T& value) {
  out.append(reinterpret_cast<const char*>(&value), sizeof value);
}

util::Error file_error(const std::string& path, std::string message) {
  return util::Error(std::move(message), "", path);
}

// The bytes a record of `rect` carries.
std::uint64_t payload_bytes(const scene::TileRect& rect, bool adaptive) {
  const std::uint64_t pixels = std::uint64_t{rect.width} * rect.height;
  return pixels * 3 * sizeof(float) + (adaptive ? pixels * sizeof(std::uint32_t) : 0);
}

// The next record of `f`, into `tile`; false at the end of the file or at a torn or damaged
// record (the caller stops there). `error` is set for a whole record that does not fit the grid.
bool read_record(std::FILE* f, const scene::TileGrid& grid, bool adaptive, std::uint32_t& index, render::Tile& tile,
                 std::string& error) {
  char head[12];
  if (std::fread(head, 1, sizeof head, f) != sizeof head || std::string_view(head, 4) != kRecordTag) return false;
  std::uint32_t bytes = 0;
  std::memcpy(&index, head + 4, 4);
  std::memcpy(&bytes, head + 8, 4);
  if (index >= grid.count()) {
    error = fmt::format("tile {} is past the render's {} tiles", index, grid.count());
    return false;
  }
  tile = {};
  tile.rect = grid.rect(index);
  if (bytes != payload_bytes(tile.rect, adaptive)) {
    error = fmt::format("tile {} holds {} bytes, not the {} of its rectangle", index, bytes,
                        payload_bytes(tile.rect, adaptive));
    return false;
  }
  std::string body(head + 4, 8);
  body.resize(8 + bytes);
  unsigned char sum[util::kSha256Bytes];
  if (std::fread(body.data() + 8, 1, bytes, f) != bytes || std::fread(sum, 1, sizeof sum, f) != sizeof sum)
    return false;
  const util::Sha256Digest expected = util::sha256_bytes(body);
  if (std::memcmp(expected.data(), sum, sizeof sum) != 0) return false;
  const std::size_t pixels = std::size_t{tile.rect.width} * tile.rect.height;
  tile.rgb.resize(pixels * 3);
  std::memcpy(tile.rgb.data(), body.data() + 8, pixels * 3 * sizeof(float));
  if (adaptive) {
    tile.spp.resize(pixels);
    std::memcpy(tile.spp.data(), body.data() + 8 + pixels * 3 * sizeof(float), pixels * sizeof(std::uint32_t));
  }
  return true;
}

}  // namespace

std::string partial_key(const scene::SceneDesc& desc, std::uint32_t tile_size) {
  return util::sha256_hex(fmt::format("{}\ntile_size {}", scene::scene_digest(desc), tile_size));
}

std::string partial_path(const std::string& output) { return output + ".partial"; }

util::Result<PartialContents> read_partial(const std::string& path, const std::string& key,
                                           const scene::RenderSettings& settings, std::uint32_t tile_size) {
  std::unique_ptr<std::FILE, int (*)(std::FILE*)> f(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (!f) return file_error(path, fmt::format("cannot open: {}", std::strerror(errno)));
  std::string header(kMagic.size() + kKeyChars + 1, '\0');
  if (std::fread(header.data(), 1, header.size(), f.get()) != header.size() || !header.starts_with(kMagic) ||
      header.back() != '\n') {
    return file_error(path, "not a dtraced partial render file");
  }
  if (std::string_view(header).substr(kMagic.size(), kKeyChars) != key) {
    return file_error(path,
                      "is a partial render of another scene or other settings (scene, render flags or tile size "
                      "differ): not resumed; delete it, or render with the same scene and flags");
  }
  const scene::TileGrid grid(settings, tile_size);
  const bool adaptive = settings.error_target > 0;
  PartialContents out;
  out.good_bytes = header.size();
  std::vector<bool> seen(grid.count(), false);
  std::uint32_t index = 0;
  render::Tile tile;
  std::string error;
  while (read_record(f.get(), grid, adaptive, index, tile, error)) {
    out.good_bytes += 12 + payload_bytes(tile.rect, adaptive) + util::kSha256Bytes;
    if (seen[index]) continue;  // the same bits again (tiles are deterministic): harmless
    seen[index] = true;
    out.tiles.push_back(std::move(tile));
  }
  if (!error.empty()) return file_error(path, error);
  if (std::fseek(f.get(), 0, SEEK_END) == 0) {
    const long end = std::ftell(f.get());
    if (end > 0 && static_cast<std::uint64_t>(end) > out.good_bytes) out.dropped_bytes = end - out.good_bytes;
  }
  return out;
}

util::Result<PartialWriter> PartialWriter::create(const std::string& path, const std::string& key) {
  std::FILE* f = std::fopen(path.c_str(), "wbx");  // x: never replaces a file
  if (f == nullptr) return file_error(path, fmt::format("cannot create: {}", std::strerror(errno)));
  PartialWriter w(path, f);
  const std::string header = fmt::format("{}{}\n", kMagic, key);
  if (std::fwrite(header.data(), 1, header.size(), f) != header.size() || std::fflush(f) != 0) {
    return file_error(path, fmt::format("cannot write: {}", std::strerror(errno)));
  }
  return w;
}

util::Result<PartialWriter> PartialWriter::reopen(const std::string& path, std::uint64_t good_bytes) {
  // A torn record at the end would hide everything appended after it.
  if (::truncate(path.c_str(), static_cast<off_t>(good_bytes)) != 0) {
    return file_error(path, fmt::format("cannot cut its torn end: {}", std::strerror(errno)));
  }
  std::FILE* f = std::fopen(path.c_str(), "ab");
  if (f == nullptr) return file_error(path, fmt::format("cannot open for appending: {}", std::strerror(errno)));
  return PartialWriter(path, f);
}

util::Status PartialWriter::append(std::uint32_t tile_index, const render::Tile& tile) {
  const std::uint64_t bytes = (tile.rgb.size() * sizeof(float)) + (tile.spp.size() * sizeof(std::uint32_t));
  std::string record(kRecordTag);
  record.reserve(12 + bytes + util::kSha256Bytes);
  put(record, tile_index);
  put(record, static_cast<std::uint32_t>(bytes));
  record.append(reinterpret_cast<const char*>(tile.rgb.data()), tile.rgb.size() * sizeof(float));
  record.append(reinterpret_cast<const char*>(tile.spp.data()), tile.spp.size() * sizeof(std::uint32_t));
  const util::Sha256Digest sum = util::sha256_bytes(std::string_view(record).substr(kRecordTag.size()));
  record.append(reinterpret_cast<const char*>(sum.data()), sum.size());
  if (std::fwrite(record.data(), 1, record.size(), file_.get()) != record.size() || std::fflush(file_.get()) != 0) {
    return file_error(path_, fmt::format("cannot append a tile: {}", std::strerror(errno)));
  }
  return {};
}

util::Status PartialWriter::sync() {
  if (std::fflush(file_.get()) != 0 || ::fsync(::fileno(file_.get())) != 0) {
    return file_error(path_, fmt::format("cannot flush: {}", std::strerror(errno)));
  }
  return {};
}

}  // namespace dtraced::cli
