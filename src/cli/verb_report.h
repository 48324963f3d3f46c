// dtraced::cli verb reporting: the exit codes and stderr lines the local verbs (render,
// validate, compare, generate) share, so a problem reads the same from each.
//
// Stateless inline functions: call from main's thread (they print).
#pragma once

#include <cstdio>

#include <fmt/format.h>

#include "scene/load.h"
#include "util/result.h"

namespace dtraced::cli::report {

inline constexpr int kExitOk = 0;
inline constexpr int kExitFailed = 1;
inline constexpr int kExitUsage = 2;

// Whether `r` holds a value; prints its error on stderr when it does not.
template <typename R>
bool reported(const R& r) {
  if (!r) fmt::print(stderr, "{}\n", r.error().to_string());
  return r.ok();
}

inline void print_errors(const scene::LoadResult& r) {
  for (const util::Error& e : r.errors) fmt::print(stderr, "{}\n", e.to_string());
}

// What a loaded scene has that is legal but likely a mistake (no lights, an empty mesh): the
// same lines from validate and render, so a render never hides what validate would say.
inline void print_warnings(const scene::LoadResult& r) {
  for (const util::Error& w : r.warnings) fmt::print(stderr, "warning: {}\n", w.to_string());
}

}  // namespace dtraced::cli::report
