#include "cli/commands.h"

#include "cli/bench_error.h"
#include "cli/overrides_flags.h"
#include "image/image_io.h"
#include "protocol/messages.h"

namespace dtraced::cli {

namespace {

void add_render(CLI::App& app, LocalCommands& c, std::optional<std::string>& isa_flag) {
  RenderArgs& render = c.render;
  CLI::App* r = app.add_subcommand("render", "Render a scene on this machine to an image file");
  r->add_option("scene", render.scene, "Scene file (JSON)")->required();
  r->add_option("-o,--output", render.output,
                "Output image: " + image::extension_list() +
                    " (by extension); a sequence names its frames with %04d (snow-%04d.png), or is one .gif")
      ->required();
  add_override_flags(*r, render.overrides);
  r->add_option("--spp-map", render.spp_map,
                "Also write the samples each pixel took: .pfm raw counts, .png/.ppm grey (white = --samples)");
  r->add_option("-t,--threads", render.threads, "Render threads (0: every CPU this process may use)")
      ->check(CLI::Range(0u, 1024u));
  r->add_flag("-q,--quiet", render.quiet, "No progress bar and no summary line");
  r->add_flag("--resume", render.resume,
              "Continue the interrupted render kept in OUTPUT.partial (a sequence: skip the frames already written)");
  r->add_flag("--gif-dither", render.gif_dither, "A .gif output: Floyd-Steinberg dithering of each frame's palette");
  r->add_flag("--exr-float", render.exr_float, "A .exr output: float32 channels instead of half");
  r->add_option("--isa", isa_flag, kIsaHelp);
  c.render_cmd = r;
}

void add_generate(CLI::App& app, LocalCommands& c) {
  GenerateArgs& generate = c.generate;
  CLI::App* g = app.add_subcommand("generate", "Write a generated stress scene (many spheres on a plane)");
  CLI::Option* count = g->add_option("-n,--count", generate.count, "Number of spheres")
                           ->check(CLI::Range(1u, 9999999u));  // with the plane, the loader's 10M objects
  g->add_option("--seed", generate.seed, "Generator seed");
  g->add_option("--mesh-triangles", generate.mesh_triangles,
                "Write a mesh scene of about this many triangles (OBJ files beside the scene) instead of spheres")
      ->check(CLI::Range(1u, 20000000u))
      ->excludes(count);
  g->add_option("--models-dir", generate.models_dir,
                "With --mesh-triangles: directory of the OBJ files, relative to the scene's (default: beside it)");
  g->add_option("-o,--output", generate.output, "Output scene file (JSON)")->required();
  c.generate_cmd = g;
}

// --collector, --token-file and --timeout-ms, which every client verb takes.
void add_connection_options(CLI::App* sub, ClientArgs& client) {
  sub->add_option("--collector", client.collector, "Collector base URL")
      ->envname("DTRACED_COLLECTOR")
      ->capture_default_str();
  sub->add_option("--token-file", client.token_file, "File holding the bearer token")->envname("DTRACED_TOKEN_FILE");
  sub->add_option("--ca-file", client.ca_file,
                  "The collector's CA certificate (PEM) for an https:// collector (STATE_DIR/tls/ca.pem on its host)")
      ->envname("DTRACED_CA_FILE");
  sub->add_option("--timeout-ms", client.timeout_ms,
                  "Per-request read/write timeout; also how long a busy collector (503), or for a "
                  "read one that does not answer, is retried with backoff")
      ->check(CLI::Range(100u, 3600000u))
      ->capture_default_str();
}

CLI::App* add_client_subcommand(CLI::App& app, ClientArgs& client, const std::string& name,
                                const std::string& description) {
  CLI::App* sub = app.add_subcommand(name, description);
  add_connection_options(sub, client);
  return sub;
}

}  // namespace

void add_local_commands(CLI::App& app, LocalCommands& c, std::optional<std::string>& isa_flag) {
  add_render(app, c, isa_flag);

  c.validate_cmd = app.add_subcommand("validate", "Check scene files; print OK or every error found");
  c.validate_cmd->add_option("scene", c.validate_files, "Scene files (JSON)")->required();

  CLI::App* compare = app.add_subcommand("compare", "Compare two images: RMSE, PSNR and largest absolute difference");
  compare->add_option("a", c.compare.a, "First image (" + image::extension_list() + ")")->required();
  compare->add_option("b", c.compare.b, "Second image")->required();
  compare->add_option("--max-rmse", c.compare.max_rmse, "Exit 1 when the RMSE is above this");
  c.compare_cmd = compare;

  add_generate(app, c);
  c.bench_error_cmd = add_bench_error_verb(app, c.bench_error, isa_flag);
}

std::optional<int> run_local_command(const LocalCommands& c, accel::Isa isa) {
  if (c.render_cmd->parsed()) {
    RenderArgs render = c.render;
    render.isa = isa;
    return run_render(render);
  }
  if (c.bench_error_cmd->parsed()) return run_bench_error(c.bench_error, isa);
  if (c.validate_cmd->parsed()) return run_validate(c.validate_files);
  if (c.compare_cmd->parsed()) return run_compare(c.compare);
  if (c.generate_cmd->parsed()) return run_generate(c.generate);
  return std::nullopt;
}

void add_client_commands(CLI::App& app, ClientCommands& c) {
  CLI::App* submit =
      add_client_subcommand(app, c.client, "submit", "Submit a render job to a collector; prints the job id");
  submit->add_option("scene", c.submit.scene, "Scene file (JSON)")->required();
  submit->add_option("-o,--output", c.submit.output,
                     "Output file name on the collector (" + image::extension_list() + ")");
  submit->add_option("--priority", c.submit.priority, "Higher runs first")
      ->check(CLI::Range(protocol::kMinPriority, protocol::kMaxPriority));
  add_override_flags(*submit, c.submit.overrides);
  submit->add_flag("!--no-cost-pass", c.submit.cost_pass,
                   "Send no tile cost estimates (a low-resolution pre-pass): the collector leases tiles in row order");
  c.submit_cmd = submit;

  c.list_cmd = add_client_subcommand(app, c.client, "list", "List the collector's jobs");
  c.list_cmd->add_flag("--json", c.list.json, "Machine-readable JSON");
  c.list_cmd
      ->add_option("--state", c.list.state, "Only jobs in this state: queued, rendering, paused, done or cancelled")
      ->check(CLI::IsMember({"queued", "rendering", "paused", "done", "cancelled"}));
  c.list_cmd->add_option("--limit", c.list.limit, "Only the newest N jobs")
      ->check(CLI::Range(std::uint32_t{1}, static_cast<std::uint32_t>(protocol::kMaxListedJobs)));

  CLI::App* status = add_client_subcommand(app, c.client, "status", "Show one job's progress");
  status->add_option("id", c.status.id, "Job id")->required();
  status->add_flag("--json", c.status.json, "Machine-readable JSON");
  status->add_flag("-w,--wait", c.status.wait, "Wait until the job is done (a progress bar on a terminal)");
  status->add_option("--poll-ms", c.status.poll_ms, "Poll interval with --wait")->check(CLI::Range(50u, 60000u));
  status
      ->add_option("--retry-for-s", c.status.retry_for_s,
                   "With --wait: retry an unreachable or restarting collector this long (with backoff)")
      ->check(CLI::Range(0u, 86400u))
      ->capture_default_str();
  c.status_cmd = status;

  c.fetch_cmd = add_client_subcommand(app, c.client, "fetch", "Fetch a job's image (partial while it renders)");
  c.fetch_cmd->add_option("id", c.fetch_id, "Job id")->required();
  c.fetch_cmd->add_option("-o,--output", c.fetch_output, "Image file (" + image::extension_list() + ")")->required();
  c.fetch_cmd->add_option("--frame", c.fetch_frame, "Frame number of a sequence (default: the frame rendering)");

  c.cancel_cmd = add_client_subcommand(app, c.client, "cancel", "Cancel a job");
  c.cancel_cmd->add_option("id", c.cancel_id, "Job id")->required();

  c.priority_cmd = add_client_subcommand(app, c.client, "priority", "Change a job's priority (higher runs first)");
  c.priority_cmd->add_option("id", c.priority_id, "Job id")->required();
  c.priority_cmd->add_option("priority", c.priority_value, "New priority")
      ->required()
      ->check(CLI::Range(protocol::kMinPriority, protocol::kMaxPriority));

  c.requeue_cmd = add_client_subcommand(app, c.client, "requeue",
                                        "Put a cancelled job back in the queue, keeping its stored tiles");
  c.requeue_cmd->add_option("id", c.requeue_id, "Job id")->required();

  c.workers_cmd = add_client_subcommand(app, c.client, "workers", "List the workers the collector has heard from");
  c.workers_cmd->add_flag("--json", c.workers_json, "Machine-readable JSON");

  c.pause_cmd =
      add_client_subcommand(app, c.client, "pause", "Stop handing out a job's tiles (tiles out are still accepted)");
  c.pause_cmd->add_option("id", c.pause_id, "Job id")->required();
  c.resume_cmd = add_client_subcommand(app, c.client, "resume", "Hand out a paused job's tiles again");
  c.resume_cmd->add_option("id", c.resume_id, "Job id")->required();
  c.delete_cmd = add_client_subcommand(app, c.client, "delete",
                                       "Delete a done or cancelled job and its stored tiles (the image file stays)");
  c.delete_cmd->add_option("id", c.delete_id, "Job id")->required();
  c.delete_cmd->add_flag("--delete-image", c.delete_image, "Also delete the job's finished image file");

  c.revoke_cmd = c.workers_cmd->add_subcommand(
      "revoke", "Revoke a worker's credential: its next request fails and its leased tiles go to other workers");
  add_connection_options(c.revoke_cmd, c.client);
  c.revoke_cmd->add_option("name", c.revoke_name, "The worker's name (as `dtraced workers` lists it)")->required();

  c.enroll_code_cmd = add_client_subcommand(app, c.client, "enroll-code",
                                            "Print a one-time join code for a new worker host (dtraced enroll)");
  c.enroll_code_cmd->add_option("--expires", c.enroll_code.expires, "How long the code is good: 90s, 30m, 1h, 7d")
      ->capture_default_str();
  c.enroll_code_cmd->add_option("--name", c.enroll_code.name, "The name the enrolled worker gets");

  CLI::App* enroll = app.add_subcommand(
      "enroll", "Join this host to a collector as a worker: store its credentials for dtraced-worker@INSTANCE");
  enroll->add_option("--collector", c.enroll.collector, "The collector's URL, https://HOST:PORT")->required();
  enroll->add_option("--code", c.enroll.code, "The join code from `dtraced enroll-code` on the collector's side")
      ->required();
  enroll->add_option("--name", c.enroll.name, "The worker name to ask for (default: this host's name)");
  enroll->add_option("--instance", c.enroll.instance, "The systemd instance: dtraced-worker@INSTANCE")
      ->capture_default_str();
  enroll->add_option("--dir", c.enroll.dir, "Where the token, CA and config go (the unit reads /etc/dtraced)")
      ->capture_default_str();
  enroll->add_option("--ca-file", c.enroll.ca_file,
                     "The collector's CA (PEM), for a join code that carries no CA fingerprint");
  enroll->add_flag("--force", c.enroll.force, "Replace this instance's existing enrollment");
  enroll->add_option("--timeout-ms", c.enroll.timeout_ms, "Per-request read/write timeout")
      ->check(CLI::Range(100u, 3600000u));
  c.enroll_cmd = enroll;

  CLI::App* credentials = app.add_subcommand("credentials", "The collector's credentials: add one, list them");
  credentials->require_subcommand(1);
  c.credentials_add_cmd = credentials->add_subcommand("add", "Create a credential and print its token (shown once)");
  add_connection_options(c.credentials_add_cmd, c.client);
  c.credentials_add_cmd->add_option("name", c.credential_add.name, "Its name")->required();
  c.credentials_add_cmd->add_option("--role", c.credential_add.role, "viewer, client or worker")
      ->required()
      ->check(CLI::IsMember({"viewer", "client", "worker"}));
  c.credentials_add_cmd->add_option("-o,--output", c.credential_add.output,
                                    "Write the token to this file (0600) instead of stdout");
  c.credentials_list_cmd = credentials->add_subcommand("list", "List the credentials (names, roles; no tokens)");
  add_connection_options(c.credentials_list_cmd, c.client);
  c.credentials_list_cmd->add_flag("--json", c.credentials_json, "Machine-readable JSON");
}

std::optional<int> run_client_command(const ClientCommands& c) {
  if (c.submit_cmd->parsed()) return run_submit(c.client, c.submit);
  if (c.list_cmd->parsed()) return run_list(c.client, c.list);
  if (c.status_cmd->parsed()) return run_status(c.client, c.status);
  if (c.fetch_cmd->parsed()) return run_fetch(c.client, c.fetch_id, c.fetch_output, c.fetch_frame);
  if (c.cancel_cmd->parsed()) return run_cancel(c.client, c.cancel_id);
  if (c.priority_cmd->parsed()) return run_priority(c.client, c.priority_id, c.priority_value);
  if (c.requeue_cmd->parsed()) return run_requeue(c.client, c.requeue_id);
  if (c.revoke_cmd->parsed()) return run_revoke(c.client, c.revoke_name);
  if (c.workers_cmd->parsed()) return run_workers(c.client, c.workers_json);
  if (c.pause_cmd->parsed()) return run_pause(c.client, c.pause_id, /*pause=*/true);
  if (c.resume_cmd->parsed()) return run_pause(c.client, c.resume_id, /*pause=*/false);
  if (c.delete_cmd->parsed()) return run_delete(c.client, c.delete_id, c.delete_image);
  if (c.enroll_code_cmd->parsed()) return run_enroll_code(c.client, c.enroll_code);
  if (c.enroll_cmd->parsed()) return run_enroll(c.enroll);
  if (c.credentials_add_cmd->parsed()) return run_credentials_add(c.client, c.credential_add);
  if (c.credentials_list_cmd->parsed()) return run_credentials_list(c.client, c.credentials_json);
  return std::nullopt;
}

}  // namespace dtraced::cli
