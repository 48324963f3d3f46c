#include "store/coalescing_vfs.h"

#include <sqlite3.h>

#include <algorithm>
#include <cstddef>
#include <mutex>
#include <new>
#include <type_traits>
#include <vector>

namespace dtraced::store {
namespace {

// At most this many bytes wait in a file's buffer (the frames of about 60 tiles); a write past it
// flushes the buffer first.
constexpr std::size_t kMaxBufferBytes = std::size_t{1} << 20;
// The default VFS for Unix writes at most 128 KiB - 1 bytes a call (it masks larger counts): the
// buffer goes out in pieces of 31 pages of 4 KiB.
constexpr std::size_t kMaxWriteBytes = 31 * 4096;
enum class Kind { kPassThrough, kWal };

// What SQLite allocates for a file (sqlite3_vfs::szOsFile): this, then the default VFS's file.
struct File {
  sqlite3_file base;  // first: SQLite's view of the file
  sqlite3_file* real = nullptr;
  Kind kind = Kind::kPassThrough;
  int deferred_rc = SQLITE_OK;  // a flush's failure that no call has reported yet
  // A flush's failure that no xWrite or xSync has reported yet: SQLite may ignore the result of
  // the call that reported it (an unlock, a file control), so the next sync fails too, and no
  // commit counts bytes that never reached the file.
  int unsynced_rc = SQLITE_OK;
  sqlite3_int64 start = 0;   // the file offset of buffer[0]
  std::vector<char> buffer;  // consecutive bytes not written yet
};
constexpr int kFileBytes = static_cast<int>((sizeof(File) + 7) / 8 * 8);

// The VFS as SQLite sees it (first member, so SQLite's pointer to it is a pointer to this), the
// default VFS it wraps, and its files' methods for each iVersion of the default VFS's files. Made
// once by coalescing_vfs_name and never changed after: SQLite keeps the pointer for the process.
struct Registration {
  sqlite3_vfs vfs{};
  sqlite3_vfs* base = nullptr;
  sqlite3_io_methods methods[3]{};
};
static_assert(std::is_standard_layout_v<Registration>, "a pointer to its first member is a pointer to it");

File& as_file(sqlite3_file* f) { return *reinterpret_cast<File*>(f); }
const sqlite3_io_methods& real_methods(File& f) { return *f.real->pMethods; }

bool gathers(const File& f) { return f.kind == Kind::kWal; }

// Writes the buffer, in pieces the default VFS takes whole; keeps the first failure in
// deferred_rc.
void write_buffer(File& f) {
  for (std::size_t at = 0; at < f.buffer.size();) {
    const std::size_t n = std::min(kMaxWriteBytes, f.buffer.size() - at);
    const int rc = real_methods(f).xWrite(f.real, f.buffer.data() + at, static_cast<int>(n),
                                          f.start + static_cast<sqlite3_int64>(at));
    if (rc != SQLITE_OK) {
      if (f.deferred_rc == SQLITE_OK) f.deferred_rc = rc;
      if (f.unsynced_rc == SQLITE_OK) f.unsynced_rc = rc;
      break;
    }
    at += n;
  }
  f.buffer.clear();
}

// Writes the buffer; returns its failure, or an earlier one not reported yet (once).
int flush(File& f) {
  write_buffer(f);
  const int rc = f.deferred_rc;
  f.deferred_rc = SQLITE_OK;
  return rc;
}

// The default VFS's `method` on the same file and arguments, once the buffer is in the file; a
// failed flush is the call's result.
template <auto method, typename... Args>
int flushed_then(sqlite3_file* file, Args... args) {
  File& f = as_file(file);
  if (const int rc = flush(f); rc != SQLITE_OK) return rc;
  return (real_methods(f).*method)(f.real, args...);
}

// The same for a call that must happen whatever the flush gave (it releases something): the
// call's failure first, then the flush's.
template <auto method, typename... Args>
int flushing(sqlite3_file* file, Args... args) {
  File& f = as_file(file);
  const int flushed = flush(f);
  const int rc = (real_methods(f).*method)(f.real, args...);
  return rc != SQLITE_OK ? rc : flushed;
}

// The default VFS's `method`, the buffer left as it is (the call neither reads nor writes the
// file's bytes).
template <auto method, typename... Args>
auto passed_on(sqlite3_file* file, Args... args) {
  File& f = as_file(file);
  return (real_methods(f).*method)(f.real, args...);
}

int x_close(sqlite3_file* file) {
  File& f = as_file(file);
  const int flushed = flush(f);
  const int rc = real_methods(f).xClose(f.real);
  f.~File();
  return rc != SQLITE_OK ? rc : flushed;
}

int x_read(sqlite3_file* file, void* out, int amount, sqlite3_int64 offset) {
  return flushed_then<&sqlite3_io_methods::xRead>(file, out, amount, offset);
}

int x_write(sqlite3_file* file, const void* data, int amount, sqlite3_int64 offset) {
  File& f = as_file(file);
  if (!gathers(f)) return flushed_then<&sqlite3_io_methods::xWrite>(file, data, amount, offset);
  const auto bytes = static_cast<std::size_t>(amount);
  const char* p = static_cast<const char*>(data);
  if (!f.buffer.empty() && offset == f.start + static_cast<sqlite3_int64>(f.buffer.size()) &&
      f.buffer.size() + bytes <= kMaxBufferBytes) {
    f.buffer.insert(f.buffer.end(), p, p + bytes);
    return SQLITE_OK;
  }
  // Not where the buffer ends (or no room): what is buffered goes first, so writes reach the file
  // in the order SQLite made them. A failure here is this write's, which SQLite always heeds.
  if (const int rc = flush(f); rc != SQLITE_OK) {
    f.unsynced_rc = SQLITE_OK;
    return rc;
  }
  if (bytes > kMaxWriteBytes) return real_methods(f).xWrite(f.real, data, amount, offset);
  if (f.buffer.capacity() == 0) f.buffer.reserve(kMaxBufferBytes);
  f.start = offset;
  f.buffer.assign(p, p + bytes);
  return SQLITE_OK;
}

int x_truncate(sqlite3_file* file, sqlite3_int64 size) {
  return flushed_then<&sqlite3_io_methods::xTruncate>(file, size);
}

int x_sync(sqlite3_file* file, int flags) {
  File& f = as_file(file);
  const int flushed = flush(f);
  // Any write since the last sync that did not reach the file fails this sync, whichever call
  // reported it first.
  const int lost = f.unsynced_rc;
  f.unsynced_rc = SQLITE_OK;
  if (flushed != SQLITE_OK) return flushed;
  if (lost != SQLITE_OK) return lost;
  return real_methods(f).xSync(f.real, flags);
}

int x_file_size(sqlite3_file* file, sqlite3_int64* size) {
  return flushed_then<&sqlite3_io_methods::xFileSize>(file, size);
}

int x_lock(sqlite3_file* file, int level) { return flushed_then<&sqlite3_io_methods::xLock>(file, level); }

int x_unlock(sqlite3_file* file, int level) { return flushing<&sqlite3_io_methods::xUnlock>(file, level); }

int x_check_reserved_lock(sqlite3_file* file, int* out) {
  return flushed_then<&sqlite3_io_methods::xCheckReservedLock>(file, out);
}

int x_file_control(sqlite3_file* file, int op, void* arg) {
  return flushed_then<&sqlite3_io_methods::xFileControl>(file, op, arg);
}

int x_sector_size(sqlite3_file* file) { return passed_on<&sqlite3_io_methods::xSectorSize>(file); }

int x_device_characteristics(sqlite3_file* file) {
  return passed_on<&sqlite3_io_methods::xDeviceCharacteristics>(file);
}

int x_shm_map(sqlite3_file* file, int page, int page_bytes, int extend, void volatile** out) {
  return flushed_then<&sqlite3_io_methods::xShmMap>(file, page, page_bytes, extend, out);
}

int x_shm_lock(sqlite3_file* file, int offset, int n, int flags) {
  // Whatever the lock tells other connections, the file holds what came before it.
  return flushing<&sqlite3_io_methods::xShmLock>(file, offset, n, flags);
}

void x_shm_barrier(sqlite3_file* file) {
  File& f = as_file(file);
  // No result to fail: a failed write waits in deferred_rc for the next call that has one.
  write_buffer(f);
  real_methods(f).xShmBarrier(f.real);
}

int x_shm_unmap(sqlite3_file* file, int delete_flag) {
  return flushing<&sqlite3_io_methods::xShmUnmap>(file, delete_flag);
}

int x_fetch(sqlite3_file* file, sqlite3_int64 offset, int amount, void** out) {
  return flushed_then<&sqlite3_io_methods::xFetch>(file, offset, amount, out);
}

int x_unfetch(sqlite3_file* file, sqlite3_int64 offset, void* p) {
  return passed_on<&sqlite3_io_methods::xUnfetch>(file, offset, p);
}

int x_open(sqlite3_vfs* self, sqlite3_filename name, sqlite3_file* file, int flags, int* out_flags) {
  File* f = new (file) File{};
  f->real = reinterpret_cast<sqlite3_file*>(reinterpret_cast<char*>(file) + kFileBytes);
  f->real->pMethods = nullptr;
  if ((flags & SQLITE_OPEN_WAL) != 0) f->kind = Kind::kWal;
  Registration& registration = *reinterpret_cast<Registration*>(self);
  sqlite3_vfs* base = registration.base;
  const int rc = base->xOpen(base, name, f->real, flags, out_flags);
  if (f->real->pMethods == nullptr) {
    // Nothing to close: SQLite will not call xClose.
    f->~File();
    file->pMethods = nullptr;
    return rc;
  }
  const int version = std::clamp(f->real->pMethods->iVersion, 1, 3);
  file->pMethods = &registration.methods[version - 1];
  return rc;
}

const char* register_vfs(Registration& r) {
  r.base = sqlite3_vfs_find(nullptr);
  if (r.base == nullptr) return nullptr;
  // One table for each iVersion a default-VFS file may have. SQLite reads the version-2 (shared
  // memory) and version-3 (memory-mapped) entries only from a table that declares them.
  const sqlite3_io_methods all{.iVersion = 3,
                               .xClose = x_close,
                               .xRead = x_read,
                               .xWrite = x_write,
                               .xTruncate = x_truncate,
                               .xSync = x_sync,
                               .xFileSize = x_file_size,
                               .xLock = x_lock,
                               .xUnlock = x_unlock,
                               .xCheckReservedLock = x_check_reserved_lock,
                               .xFileControl = x_file_control,
                               .xSectorSize = x_sector_size,
                               .xDeviceCharacteristics = x_device_characteristics,
                               .xShmMap = x_shm_map,
                               .xShmLock = x_shm_lock,
                               .xShmBarrier = x_shm_barrier,
                               .xShmUnmap = x_shm_unmap,
                               .xFetch = x_fetch,
                               .xUnfetch = x_unfetch};
  for (int v = 1; v <= 3; ++v) {
    r.methods[v - 1] = all;
    r.methods[v - 1].iVersion = v;
  }
  // Everything but opening a file is the default VFS's own (its other calls ignore the VFS they
  // are given beyond what this copy holds).
  r.vfs = *r.base;
  r.vfs.zName = "dtraced-coalesce";
  r.vfs.szOsFile = kFileBytes + r.base->szOsFile;
  r.vfs.pNext = nullptr;
  r.vfs.xOpen = x_open;
  if (sqlite3_vfs_register(&r.vfs, 0) != SQLITE_OK) return nullptr;
  return r.vfs.zName;
}

}  // namespace

const char* coalescing_vfs_name() {
  // Static storage because SQLite keeps a pointer to the VFS; written once, under the guard of
  // the function-local static's initialisation, and only read after.
  static Registration registration;
  static const char* const name = register_vfs(registration);
  return name;
}

}  // namespace dtraced::store
