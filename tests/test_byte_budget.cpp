// util::ByteBudget: leases up to the limit, a wait for bytes that do not fit until a lease goes,
// a lease larger than the limit granted alone, and leases that move without releasing twice.
#include <atomic>
#include <cstdint>
#include <optional>
#include <thread>
#include <utility>

#include <catch2/catch.hpp>

#include "util/byte_budget.h"

using dtraced::util::ByteBudget;

TEST_CASE("byte budget: leases fit up to the limit and give their bytes back", "[util][budget]") {
  ByteBudget budget(100);
  std::optional<ByteBudget::Lease> a = budget.try_acquire(60);
  REQUIRE(a);
  CHECK(budget.held() == 60);
  CHECK_FALSE(budget.try_acquire(41));
  std::optional<ByteBudget::Lease> b = budget.try_acquire(40);
  REQUIRE(b);
  CHECK(budget.held() == 100);
  CHECK_FALSE(budget.try_acquire(1));
  b.reset();
  CHECK(budget.held() == 60);
  a.reset();
  CHECK(budget.held() == 0);
}

TEST_CASE("byte budget: a lease larger than the limit goes alone, and nothing joins it", "[util][budget]") {
  ByteBudget budget(100);
  {
    std::optional<ByteBudget::Lease> small = budget.try_acquire(1);
    REQUIRE(small);
    CHECK_FALSE(budget.try_acquire(500));  // not while anything else is held
  }
  std::optional<ByteBudget::Lease> big = budget.try_acquire(500);
  REQUIRE(big);
  CHECK(budget.held() == 500);
  CHECK_FALSE(budget.try_acquire(1));
  big.reset();
  CHECK(budget.held() == 0);
}

TEST_CASE("byte budget: a moved lease releases once", "[util][budget]") {
  ByteBudget budget(100);
  ByteBudget::Lease a = budget.acquire(70);
  ByteBudget::Lease b = std::move(a);
  CHECK(a.bytes() == 0);
  CHECK(b.bytes() == 70);
  CHECK(budget.held() == 70);
  ByteBudget::Lease c = budget.acquire(30);
  c = std::move(b);  // c's 30 go back, b's 70 move into c
  CHECK(budget.held() == 70);
  { ByteBudget::Lease gone = std::move(c); }
  CHECK(budget.held() == 0);
}

TEST_CASE("byte budget: acquire waits for bytes until a lease goes", "[util][budget]") {
  ByteBudget budget(100);
  ByteBudget::Lease first = budget.acquire(60);
  std::atomic<std::uint64_t> held_when_granted{0};
  std::thread waiter([&] {
    ByteBudget::Lease mine = budget.acquire(50);  // 110 > 100: only once `first` goes
    held_when_granted = budget.held();
  });
  first = ByteBudget::Lease();  // gives the 60 back
  waiter.join();
  // Granted after the 60 went back: never 110 at once (had acquire not waited, the thread would
  // most likely have read 110).
  CHECK(held_when_granted == 50);
  CHECK(budget.held() == 0);
}
