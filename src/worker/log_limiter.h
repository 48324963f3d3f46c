// dtraced::worker log limiter: identical log lines are written once, then at most once per
// interval with how many were held back in between.
//
// Why: a worker that meets the same problem many times a second (a collector refusing every
// tile) once wrote 16,427 lines in 15 s, burying everything else in the journal. A line is
// identified by a key the caller chooses (what stays the same from one occurrence to the next:
// "tile refused, job 7", not the tile number), so lines that differ only in a counter still count
// as one. Occurrences after the last written line are only counted; the next occurrence once the
// interval is over is written with that count. Time comes from the caller (a util::Clock's now()),
// so tests decide when an interval ends.
//
// Memory is bounded: at most kMaxLoggedKeys keys are remembered; past that the key written
// longest ago is forgotten (its next occurrence is written as if new).
//
// Thread safety: none; one owner (the worker's event loop).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <string_view>

#include "util/clock.h"

namespace dtraced::worker {

// The interval between two lines of one key.
inline constexpr std::chrono::seconds kLogRepeatEvery{30};
inline constexpr std::size_t kMaxLoggedKeys = 256;

class LogLimiter {
 public:
  explicit LogLimiter(std::chrono::steady_clock::duration every = kLogRepeatEvery) : every_(every) {}

  // Whether an occurrence of `key` at `now` is to be written: nullopt if not (it is counted),
  // else the number of occurrences held back since the last line of this key.
  std::optional<std::uint64_t> admit(std::string_view key, util::TimePoint now);

 private:
  struct Seen {
    util::TimePoint written;
    std::uint64_t held_back = 0;
  };

  std::chrono::steady_clock::duration every_;
  std::map<std::string, Seen, std::less<>> seen_;
};

// "" for 0, else " (N more like it since the last such line, ...)": the tail of a line
// LogLimiter admitted.
std::string held_back_suffix(std::uint64_t held_back, std::chrono::steady_clock::duration every = kLogRepeatEvery);

}  // namespace dtraced::worker
