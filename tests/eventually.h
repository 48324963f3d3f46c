// Polls a condition until it holds or a bound of real time passes: for state that another thread
// changes and that shows only through a counter or a status. The bound only turns a hang into a
// failure; nothing asserts how long anything took.
#pragma once

#include <chrono>
#include <functional>
#include <thread>

namespace dtraced::testing {

inline bool eventually(const std::function<bool()>& condition,
                       std::chrono::milliseconds bound = std::chrono::seconds(20)) {
  const auto deadline = std::chrono::steady_clock::now() + bound;
  while (!condition()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  return true;
}

}  // namespace dtraced::testing
