// The target that owns the test suite's precompiled Catch2 header (tests/CMakeLists.txt): CMake
// needs a source to build it with; every test program reuses its precompiled copy.
