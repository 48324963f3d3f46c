// dtraced::cli verbs: one function per command, each returning the process exit code. They
// print results to stdout and diagnostics to stderr, and never call exit().
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "accel/isa.h"
#include "scene/overrides.h"

namespace dtraced::cli {

std::string_view version_string();

struct RenderArgs {
  std::string scene;
  std::string output;
  scene::Overrides overrides;  // of the scene's render block, plus tile size and PNG bit depth
  // Where to write the samples each pixel took: .pfm holds the raw counts (R = G = B = n);
  // .png and .ppm a grey picture whose code values are proportional to n / samples (white: all
  // samples). Empty: none.
  std::string spp_map;
  std::uint32_t threads = 0;
  bool quiet = false;
  // Continue the interrupted render whose finished tiles OUTPUT.partial keeps (refused when they
  // are of another scene or other settings). Without it, an OUTPUT.partial that is there is an
  // error, never replaced.
  bool resume = false;
  bool gif_dither = false;               // Floyd-Steinberg dithering of a .gif output's palette
  bool exr_float = false;                // a .exr output in float32 channels instead of half
  accel::Isa isa = accel::Isa::kScalar;  // resolved by main (cli/isa_option.h)
};
int run_render(const RenderArgs& args);

int run_validate(const std::vector<std::string>& files);

struct CompareArgs {
  std::string a, b;
  std::optional<double> max_rmse;
};
int run_compare(const CompareArgs& args);

struct GenerateArgs {
  std::uint32_t count = 100000;
  std::uint64_t seed = 1;
  std::string output;
  // Set: a mesh scene of about this many triangles instead of spheres, its OBJ files written
  // under models_dir (relative to the scene's directory; "" = beside it).
  std::optional<std::uint32_t> mesh_triangles;
  std::string models_dir;
};
int run_generate(const GenerateArgs& args);

}  // namespace dtraced::cli
