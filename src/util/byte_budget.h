// dtraced::util::ByteBudget: a limit on the bytes that callers on several threads hold at once.
//
// A caller asks for a lease of n bytes before it allocates them and holds the lease as long as it
// holds the memory. acquire() waits while other leases are held and the new one would take the
// total past the limit; a lease larger than the whole limit is granted once nothing else is held
// (it could never fit otherwise), so a request never waits forever and the bytes held at once are
// at most max(limit, the largest single lease). The collector bounds the float images it assembles
// from the store with one (CollectorConfig::image_memory_bytes).
//
// Thread safety: every member may be called from any thread; a Lease releases its bytes on any
// thread. Holders must not wait for other leases (nothing here can then deadlock).
#pragma once

#include <algorithm>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <optional>
#include <utility>

namespace dtraced::util {

class ByteBudget {
 public:
  explicit ByteBudget(std::uint64_t limit) : limit_(limit) {}
  ByteBudget(const ByteBudget&) = delete;
  ByteBudget& operator=(const ByteBudget&) = delete;

  // Bytes held from acquire() until destroyed or moved from.
  class Lease {
   public:
    Lease() = default;
    Lease(Lease&& o) noexcept : budget_(std::exchange(o.budget_, nullptr)), bytes_(std::exchange(o.bytes_, 0)) {}
    Lease& operator=(Lease&& o) noexcept {
      if (this != &o) {
        release();
        budget_ = std::exchange(o.budget_, nullptr);
        bytes_ = std::exchange(o.bytes_, 0);
      }
      return *this;
    }
    ~Lease() { release(); }
    std::uint64_t bytes() const { return bytes_; }

   private:
    friend class ByteBudget;
    Lease(ByteBudget* budget, std::uint64_t bytes) : budget_(budget), bytes_(bytes) {}
    void release() {
      if (budget_ != nullptr) budget_->give_back(bytes_);
      budget_ = nullptr;
      bytes_ = 0;
    }
    ByteBudget* budget_ = nullptr;
    std::uint64_t bytes_ = 0;
  };

  // Waits until `bytes` fit (or nothing else is held), then holds them.
  Lease acquire(std::uint64_t bytes) {
    std::unique_lock lock(mu_);
    freed_.wait(lock, [&] { return fits(bytes); });
    held_ += bytes;
    return Lease(this, bytes);
  }

  // The same without waiting: nullopt when `bytes` do not fit now.
  std::optional<Lease> try_acquire(std::uint64_t bytes) {
    std::lock_guard lock(mu_);
    if (!fits(bytes)) return std::nullopt;
    held_ += bytes;
    return Lease(this, bytes);
  }

  std::uint64_t limit() const { return limit_; }
  std::uint64_t held() const {
    std::lock_guard lock(mu_);
    return held_;
  }

 private:
  bool fits(std::uint64_t bytes) const { return held_ == 0 || bytes <= limit_ - std::min(held_, limit_); }
  void give_back(std::uint64_t bytes) {
    {
      std::lock_guard lock(mu_);
      held_ -= bytes;
    }
    freed_.notify_all();
  }

  const std::uint64_t limit_;
  mutable std::mutex mu_;
  std::condition_variable freed_;
  std::uint64_t held_ = 0;  // guarded by mu_
};

}  // namespace dtraced::util
