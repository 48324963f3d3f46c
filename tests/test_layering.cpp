// The code layout, made executable: every `#include "module/..."` under src/ and every dtraced_*
// library named in a folder's CMakeLists.txt is an arrow from that folder's module to another.
// An arrow that the table below does not allow fails the test, naming the file and line. The
// table is the one README.md's "Code layout" shows; change both together.
//
// The test reads source text only (no compiler, no CMake): it runs in milliseconds and fails on
// the line that introduced the arrow.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

namespace {

namespace fs = std::filesystem;

// Which module may use which (beside itself). Dependencies point down only: the renderer
// (math, image, scene, accel, render) knows nothing of the network, and the daemons' shared
// vocabulary (scene, jsonio, image, protocol) never reaches the renderer.
const std::map<std::string, std::set<std::string>>& allowed() {
  static const std::map<std::string, std::set<std::string>> table = {
      {"util", {}},
      {"math", {"util"}},
      {"jsonio", {"util"}},
      {"image", {"math", "util"}},
      {"scene", {"jsonio", "image", "math", "util"}},  // image: kMaxImageSide, the one image bound
      {"accel", {"math", "util"}},
      {"render", {"scene", "accel", "image", "math", "util"}},
      {"protocol", {"scene", "jsonio", "image", "math", "util"}},
      {"async", {"util"}},
      {"tls", {"util"}},
      {"http", {"tls", "async", "util"}},
      {"store", {"util"}},
      {"web", {}},  // the web page's files, embedded: data only
      {"collector", {"web", "protocol", "http", "tls", "async", "store", "scene", "jsonio", "image", "math", "util"}},
      {"worker", {"protocol", "http", "async", "render", "accel", "scene", "jsonio", "image", "math", "util"}},
      {"cli",
       {"collector", "web", "worker", "protocol", "http", "tls", "async", "store", "render", "accel", "scene", "jsonio",
        "image", "math", "util"}},
      // Benchmark tools, not the product: they may measure anything.
      {"bench",
       {"collector", "web", "worker", "protocol", "http", "tls", "async", "store", "render", "accel", "scene", "jsonio",
        "image", "math", "util"}},
  };
  return table;
}

struct Arrow {
  std::string from, to;
  std::string where;  // "src/collector/jobs.h:24"
};

fs::path source_dir() { return fs::path(DTRACED_SOURCE_DIR) / "src"; }

std::vector<std::string> modules_on_disk() {
  std::vector<std::string> out;
  for (const auto& entry : fs::directory_iterator(source_dir())) {
    if (entry.is_directory()) out.push_back(entry.path().filename().string());
  }
  std::sort(out.begin(), out.end());
  return out;
}

// Every arrow written in the sources and build files of one module.
std::vector<Arrow> arrows_of(const std::string& module, const std::set<std::string>& modules) {
  static const std::regex include_re(R"re(^\s*#\s*include\s*"([a-z_0-9]+)/)re");
  static const std::regex library_re(R"re(\bdtraced_([a-z_0-9]+)\b)re");
  std::vector<Arrow> out;
  const fs::path dir = source_dir() / module;
  std::vector<fs::path> files;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (entry.is_regular_file()) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  for (const fs::path& file : files) {
    const std::string name = file.filename().string();
    const bool cmake = name == "CMakeLists.txt";
    const bool source = file.extension() == ".h" || file.extension() == ".cpp";
    if (!cmake && !source) continue;
    std::ifstream in(file);
    REQUIRE(in);
    const std::string shown = fs::relative(file, source_dir().parent_path()).string();
    std::string line;
    for (int number = 1; std::getline(in, line); ++number) {
      const std::string where = shown + ":" + std::to_string(number);
      if (source) {
        std::smatch m;
        if (std::regex_search(line, m, include_re) && modules.contains(m[1].str())) {
          out.push_back({module, m[1].str(), where});
        }
        continue;
      }
      // CMake: library names on any line (target_link_libraries may span lines); the module's
      // own target and comments do not count.
      const std::string code = line.substr(0, line.find('#'));
      for (auto it = std::sregex_iterator(code.begin(), code.end(), library_re); it != std::sregex_iterator(); ++it) {
        const std::string to = (*it)[1].str();
        if (modules.contains(to)) out.push_back({module, to, where});
      }
    }
  }
  return out;
}

}  // namespace

TEST_CASE("every module of src/ is in the layering table", "[layering]") {
  for (const std::string& module : modules_on_disk()) {
    INFO("src/" << module << "/ has no row in the table of allowed dependencies (tests/test_layering.cpp)");
    CHECK(allowed().contains(module));
  }
}

TEST_CASE("includes and link libraries only point down the layers", "[layering]") {
  const std::vector<std::string> list = modules_on_disk();
  const std::set<std::string> modules(list.begin(), list.end());
  std::size_t arrows = 0;
  std::vector<std::string> violations;
  for (const std::string& module : list) {
    const auto row = allowed().find(module);
    if (row == allowed().end()) continue;  // reported by the test above
    for (const Arrow& a : arrows_of(module, modules)) {
      ++arrows;
      if (a.to == a.from || row->second.contains(a.to)) continue;
      violations.push_back(a.where + ": " + a.from + " -> " + a.to);
    }
  }
  // The scan found the arrows that exist (a broken pattern would find none and pass).
  CHECK(arrows > 100);
  std::ostringstream report;
  for (const std::string& v : violations) report << "\n  " << v;
  INFO("arrows outside the table:" << report.str());
  CHECK(violations.empty());
}

TEST_CASE("the table is layered: no module reaches itself through others", "[layering]") {
  // Depth-first search for a cycle; every module's closure stays inside the table.
  std::map<std::string, int> state;  // 0 new, 1 on the path, 2 done
  std::vector<std::string> cycle;
  std::function<bool(const std::string&)> visit = [&](const std::string& m) {
    state[m] = 1;
    for (const std::string& next : allowed().at(m)) {
      REQUIRE(allowed().contains(next));
      if (state[next] == 1 || (state[next] == 0 && visit(next))) {
        cycle.push_back(m);
        return true;
      }
    }
    state[m] = 2;
    return false;
  };
  for (const auto& [m, _] : allowed()) {
    if (state[m] == 0) visit(m);
  }
  INFO("cycle through " << (cycle.empty() ? std::string("nothing") : cycle.front()));
  CHECK(cycle.empty());
}

TEST_CASE("the daemons' shared vocabulary never reaches the renderer", "[layering]") {
  // The closure of what protocol and collector may use, through the table.
  for (const std::string root : {"protocol", "collector", "http", "store"}) {
    std::set<std::string> seen;
    std::vector<std::string> stack{root};
    while (!stack.empty()) {
      const std::string m = stack.back();
      stack.pop_back();
      for (const std::string& next : allowed().at(m)) {
        if (seen.insert(next).second) stack.push_back(next);
      }
    }
    INFO(root);
    CHECK_FALSE(seen.contains("render"));
    CHECK_FALSE(seen.contains("accel"));
  }
}
