// Adaptive sampling: deterministic across tilings, threads and packets; stops where it should.
#include <catch2/catch.hpp>
