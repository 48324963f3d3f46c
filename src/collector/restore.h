// dtraced::collector start-up and restore: from a state directory to a loop ready to serve.
//
// Owns: open_collector (see service.h's "Lifecycle"): the state directory locked (an exclusive
// flock on <state_dir>/collector.lock, holding the PID of its holder, taken before the database
// opens; a second collector on the directory is refused with a message naming the directory and
// that PID), the database opened (a bad one stops start-up with a message and is left as it was),
// the start counter ("epoch", in <state_dir>/collector.epoch) incremented, every stored job
// restored (an unfinished one with its scene and its stored tiles, counted and put in the
// queue as already done, so they are never leased again; a complete one whose image was not
// written gets it written), the one-shot job found by its key and resumed, or stored and
// enqueued; and, after start-up, the finished adaptive jobs' sample counts read back off the loop.
//
// Thread safety: open_collector runs before the loop does, on the thread that will run it.
#pragma once

#include <string_view>

#include "collector/context.h"
#include "util/result.h"

namespace dtraced::collector {

// In the state directory: locked by the running collector (util/lock_file.h). Never deleted: the
// lock, not the file, says whether a collector runs.
inline constexpr std::string_view kLockFileName = "collector.lock";

// Start-up, blocking. The error is a message for the operator.
util::Status open_collector(Context& c);

}  // namespace dtraced::collector
