// dtraced::store::coalescing_vfs_name: an SQLite VFS over the platform's default one that gathers
// the many small, consecutive writes of a commit and of a checkpoint into few large ones.
//
// SQLite writes every WAL frame as two pwrite calls (its 24-byte header, then its page), and a
// checkpoint copies each page into the database file with a pwrite of its own: for a stream of
// tiles about three system calls a tile, each costing several microseconds of kernel entry and
// file-system bookkeeping on a virtual machine, where the bytes alone would cost little. This VFS
// keeps the writes that follow each other in one file in a buffer (up to 1 MiB) and hands them to
// the kernel as few writes, before anything could look at them:
//   - the WAL file: always; the buffer goes to the file before every other call on it (a read,
//     a sync, a size, a truncation, a lock, a file control, a close). COMMIT syncs the WAL before
//     SQLite publishes its frames in the shared-memory index, so what a commit wrote is in the
//     file, and on disk, when other connections can see it and when COMMIT returns, as without
//     this VFS. That needs synchronous = FULL on a connection that writes through this VFS (the
//     store's): with NORMAL, a commit does not sync, and another connection could find frames in
//     the index that are still in the buffer.
//   - the database file: only while its connection holds the WAL's checkpoint lock (a checkpoint
//     copying pages, in page order); the buffer goes to the file before every other call on it
//     (the checkpoint's sync among them) and at every call on the shared-memory index (its locks,
//     where the checkpoint lock is released, and its memory barriers).
// Other files (journals, temporary files) pass straight through. A write that fails when the
// buffer is flushed fails the call that flushed it (a sync, a read, ...); a flush that has no
// result to fail (a memory barrier) leaves the error for the next call that has one.
//
// Thread safety: the VFS is registered once (thread-safe); each file belongs to its connection,
// which SQLite serialises.
#pragma once

namespace dtraced::store {

// The VFS's name for sqlite3_open_v2, registered on first use (not as the default VFS); nullptr
// (SQLite's default VFS) if it could not be registered.
const char* coalescing_vfs_name();

}  // namespace dtraced::store
