#include "cli/partial_render.h"

#include <fcntl.h>
#include <sys/uio.h>
#include <unistd.h>

#include <bit>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <memory>
#include <string_view>

#include <fmt/format.h>

#include "scene/digest.h"
#include "scene/tiling.h"
#include "util/crc32c.h"
#include "util/sha256.h"

namespace dtraced::cli {

namespace {

// The records hold the host's floats and integers as they are in memory.
static_assert(std::endian::native == std::endian::little, "the partial file format is little-endian");

constexpr std::string_view kMagic = "dtraced-partial-v2\n";
constexpr std::string_view kMagicV1 = "dtraced-partial-v1\n";  // same length as kMagic
constexpr std::string_view kRecordTag = "TILE";
constexpr std::size_t kKeyChars = 64;

// The checksum's bytes at the end of a record of format `version`.
constexpr std::size_t sum_bytes(std::uint32_t version) { return version == 1 ? util::kSha256Bytes : 4; }

util::Error file_error(const std::string& path, std::string message) {
  return util::Error(std::move(message), "", path);
}

// The bytes a record of `rect` carries.
std::uint64_t payload_bytes(const scene::TileRect& rect, bool adaptive) {
  const std::uint64_t pixels = std::uint64_t{rect.width} * rect.height;
  return pixels * 3 * sizeof(float) + (adaptive ? pixels * sizeof(std::uint32_t) : 0);
}

// The next record of `f` (of format `version`), into `tile`; false at the end of the file or at a
// torn or damaged record (the caller stops there). `error` is set for a whole record that does not
// fit the grid.
bool read_record(std::FILE* f, std::uint32_t version, const scene::TileGrid& grid, bool adaptive, std::uint32_t& index,
                 render::Tile& tile, std::string& error) {
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
  const std::size_t sum_size = sum_bytes(version);
  if (std::fread(body.data() + 8, 1, bytes, f) != bytes || std::fread(sum, 1, sum_size, f) != sum_size) return false;
  if (version == 1) {
    const util::Sha256Digest expected = util::sha256_bytes(body);
    if (std::memcmp(expected.data(), sum, sum_size) != 0) return false;
  } else {
    util::Crc32c crc;
    crc.update(body.data(), body.size());
    const std::uint32_t expected = crc.value();
    if (std::memcmp(&expected, sum, sum_size) != 0) return false;
  }
  const std::size_t pixels = std::size_t{tile.rect.width} * tile.rect.height;
  tile.rgb.resize(pixels * 3);
  std::memcpy(tile.rgb.data(), body.data() + 8, pixels * 3 * sizeof(float));
  if (adaptive) {
    tile.spp.resize(pixels);
    std::memcpy(tile.spp.data(), body.data() + 8 + pixels * 3 * sizeof(float), pixels * sizeof(std::uint32_t));
  }
  return true;
}

// Writes all of `iov` (`count` pieces) to `fd`, going on after a short write or an interrupted
// one. False with errno set on an error.
bool write_all(int fd, iovec* iov, int count) {
  while (count > 0) {
    const ssize_t n = ::writev(fd, iov, count);
    if (n < 0) {
      if (errno == EINTR) continue;
      return false;
    }
    if (n == 0 && iov->iov_len > 0) {  // no progress: give up rather than spin
      errno = EIO;
      return false;
    }
    auto left = static_cast<std::size_t>(n);
    while (count > 0 && left >= iov->iov_len) {
      left -= iov->iov_len;
      ++iov;
      --count;
    }
    if (count > 0) {
      iov->iov_base = static_cast<char*>(iov->iov_base) + left;
      iov->iov_len -= left;
    }
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
  if (std::fread(header.data(), 1, header.size(), f.get()) != header.size() ||
      !(header.starts_with(kMagic) || header.starts_with(kMagicV1)) || header.back() != '\n') {
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
  out.version = header.starts_with(kMagicV1) ? 1 : 2;
  out.good_bytes = header.size();
  std::vector<bool> seen(grid.count(), false);
  std::uint32_t index = 0;
  render::Tile tile;
  std::string error;
  while (read_record(f.get(), out.version, grid, adaptive, index, tile, error)) {
    out.good_bytes += 12 + payload_bytes(tile.rect, adaptive) + sum_bytes(out.version);
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
  // O_EXCL: never replaces a file.
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_APPEND | O_CLOEXEC, 0666);
  if (fd < 0) return file_error(path, fmt::format("cannot create: {}", std::strerror(errno)));
  PartialWriter w(path, fd, 2);
  std::string header = fmt::format("{}{}\n", kMagic, key);
  iovec iov{header.data(), header.size()};
  if (!write_all(fd, &iov, 1)) return file_error(path, fmt::format("cannot write: {}", std::strerror(errno)));
  return w;
}

util::Result<PartialWriter> PartialWriter::reopen(const std::string& path, std::uint64_t good_bytes,
                                                  std::uint32_t version) {
  // A torn record at the end would hide everything appended after it.
  if (::truncate(path.c_str(), static_cast<off_t>(good_bytes)) != 0) {
    return file_error(path, fmt::format("cannot cut its torn end: {}", std::strerror(errno)));
  }
  const int fd = ::open(path.c_str(), O_WRONLY | O_APPEND | O_CLOEXEC);
  if (fd < 0) return file_error(path, fmt::format("cannot open for appending: {}", std::strerror(errno)));
  return PartialWriter(path, fd, version);
}

util::Status PartialWriter::append(std::uint32_t tile_index, const render::Tile& tile) {
  const std::size_t rgb_bytes = tile.rgb.size() * sizeof(float);
  const std::size_t spp_bytes = tile.spp.size() * sizeof(std::uint32_t);
  const auto bytes = static_cast<std::uint32_t>(rgb_bytes + spp_bytes);
  char head[12];
  std::memcpy(head, kRecordTag.data(), 4);
  std::memcpy(head + 4, &tile_index, 4);
  std::memcpy(head + 8, &bytes, 4);
  // The checksum covers index, bytes and payload, hashed where they are.
  unsigned char sum[util::kSha256Bytes];
  if (version_ == 1) {  // an earlier dtraced's file being resumed: the old way, with a copy
    std::string body(head + 4, 8);
    body.append(reinterpret_cast<const char*>(tile.rgb.data()), rgb_bytes);
    body.append(reinterpret_cast<const char*>(tile.spp.data()), spp_bytes);
    const util::Sha256Digest d = util::sha256_bytes(body);
    std::memcpy(sum, d.data(), d.size());
  } else {
    util::Crc32c crc;
    crc.update(head + 4, 8);
    crc.update(tile.rgb.data(), rgb_bytes);
    crc.update(tile.spp.data(), spp_bytes);
    const std::uint32_t c = crc.value();
    std::memcpy(sum, &c, 4);
  }
  // One writev of the pieces: with O_APPEND a record is one write at the file's end, and a kill
  // leaves at most a torn last record (read_partial drops it).
  iovec iov[4] = {{head, sizeof head},
                  {const_cast<float*>(tile.rgb.data()), rgb_bytes},
                  {const_cast<std::uint32_t*>(tile.spp.data()), spp_bytes},
                  {sum, sum_bytes(version_)}};
  if (!write_all(file_.get(), iov, 4)) {
    return file_error(path_, fmt::format("cannot append a tile: {}", std::strerror(errno)));
  }
  return {};
}

util::Status PartialWriter::sync() {
  if (::fsync(file_.get()) != 0) return file_error(path_, fmt::format("cannot flush: {}", std::strerror(errno)));
  return {};
}

}  // namespace dtraced::cli
