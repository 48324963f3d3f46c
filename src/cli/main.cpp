// dtraced command line: parses flags, picks the verb, turns results into exit codes.
//
// Exit codes: 0 success; 1 the work failed (invalid scene, unreadable or mismatching image,
// render or write error); 2 usage error (unknown flag, missing argument, bad value).
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <optional>
#include <string>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "cli/verbs.h"

namespace {

constexpr int kExitUsage = 2;

}  // namespace

int main(int argc, char** argv) {
  using namespace dtraced::cli;
  CLI::App app{"dtraced: a distributed ray tracer. Renders JSON scenes locally or across a farm.", "dtraced"};
  app.set_version_flag("--version", std::string(version_string()));
  app.require_subcommand(1);
  app.fallthrough(false);

  RenderArgs render;
  CLI::App* r = app.add_subcommand("render", "Render a scene on this machine to an image file");
  r->add_option("scene", render.scene, "Scene file (JSON)")->required();
  r->add_option("-o,--output", render.output, "Output image: .png, .ppm or .pfm (by extension)")->required();
  r->add_option("--width", render.width, "Image width in pixels")->check(CLI::Range(1u, 16384u));
  r->add_option("--height", render.height, "Image height in pixels")->check(CLI::Range(1u, 16384u));
  r->add_option("-s,--samples", render.samples, "Samples per pixel")->check(CLI::Range(1u, 65536u));
  r->add_option("--max-depth", render.max_depth, "Maximum reflection/refraction depth")->check(CLI::Range(0u, 64u));
  r->add_option("--seed", render.seed, "Sampling seed")
      ->check(CLI::Range(std::uint64_t{0}, (std::uint64_t{1} << 53) - 1));
  r->add_option("--background", render.background, "Background colour, linear RGB: R,G,B")
      ->delimiter(',')
      ->expected(3)
      ->check(CLI::Validator(
          [](std::string& v) -> std::string {
            double x = 0;
            if (!CLI::detail::lexical_cast(v, x) || !(x >= 0.0 && x <= 3.4e38)) {
              return "each channel must be a finite number >= 0, got " + v;
            }
            return {};
          },
          "R,G,B"));
  r->add_option("--frame", render.frame, "Frame number (part of every sample's random key)");
  r->add_option("-t,--threads", render.threads, "Render threads (0: every core)")->check(CLI::Range(0u, 1024u));
  r->add_option("--tile-size", render.tile_size, "Tile side in pixels")->check(CLI::Range(1u, 4096u));
  r->add_option("--bit-depth", render.bit_depth, "PNG bit depth: 8 or 16")->check(CLI::IsMember({8, 16}));
  r->add_flag("-q,--quiet", render.quiet, "No progress bar and no summary line");

  std::vector<std::string> validate_files;
  CLI::App* v = app.add_subcommand("validate", "Check scene files; print OK or every error found");
  v->add_option("scene", validate_files, "Scene files (JSON)")->required();

  CompareArgs compare;
  CLI::App* c = app.add_subcommand("compare", "Compare two images: RMSE, PSNR and largest absolute difference");
  c->add_option("a", compare.a, "First image (.png, .ppm, .pfm)")->required();
  c->add_option("b", compare.b, "Second image")->required();
  c->add_option("--max-rmse", compare.max_rmse, "Exit 1 when the RMSE is above this");

  GenerateArgs generate;
  CLI::App* g = app.add_subcommand("generate", "Write a generated stress scene (many spheres on a plane)");
  g->add_option("-n,--count", generate.count, "Number of spheres")
      ->check(CLI::Range(1u, 500000u));  // keeps the file under the loader's size limit
  g->add_option("--seed", generate.seed, "Generator seed");
  g->add_option("-o,--output", generate.output, "Output scene file (JSON)")->required();

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitUsage;
  }
  if (r->parsed()) return run_render(render);
  if (v->parsed()) return run_validate(validate_files);
  if (c->parsed()) return run_compare(compare);
  if (g->parsed()) return run_generate(generate);
  return kExitUsage;
}
