#include "cli/verbs.h"

#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <optional>
#include <system_error>
#include <thread>

#include <fmt/format.h>

#include "cli/verb_report.h"
#include "image/image_io.h"
#include "image/metrics.h"
#include "jsonio/parse.h"
#include "jsonio/write.h"
#include "render/local_render.h"
#include "render/render_scene.h"
#include "scene/digest.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "scene/tiling.h"
#include "util/file.h"

namespace dtraced::cli {

namespace {

using report::kExitFailed;
using report::kExitOk;
using report::print_errors;
using report::print_warnings;
using report::reported;

}  // namespace

std::string_view version_string() { return DTRACED_VERSION; }

int run_validate(const std::vector<std::string>& files) {
  int code = kExitOk;
  for (const std::string& f : files) {
    const scene::LoadResult r = scene::load_scene_file(f);
    if (r.ok()) {
      print_warnings(r);
      // Meshes add their triangle counts; degenerate (zero-area) triangles are legal but never
      // seen, so a count is worth a look.
      std::size_t meshes = 0, triangles = 0, degenerate = 0;
      for (const scene::Object& o : r.scene->objects) {
        if (o.type != scene::ObjectType::kMesh) continue;
        ++meshes;
        triangles += o.mesh->triangle_count();
        degenerate += o.mesh->degenerate_triangles;
      }
      const std::string mesh_note =
          meshes == 0 ? std::string()
                      : fmt::format(", {} mesh{} of {} triangles, {} degenerate triangle{}", meshes,
                                    meshes == 1 ? "" : "es", triangles, degenerate, degenerate == 1 ? "" : "s");
      fmt::print("{}: OK ({} objects, {} lights{}, digest {})\n", f, r.scene->objects.size(), r.scene->lights.size(),
                 mesh_note, scene::scene_digest(*r.scene));
    } else {
      print_errors(r);
      fmt::print("{}: {} error{}\n", f, r.errors.size(), r.errors.size() == 1 ? "" : "s");
      code = kExitFailed;
    }
  }
  return code;
}

int run_compare(const CompareArgs& args) {
  const auto a = image::read_image(args.a);
  if (!reported(a)) return kExitFailed;
  const auto b = image::read_image(args.b);
  if (!reported(b)) return kExitFailed;
  const auto diff = image::compare_images(*a, *b);
  if (!reported(diff)) return kExitFailed;
  const std::string psnr = std::isinf(diff->psnr_db) ? "inf" : fmt::format("{:.2f}", diff->psnr_db);
  fmt::print("rmse {:.6g}  psnr {} dB  max_abs {:.6g}  ({}x{})\n", diff->rmse, psnr, diff->max_abs, a->width,
             a->height);
  if (args.max_rmse && !(diff->rmse <= *args.max_rmse)) {
    fmt::print(stderr, "rmse {:.6g} is above --max-rmse {:.6g}\n", diff->rmse, *args.max_rmse);
    return kExitFailed;
  }
  return kExitOk;
}

namespace {

// The mesh scene: its OBJ files first (so the scene never names a file that is not there yet),
// then the scene, then a load of what was written, for the digest and as a check.
int generate_mesh(const GenerateArgs& args) {
  const std::filesystem::path output(args.output);
  const std::filesystem::path dir = output.parent_path();
  const std::filesystem::path prefix = std::filesystem::path(args.models_dir) / output.stem();
  const scene::GeneratedMeshScene generated =
      scene::generate_mesh_scene(*args.mesh_triangles, args.seed, prefix.generic_string());
  for (const scene::GeneratedFile& obj : generated.objs) {
    const std::filesystem::path path = dir / obj.path;
    std::error_code ec;
    std::filesystem::create_directories(path.parent_path().empty() ? "." : path.parent_path(), ec);
    if (ec) {
      fmt::print(stderr, "{}: cannot create the directory: {}\n", path.parent_path().string(), ec.message());
      return kExitFailed;
    }
    if (!reported(util::write_file_atomic(path.string(), obj.text))) return kExitFailed;
  }
  if (!reported(util::write_file_atomic(args.output, generated.scene_json))) return kExitFailed;
  const scene::LoadResult loaded = scene::load_scene_file(args.output);
  if (!loaded.ok()) {  // a bug in the generator, not a user error; say so loudly
    print_errors(loaded);
    return kExitFailed;
  }
  fmt::print(stderr, "wrote {} and {} OBJ files ({} objects, {} triangles, digest {})\n", args.output,
             generated.objs.size(), loaded.scene->objects.size(), generated.triangles,
             scene::scene_digest(*loaded.scene));
  return kExitOk;
}

// The canonical text with plain decimals (2.2, not Boost's 2.2E0) for people to read: the same
// doubles (both forms are shortest round-trip), so the same scene and digest.
std::string readable_json(const std::string& canonical) {
  // A large scene is written as it is: re-reading it into a tree would cost ~1 GB per 1M objects.
  if (canonical.size() > (std::size_t(64) << 20)) return canonical + "\n";
  jsonio::Document doc = jsonio::parse_strict(canonical, scene::kMaxJsonDepth, 1);
  return doc.parsed ? jsonio::to_text(doc.value) + "\n" : canonical;
}

}  // namespace

int run_generate(const GenerateArgs& args) {
  if (args.mesh_triangles) return generate_mesh(args);
  const scene::SceneDesc desc = scene::generate_sphere_field(args.count, args.seed);
  if (!reported(util::write_file_atomic(args.output, readable_json(scene::canonical_json(desc))))) return kExitFailed;
  fmt::print(stderr, "wrote {} ({} objects, digest {})\n", args.output, desc.objects.size(), scene::scene_digest(desc));
  return kExitOk;
}

}  // namespace dtraced::cli
