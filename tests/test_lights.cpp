// Area lights against closed forms, and the scene-specialised integrator against the generic one.
#include <catch2/catch.hpp>
