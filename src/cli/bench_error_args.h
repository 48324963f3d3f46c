// The flags of `dtraced bench error` (cli/bench_error.h).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "scene/overrides.h"

namespace dtraced::cli {

struct BenchErrorArgs {
  std::string scene;
  std::uint32_t max_spp = 64;                          // uniform rows 1, 2, 4, ... up to this
  std::vector<double> targets{0.1, 0.05, 0.02, 0.01};  // adaptive rows, at max_spp
  bool no_adaptive = false;
  std::uint32_t min_samples = 8;  // adaptive rows' first checkpoint
  // Cut-off rows: uniform renders at max_spp with each of these RenderSettings::branch_cutoff
  // values, against the same reference (rendered at the strictest cut-off).
  std::vector<double> cutoffs{1.0 / 255.0};
  bool no_cutoffs = false;
  // Of the scene's render block and the tile size; samples, error target and min samples are the
  // bench's own (the rows), so they are not among its override flags (kBenchOverrides).
  scene::Overrides overrides;
  std::optional<std::uint32_t> reference_spp;  // default: 16 * max_spp
  std::string cache_dir;                       // default: the scene's directory
  std::string csv;                             // default: <scene stem>-error.csv
  std::string plot;                            // default: <scene stem>-error.svg
  bool no_plot = false;
  std::uint32_t repeats = 3;   // each row's seconds are the median of this many renders
  std::uint32_t spec_spp = 4;  // samples of the specialised-against-generic comparison
  std::uint32_t threads = 0;   // 0: every core
};

}  // namespace dtraced::cli
