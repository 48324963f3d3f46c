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

// The end of an exit_when_done one-shot collector's job (done: 0, cancelled: 1): lingers
// (linger.h) while lease requests are answered "finished", then begins the stop with
// `exit_code`. With no recent worker to tell, the stop begins at once.
void begin_linger(Context& c, int exit_code);

// While lingering: `id` was answered "finished"; the stop begins once every worker was told.
void linger_told(Context& c, const WorkerId& id);

}  // namespace dtraced::collector
