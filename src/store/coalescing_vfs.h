// dtraced::store::coalescing_vfs_name: an SQLite VFS over the platform's default one that gathers
// the many small, consecutive writes of a commit into the WAL into few large ones.
//
// SQLite writes every WAL frame as two pwrite calls (its 24-byte header, then its page): for a
// stream of tiles two system calls a tile, each costing several microseconds of kernel entry and
// file-system bookkeeping on a virtual machine, where the bytes alone would cost little. This VFS
// keeps the writes that follow each other in the WAL file in a buffer (up to 1 MiB) and hands them
// to the kernel as few writes. The buffer goes to the file before every other call on it (a read,
// a sync, a size, a truncation, a lock, a file control, a close) and at every call on the
// shared-memory index. COMMIT syncs the WAL before SQLite publishes its frames in the
// shared-memory index, so what a commit wrote is in the file, and on disk, when other connections
// can see it and when COMMIT returns, as without this VFS. That needs synchronous = FULL on a
// connection that writes through this VFS (the store's): with NORMAL, a commit does not sync, and
// another connection could find frames in the index that are still in the buffer.
//
// A write that fails when the buffer is flushed fails the call that flushed it, and also the next
// sync whatever call reported it first: SQLite ignores the results of some calls (an unlock, some
// file controls), and a commit must never count bytes that did not reach the file.
//
// The database file and every other file pass straight through. Gathering a checkpoint's page
// copies as well (round 15) lost pages when a write failed: after its copy loop SQLite makes only
// calls whose results it ignores before it records the frames as copied (a file control, and with
// frames still in use by a reader not even a sync), so a failed copy went unnoticed, the WAL was
// later reused, and those pages were gone. The failing-checkpoint test caught it, 1 run in 3.
//
// Thread safety: the VFS is registered once (thread-safe); each file belongs to its connection,
// which SQLite serialises.
#pragma once

namespace dtraced::store {

// The VFS's name for sqlite3_open_v2, registered on first use (not as the default VFS); nullptr
// (SQLite's default VFS) if it could not be registered.
const char* coalescing_vfs_name();

}  // namespace dtraced::store
