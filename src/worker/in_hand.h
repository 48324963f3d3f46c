// dtraced::worker bookkeeping: the tiles a worker holds (config.h, max_unacknowledged) and the
// jobs the collector said are gone.
//
// Thread safety: one owner, the worker's event loop, changes both. InHand's counts may also be
// read from any thread (Worker::stats()); GoneJobs has none.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <set>
#include <utility>

#include "async/async.h"

namespace dtraced::worker {

// Jobs remembered as gone (410), so that their other tiles and leases are dropped unsent.
inline constexpr std::size_t kMaxGoneJobs = 1024;

// The tiles in hand (config.h, max_unacknowledged), counted by reservations that release
// themselves when the lease, the tile or the coroutine holding them goes away; and the bytes of
// the rendered tiles among them (config.h, kHeldBytesPerThread), which a reservation holds from
// hold() on. Full at either bound. The event loop changes the counts; other threads may read them.
class InHand {
 public:
  class Reservation {
   public:
    Reservation() = default;
    Reservation(Reservation&& other) noexcept
        : owner_(std::exchange(other.owner_, nullptr)), bytes_(std::exchange(other.bytes_, 0)) {}
    Reservation& operator=(Reservation&& other) noexcept {
      if (this != &other) {
        reset();
        owner_ = std::exchange(other.owner_, nullptr);
        bytes_ = std::exchange(other.bytes_, 0);
      }
      return *this;
    }
    Reservation(const Reservation&) = delete;
    Reservation& operator=(const Reservation&) = delete;
    ~Reservation() { reset(); }

    void reset() {
      if (owner_ != nullptr) std::exchange(owner_, nullptr)->release(std::exchange(bytes_, 0));
    }

    // The tile is rendered: its `bytes` count toward the byte bound until the release.
    void hold(std::uint64_t bytes) {
      if (owner_ == nullptr) return;
      owner_->bytes_.store(owner_->bytes_.load(std::memory_order_relaxed) + bytes, std::memory_order_relaxed);
      bytes_ += bytes;
    }

    // The tile is acknowledged and its place goes to the next lease (the answer to its upload
    // carried one): its bytes no longer count, its place in hand does.
    void unhold() {
      if (owner_ == nullptr) return;
      owner_->bytes_.store(owner_->bytes_.load(std::memory_order_relaxed) - bytes_, std::memory_order_relaxed);
      bytes_ = 0;
      owner_->changed_.notify_all();
    }

   private:
    friend class InHand;
    explicit Reservation(InHand* owner) : owner_(owner) {}
    InHand* owner_ = nullptr;
    std::uint64_t bytes_ = 0;
  };

  // At most `limit` tiles, and no new reservation once the held bytes reach `byte_limit`.
  InHand(const async::Executor& executor, std::uint64_t limit, std::uint64_t byte_limit)
      : limit_(limit), byte_limit_(byte_limit), changed_(executor) {}

  bool full() const {
    return count_.load(std::memory_order_relaxed) >= limit_ || bytes_.load(std::memory_order_relaxed) >= byte_limit_;
  }
  std::uint64_t count() const { return count_.load(std::memory_order_relaxed); }
  std::uint64_t bytes() const { return bytes_.load(std::memory_order_relaxed); }
  std::uint64_t peak() const { return peak_.load(std::memory_order_relaxed); }

  // Notified whenever a reservation is released.
  async::Signal& changed() { return changed_; }

  Reservation reserve() {
    const std::uint64_t n = count_.load(std::memory_order_relaxed) + 1;
    count_.store(n, std::memory_order_relaxed);
    if (n > peak_.load(std::memory_order_relaxed)) peak_.store(n, std::memory_order_relaxed);
    return Reservation(this);
  }

 private:
  void release(std::uint64_t bytes) {
    count_.store(count_.load(std::memory_order_relaxed) - 1, std::memory_order_relaxed);
    bytes_.store(bytes_.load(std::memory_order_relaxed) - bytes, std::memory_order_relaxed);
    changed_.notify_all();
  }

  std::uint64_t limit_;
  std::uint64_t byte_limit_;
  std::atomic<std::uint64_t> count_{0};
  std::atomic<std::uint64_t> bytes_{0};
  std::atomic<std::uint64_t> peak_{0};
  async::Signal changed_;
};

// Jobs the collector said are gone, the most recent kMaxGoneJobs of them.
class GoneJobs {
 public:
  bool contains(std::uint64_t job) const { return jobs_.contains(job); }
  void add(std::uint64_t job) {
    if (!jobs_.insert(job).second) return;
    order_.push_back(job);
    if (order_.size() > kMaxGoneJobs) {
      jobs_.erase(order_.front());
      order_.pop_front();
    }
  }
  void remove(std::uint64_t job) {
    if (jobs_.erase(job) == 0) return;
    order_.erase(std::find(order_.begin(), order_.end(), job));
  }

 private:
  std::set<std::uint64_t> jobs_;
  std::deque<std::uint64_t> order_;
};

}  // namespace dtraced::worker
