// dtraced::collector stop: the graceful end of the daemon.
//
// Owns: the stop sequence (see service.h's "Stop"): STOPPING=1 to systemd; the HTTP server
// stopped gracefully (no new connections; requests in flight finish within shutdown_grace);
// image writes in flight waited for within the same grace, on the collector's clock; the store
// writer drained (everything accepted is committed and answered) and closed; the read connection
// closed; the state directory's lock released; then the loop stops, so run() returns.
//
// Thread safety: on the loop only (Collector::stop posts there).
#pragma once

#include "collector/context.h"

namespace dtraced::collector {

// Begins the stop sequence once; `exit_code` is what run() returns (the first one given wins).
void begin_stop(Context& c, int exit_code);

}  // namespace dtraced::collector
