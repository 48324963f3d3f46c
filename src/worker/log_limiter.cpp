#include "worker/log_limiter.h"

#include <algorithm>

#include <fmt/format.h>

namespace dtraced::worker {

std::optional<std::uint64_t> LogLimiter::admit(std::string_view key, util::TimePoint now) {
  if (const auto it = seen_.find(key); it != seen_.end()) {
    Seen& seen = it->second;
    if (now - seen.written < every_) {
      ++seen.held_back;
      return std::nullopt;
    }
    const std::uint64_t held_back = seen.held_back;
    seen = Seen{now, 0};
    return held_back;
  }
  if (seen_.size() >= kMaxLoggedKeys) {
    // A linear scan, but only when a new key arrives with the table full: rare by design.
    seen_.erase(std::min_element(seen_.begin(), seen_.end(),
                                 [](const auto& a, const auto& b) { return a.second.written < b.second.written; }));
  }
  seen_.emplace(std::string(key), Seen{now, 0});
  return 0;
}

std::string held_back_suffix(std::uint64_t held_back, std::chrono::steady_clock::duration every) {
  if (held_back == 0) return {};
  return fmt::format(" ({} more like it since the last such line, at most one line per {} s)", held_back,
                     std::chrono::duration_cast<std::chrono::seconds>(every).count());
}

}  // namespace dtraced::worker
