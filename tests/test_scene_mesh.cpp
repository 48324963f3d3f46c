// Tests for dtraced::scene meshes: inline and file OBJ meshes, their transforms, their errors
// (naming the scene file, the field, the OBJ file and the line) and their digest.
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>

#include <catch2/catch.hpp>

#include "scene/digest.h"
#include "scene/generate.h"
#include "scene/load.h"
#include "scene_testing.h"

using namespace scene_testing;

namespace {

// A unit right triangle in the xy plane and a square (two triangles after triangulation).
constexpr std::string_view kTriangleObj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
constexpr std::string_view kQuadObj = "# a square\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";

// A JSON string literal of `text` (quotes and newlines escaped).
std::string json_string(std::string_view text) {
  std::string out = "\"";
  for (const char c : text) {
    if (c == '\n') {
      out += "\\n";
    } else if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

std::string inline_mesh(std::string_view obj, std::string_view extra = "") {
  return with_object(R"({"type": "mesh", "obj": )" + json_string(obj) + std::string(extra) + "}");
}

// A directory removed when the test ends, for scenes with mesh files beside them.
class TempDir {
 public:
  TempDir() : path_(std::filesystem::temp_directory_path() / ("dtraced_test_mesh_" + std::to_string(::getpid()))) {
    std::filesystem::create_directories(path_);
  }
  ~TempDir() { std::filesystem::remove_all(path_); }
  std::string write(const std::string& name, std::string_view contents) const {
    const std::filesystem::path p = path_ / name;
    std::filesystem::create_directories(p.parent_path());
    std::ofstream(p, std::ios::binary) << contents;
    return p.string();
  }
  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

// A copy: callers pass temporaries.
dtraced::scene::Mesh only_mesh(const SceneDesc& d) {
  REQUIRE(d.objects.size() == 1);
  REQUIRE(d.objects[0].type == ObjectType::kMesh);
  REQUIRE(d.objects[0].mesh != nullptr);
  return *d.objects[0].mesh;
}

}  // namespace

TEST_CASE("an inline mesh loads its triangles, triangulating polygons", "[scene][mesh]") {
  const SceneDesc tri = load_ok(inline_mesh(kTriangleObj));
  const auto& m = only_mesh(tri);
  REQUIRE(m.triangle_count() == 1);
  CHECK(m.vertices[1] == dtraced::math::Vec3f{1, 0, 0});
  CHECK(m.degenerate_triangles == 0);
  CHECK(m.file.empty());
  CHECK(only_mesh(load_ok(inline_mesh(kQuadObj))).triangle_count() == 2);
}

TEST_CASE("a mesh file is read relative to the scene file, and digests like the same text inline",
          "[scene][mesh][digest]") {
  const TempDir dir;
  dir.write("models/tri.obj", kTriangleObj);
  const std::string scene = dir.write("scene.json", with_object(R"({"type": "mesh", "file": "models/tri.obj"})"));
  // From another working directory: the path is the scene's, not the process's.
  const LoadResult r = load_scene_file(scene);
  INFO(format_errors(r.errors));
  REQUIRE(r.ok());
  CHECK(only_mesh(*r.scene).file == "models/tri.obj");
  CHECK(only_mesh(*r.scene).triangle_count() == 1);

  const SceneDesc inlined = load_ok(inline_mesh(kTriangleObj));
  CHECK(*r.scene == inlined);
  CHECK(canonical_json(*r.scene) == canonical_json(inlined));
  CHECK(scene_digest(*r.scene) == scene_digest(inlined));
  // The canonical form carries the text, so it loads where the file does not exist.
  LoadOptions no_files;
  no_files.allow_mesh_files = false;
  const LoadResult canonical = load_scene_string(canonical_json(*r.scene), "canonical.json", no_files);
  REQUIRE(canonical.ok());
  CHECK(*canonical.scene == *r.scene);

  // load_scene_string resolves against base_dir.
  LoadOptions based;
  based.base_dir = dir.path().string();
  CHECK(load_scene_string(with_object(R"({"type": "mesh", "file": "models/tri.obj"})"), "s.json", based).ok());
}

TEST_CASE("mesh transforms: scale, then rotate X, Y, Z, then translate", "[scene][mesh]") {
  // (1, 0, 0) scaled by 2 -> (2, 0, 0); rotated 90 about Z -> (0, 2, 0); translated -> (10, 22, 30).
  const auto& m =
      only_mesh(load_ok(inline_mesh(kTriangleObj, R"(, "scale": 2, "rotate": [0, 0, 90], "translate": [10, 20, 30])")));
  CHECK(m.vertices[1] == dtraced::math::Vec3f{10, 22, 30});
  CHECK(m.vertices[0] == dtraced::math::Vec3f{10, 20, 30});

  // X first, then Y: (0, 1, 0) -> about X by 90 -> (0, 0, 1) -> about Y by 90 -> (1, 0, 0).
  const auto& xy = only_mesh(load_ok(inline_mesh(kTriangleObj, R"(, "rotate": [90, 90, 0])")));
  CHECK(xy.vertices[2] == dtraced::math::Vec3f{1, 0, 0});

  // A general angle, checked numerically: (1, 0, 0) about Y by 30 degrees -> (cos 30, 0, -sin 30).
  const auto& y30 = only_mesh(load_ok(inline_mesh(kTriangleObj, R"(, "rotate": [0, 30, 0], "scale": [3, 1, 1])")));
  CHECK(y30.vertices[1].x == Approx(3 * 0.8660254037844386).epsilon(1e-6));
  CHECK(y30.vertices[1].y == 0.0f);
  CHECK(y30.vertices[1].z == Approx(-1.5).epsilon(1e-6));

  // A mirroring scale keeps the normal on the side the OBJ's winding says (+z here).
  const auto& mirrored = only_mesh(load_ok(inline_mesh(kTriangleObj, R"(, "scale": [-1, 1, 1])")));
  const dtraced::math::Vec3f n =
      dtraced::math::cross(mirrored.vertices[1] - mirrored.vertices[0], mirrored.vertices[2] - mirrored.vertices[0]);
  CHECK(n.z > 0);
}

TEST_CASE("broken meshes name the scene file, the field, the OBJ file and the problem", "[scene][mesh][errors]") {
  const TempDir dir;
  dir.write("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n");
  dir.write("index.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n");
  dir.write("quad_index.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3 9\n");
  dir.write("junk.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n");
  const auto load_with = [&](std::string_view object) {
    return load_scene_file(dir.write("scene.json", with_object(std::string(object))));
  };
  const auto has = [](const LoadResult& r, std::string_view path, std::string_view a, std::string_view b = "") {
    INFO(format_errors(r.errors));
    return std::any_of(r.errors.begin(), r.errors.end(), [&](const auto& e) {
      return e.file.ends_with("scene.json") && e.path == path && e.message.find(a) != std::string::npos &&
             e.message.find(b) != std::string::npos;
    });
  };
  const std::string at = "/scene_objects/0";

  CHECK(has(load_with(R"({"type": "mesh", "file": "nan.obj"})"), at + "/file", "nan.obj: line 2", "\"nan\""));
  CHECK(has(load_with(R"({"type": "mesh", "file": "index.obj"})"), at + "/file", "index.obj", "out of"));
  CHECK(has(load_with(R"({"type": "mesh", "file": "quad_index.obj"})"), at + "/file", "quad_index.obj", "out of"));
  CHECK(has(load_with(R"({"type": "mesh", "file": "junk.obj"})"), at + "/file", "junk.obj", "tinyobjloader"));
  CHECK(has(load_with(R"({"type": "mesh", "file": "missing.obj"})"), at + "/file", "missing.obj"));
  CHECK(has(load_with(R"({"type": "mesh", "file": "nan.obj", "obj": "v 0 0 0"})"), at, "not both"));
  CHECK(has(load_with(R"({"type": "mesh"})"), at, "needs \"file\""));
  CHECK(has(load_with(R"({"type": "mesh", "file": 3})"), at + "/file", "expected a string"));
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "scale": 0})"), at + "/scale",
            "must not be zero"));
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "scale": [1, 0, 1]})"),
            at + "/scale/1", "must not be zero"));
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "scale": "big"})"),
            at + "/scale", "expected a number"));
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 1e39 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"})"), at + "/obj",
            "float range"));
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "colour": 1})"),
            at + "/colour", "unknown key"));
  // Inline OBJ errors carry the line too.
  CHECK(has(load_with(R"({"type": "mesh", "obj": "v 0 0 0\nv 1 x 0\n"})"), at + "/obj", "line 2"));

  // Refused outright where files are not allowed (scenes from the network).
  LoadOptions no_files;
  no_files.allow_mesh_files = false;
  const LoadResult refused = load_scene_string(with_object(R"({"type": "mesh", "file": "nan.obj"})"), kFile, no_files);
  CHECK(has_error(refused, at + "/file", "inline"));

  // The triangle budget is per scene.
  LoadOptions small;
  small.max_triangles = 3;
  const LoadResult over = load_scene_string(
      "{\"camera\": {}, \"scene_objects\": [" + std::string(R"({"type": "mesh", "obj": )") + json_string(kQuadObj) +
          "}, " + R"({"type": "mesh", "obj": )" + json_string(kQuadObj) + "}], \"scene_lights\": []}",
      kFile, small);
  CHECK(has_error(over, "/scene_objects/1/obj", "triangles"));
}

TEST_CASE("the digest follows the OBJ content and the transform", "[scene][mesh][digest]") {
  const SceneDesc base = load_ok(inline_mesh(kTriangleObj));
  const SceneDesc moved_vertex = load_ok(inline_mesh("v 0 0 0\nv 1 0 0\nv 0 2 0\nf 1 2 3\n"));
  const SceneDesc translated = load_ok(inline_mesh(kTriangleObj, R"(, "translate": [0, 0, 1])"));
  CHECK(scene_digest(base) != scene_digest(moved_vertex));
  CHECK(scene_digest(base) != scene_digest(translated));
  CHECK(canonical_json(base) != canonical_json(moved_vertex));
  // A scale written as a number or as [s, s, s] is the same scene.
  CHECK(scene_digest(load_ok(inline_mesh(kTriangleObj, R"(, "scale": 2)"))) ==
        scene_digest(load_ok(inline_mesh(kTriangleObj, R"(, "scale": [2, 2, 2])"))));
  // Round trip, bit for bit.
  const SceneDesc again = load_ok(canonical_json(translated));
  CHECK(again == translated);
  CHECK(canonical_json(again) == canonical_json(translated));
}

TEST_CASE("degenerate triangles are kept and counted", "[scene][mesh]") {
  // One good triangle, one with a repeated vertex, one with collinear vertices.
  const auto& m = only_mesh(load_ok(inline_mesh("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 2 0 0\nf 1 2 3\nf 1 1 2\nf 1 2 4\n")));
  CHECK(m.triangle_count() == 3);
  CHECK(m.degenerate_triangles == 2);
}

TEST_CASE("the mesh generator is deterministic and its scene loads", "[scene][mesh][generate]") {
  const auto a = dtraced::scene::generate_mesh_scene(5000, 3, "models/g");
  const auto b = dtraced::scene::generate_mesh_scene(5000, 3, "models/g");
  CHECK(a.scene_json == b.scene_json);
  REQUIRE(a.objs.size() == b.objs.size());
  for (std::size_t i = 0; i < a.objs.size(); ++i) CHECK(a.objs[i].text == b.objs[i].text);
  CHECK(a.triangles > 2500);
  CHECK(a.triangles < 10000);

  const TempDir dir;
  for (const auto& f : a.objs) dir.write(f.path, f.text);
  const LoadResult r = load_scene_file(dir.write("g.json", a.scene_json));
  INFO(format_errors(r.errors));
  REQUIRE(r.ok());
  std::size_t triangles = 0;
  for (const auto& o : r.scene->objects) triangles += o.mesh ? o.mesh->triangle_count() : 0;
  CHECK(triangles == a.triangles);
}

TEST_CASE("a scene's keys, file names and OBJ text are escaped in its errors", "[scene][errors][escape]") {
  // Each error is one line of printable text: a scene cannot forge a line or send a terminal escape.
  const auto check_printable = [](const LoadResult& r, std::string_view fragment) {
    const std::string text = format_errors(r.errors);
    INFO(text);
    REQUIRE_FALSE(r.errors.empty());
    CHECK(static_cast<std::size_t>(std::count(text.begin(), text.end(), '\n')) == r.errors.size());
    for (const char c : text) CHECK((c == '\n' || static_cast<unsigned char>(c) >= 0x20));
    CHECK(text.find(fragment) != std::string::npos);
  };
  check_printable(load_scene_string(with_object(R"({"type": "sphere", "loc": [0, 0, 0], "radius": 1,
                                                    "x\ndtraced: info: all good\u001b[2J": 1})"),
                                    kFile),
                  R"(/scene_objects/0/x\ndtraced: info: all good\u001b[2J: unknown key "x\ndtraced)");
  check_printable(load_scene_string(with_object(R"({"type": "mesh", "obj": "v 0 0 0\nv 1\u001b[31m 0 0\n"})"), kFile),
                  R"("1\u001b[31m")");
  // An OBJ file that is not UTF-8 is refused at its line (it would not fit in the canonical JSON).
  const TempDir dir;
  dir.write("latin1.obj", "v 0 0 0\nv 1 0 0\n# caf\xe9\nv 0 1 0\nf 1 2 3\n");
  check_printable(load_scene_file(dir.write("scene.json", with_object(R"({"type": "mesh", "file": "latin1.obj"})"))),
                  "latin1.obj: line 3: not valid UTF-8");
  LoadOptions no_files;
  no_files.allow_mesh_files = false;
  check_printable(load_scene_string(with_object(R"({"type": "mesh", "file": "a\r\nb.obj"})"), kFile, no_files),
                  R"(mesh file "a\r\nb.obj" not accepted)");
}
