// dtraced command line: parses flags, picks the verb, turns results into exit codes.
//
// Exit codes: 0 success; 1 the work failed (invalid scene, unreadable or mismatching image,
// render or write error); 2 usage error (unknown flag, missing argument, bad value).
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <string>

#include <CLI/CLI.hpp>
#include <fmt/format.h>

#include "cli/bench_error.h"
#include "cli/bench_error_args.h"
#include "cli/client_verbs.h"
#include "cli/isa_option.h"
#include "cli/json_config.h"
#include "cli/overrides_flags.h"
#include "cli/roles.h"
#include "cli/verbs.h"
#include "image/image_io.h"
#include "protocol/messages.h"

namespace {

constexpr int kExitUsage = 2;

// The file named by --config, for error messages ("" when none): CLI11 hands the formatter only
// a stream.
std::string config_file_argument(int argc, char** argv) {
  for (int i = 1; i < argc; ++i) {
    const std::string_view a = argv[i];
    if (a == "--config" && i + 1 < argc) return argv[i + 1];
    if (a.starts_with("--config=")) return std::string(a.substr(9));
  }
  return "config";
}

}  // namespace

int main(int argc, char** argv) {
  using namespace dtraced::cli;
  CLI::App app{"dtraced: a distributed ray tracer. Renders JSON scenes locally or across a farm.", "dtraced"};
  // The environment is read here, at the edge, and handed down as values.
  const char* isa_env = std::getenv("DTRACED_ISA");
  app.set_version_flag("--version", version_line(version_string(), isa_env));
  app.require_subcommand(0, 1);

  RoleArgs role;
  add_role_options(app, role);
  // --config FILE: a JSON object of long flag names in snake_case; flags on the command line win.
  add_config_option(app, config_file_argument(argc, argv));
  app.fallthrough(false);

  RenderArgs render;
  CLI::App* r = app.add_subcommand("render", "Render a scene on this machine to an image file");
  r->add_option("scene", render.scene, "Scene file (JSON)")->required();
  r->add_option("-o,--output", render.output, "Output image: " + dtraced::image::extension_list() + " (by extension)")
      ->required();
  add_override_flags(*r, render.overrides);
  r->add_option("--spp-map", render.spp_map,
                "Also write the samples each pixel took: .pfm raw counts, .png/.ppm grey (white = --samples)");
  r->add_option("-t,--threads", render.threads, "Render threads (0: every core)")->check(CLI::Range(0u, 1024u));
  r->add_flag("-q,--quiet", render.quiet, "No progress bar and no summary line");
  r->add_option("--isa", role.isa, kIsaHelp);

  std::vector<std::string> validate_files;
  CLI::App* v = app.add_subcommand("validate", "Check scene files; print OK or every error found");
  v->add_option("scene", validate_files, "Scene files (JSON)")->required();

  CompareArgs compare;
  CLI::App* c = app.add_subcommand("compare", "Compare two images: RMSE, PSNR and largest absolute difference");
  c->add_option("a", compare.a, "First image (" + dtraced::image::extension_list() + ")")->required();
  c->add_option("b", compare.b, "Second image")->required();
  c->add_option("--max-rmse", compare.max_rmse, "Exit 1 when the RMSE is above this");

  GenerateArgs generate;
  CLI::App* g = app.add_subcommand("generate", "Write a generated stress scene (many spheres on a plane)");
  CLI::Option* count = g->add_option("-n,--count", generate.count, "Number of spheres")
                           ->check(CLI::Range(1u, 500000u));  // keeps the file under the loader's size limit
  g->add_option("--seed", generate.seed, "Generator seed");
  g->add_option("--mesh-triangles", generate.mesh_triangles,
                "Write a mesh scene of about this many triangles (OBJ files beside the scene) instead of spheres")
      ->check(CLI::Range(1u, 20000000u))
      ->excludes(count);
  g->add_option("--models-dir", generate.models_dir,
                "With --mesh-triangles: directory of the OBJ files, relative to the scene's (default: beside it)");
  g->add_option("-o,--output", generate.output, "Output scene file (JSON)")->required();

  BenchErrorArgs bench_error;
  CLI::App* sub_bench_error = add_bench_error_verb(app, bench_error, role.isa);

  // Client verbs: they talk to a collector.
  ClientArgs client;
  auto add_client_options = [&client](CLI::App* sub) {
    sub->add_option("--collector", client.collector, "Collector base URL")
        ->envname("DTRACED_COLLECTOR")
        ->capture_default_str();
    sub->add_option("--token-file", client.token_file, "File holding the bearer token")->envname("DTRACED_TOKEN_FILE");
    sub->add_option("--timeout-ms", client.timeout_ms, "Per-request read/write timeout")
        ->check(CLI::Range(100u, 3600000u))
        ->capture_default_str();
  };

  SubmitArgs submit;
  CLI::App* sub_submit = app.add_subcommand("submit", "Submit a render job to a collector; prints the job id");
  add_client_options(sub_submit);
  sub_submit->add_option("scene", submit.scene, "Scene file (JSON)")->required();
  sub_submit->add_option("-o,--output", submit.output,
                         "Output file name on the collector (" + dtraced::image::extension_list() + ")");
  sub_submit->add_option("--priority", submit.priority, "Higher runs first")
      ->check(CLI::Range(dtraced::protocol::kMinPriority, dtraced::protocol::kMaxPriority));
  add_override_flags(*sub_submit, submit.overrides);

  bool list_json = false;
  CLI::App* sub_list = app.add_subcommand("list", "List the collector's jobs");
  add_client_options(sub_list);
  sub_list->add_flag("--json", list_json, "Machine-readable JSON");

  StatusArgs status;
  CLI::App* sub_status = app.add_subcommand("status", "Show one job's progress");
  add_client_options(sub_status);
  sub_status->add_option("id", status.id, "Job id")->required();
  sub_status->add_flag("--json", status.json, "Machine-readable JSON");
  sub_status->add_flag("-w,--wait", status.wait, "Wait until the job is done (a progress bar on a terminal)");
  sub_status->add_option("--poll-ms", status.poll_ms, "Poll interval with --wait")->check(CLI::Range(50u, 60000u));

  std::uint64_t fetch_id = 0;
  std::string fetch_out;
  CLI::App* sub_fetch = app.add_subcommand("fetch", "Fetch a job's image (partial while it renders)");
  add_client_options(sub_fetch);
  sub_fetch->add_option("id", fetch_id, "Job id")->required();
  sub_fetch->add_option("-o,--output", fetch_out, "Image file (" + dtraced::image::extension_list() + ")")->required();

  std::uint64_t cancel_id = 0;
  CLI::App* sub_cancel = app.add_subcommand("cancel", "Cancel a job");
  add_client_options(sub_cancel);
  sub_cancel->add_option("id", cancel_id, "Job id")->required();

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitUsage;
  }
  // The kernels, for the two commands that render: --isa, else $DTRACED_ISA, else the best.
  if (r->parsed() || sub_bench_error->parsed() || role.role == "worker") {
    std::string error;
    const std::optional<dtraced::accel::Isa> isa = choose_isa(role.isa, isa_env, error);
    if (!isa) {
      fmt::print(stderr, "{}\n", error);
      return kExitUsage;
    }
    role.kernels = render.isa = *isa;
  }
  if (!role.role.empty()) {
    if (app.get_subcommands().size() > 0) {
      fmt::print(stderr, "--role runs a daemon; it does not combine with the verb {}\n",
                 app.get_subcommands()[0]->get_name());
      return kExitUsage;
    }
    return run_role(app, role);
  }
  if (app.get_subcommands().empty()) {
    fmt::print(stderr, "dtraced: give a verb (render, validate, submit, ...) or --role collector|worker; see --help\n");
    return kExitUsage;
  }
  if (r->parsed()) return run_render(render);
  if (sub_bench_error->parsed()) return run_bench_error(bench_error, render.isa);
  if (v->parsed()) return run_validate(validate_files);
  if (c->parsed()) return run_compare(compare);
  if (g->parsed()) return run_generate(generate);
  if (sub_submit->parsed()) return run_submit(client, submit);
  if (sub_list->parsed()) return run_list(client, list_json);
  if (sub_status->parsed()) return run_status(client, status);
  if (sub_fetch->parsed()) return run_fetch(client, fetch_id, fetch_out);
  if (sub_cancel->parsed()) return run_cancel(client, cancel_id);
  return kExitUsage;
}
