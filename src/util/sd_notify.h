// dtraced::util systemd readiness notification.
//
// Sends a state line ("READY=1", "STOPPING=1", "STATUS=...") to the datagram socket named by
// $NOTIFY_SOCKET, as systemd's Type=notify services do. Without $NOTIFY_SOCKET (not under
// systemd) it does nothing and returns true. Stateless: thread-safe.
#pragma once

#include <string_view>

namespace dtraced::util {

bool sd_notify_state(std::string_view state);

}  // namespace dtraced::util
