// dtraced::store pixel files: a job's tile pixels, appended to a file of its own beside the
// database (<state_dir>/pixels/job-<id>.pixels), so that a tile's 12 KB are written once (where the
// WAL and then a checkpoint wrote them twice). The database keeps, for each tile, where its bytes
// lie (offset, length) and their CRC-32C; the table pixel_files keeps each file's committed length.
//
// Order of a group commit (Store::insert_tiles): inside the transaction, the tiles' rows are
// inserted, their bytes appended to each job's file past its committed length with one gathered
// write, the file fdatasync'ed, its new committed length written, then COMMIT. So a row never
// points at bytes that are not on disk, and bytes past a file's committed length (a crash or a
// failed commit between the append and the COMMIT) belong to no row: reads never look at them,
// the next append overwrites them, and the writer truncates them when it first opens the file.
//
// Reads check the length (a truncated file) and the checksum, and report a mismatch as an error
// naming the file, the job and the tile.
//
// Private to the store module. Thread safety: free functions, no shared state.
#pragma once

#include <sys/uio.h>

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "store/store.h"
#include "util/file.h"
#include "util/result.h"

namespace dtraced::store {

inline constexpr std::string_view kPixelDirName = "pixels";

// <pixel_dir>/job-<id>.pixels
std::string pixel_file_path(const std::string& pixel_dir, std::int64_t job);

// Writes every byte of `pieces` at `offset` (pwritev, continued after short writes, at most
// IOV_MAX pieces a call). An error names `path`.
util::Status write_all(int fd, const std::string& path, std::uint64_t offset, std::span<const iovec> pieces);

// Reads `length` bytes at `offset` from `fd` (the file `path`) and checks them against `crc`. A
// short read (a truncated file) or a checksum mismatch is an error naming the file, job and tile.
util::Result<Blob> read_checked(int fd, const std::string& path, std::int64_t job, std::uint32_t tile,
                                std::uint64_t offset, std::uint64_t length, std::uint32_t crc);

// Opens `path` for reading; a missing file is an error naming it.
util::Result<util::FileHandle> open_for_reading(const std::string& path);

}  // namespace dtraced::store
