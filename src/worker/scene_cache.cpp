#include "worker/scene_cache.h"

#include <unistd.h>

#include <algorithm>
#include <array>
#include <cassert>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <memory>
#include <type_traits>
#include <utility>
#include <vector>

#include <fmt/format.h>

#include "scene/animation.h"
#include "scene/digest.h"
#include "scene/load.h"
#include "util/sha256.h"

namespace dtraced::worker {
namespace {

// Load errors quoted in a refusal: the first few say enough, and the message stays one log line.
constexpr std::size_t kMaxQuotedErrors = 3;

// Why a body that does not load is refused: its first few errors.
std::string refusal(const std::string& label, const scene::LoadResult& loaded) {
  std::string reasons;
  for (std::size_t i = 0; i < loaded.errors.size() && i < kMaxQuotedErrors; ++i) {
    reasons += (i == 0 ? "" : "; ") + loaded.errors[i].to_string();
  }
  if (loaded.errors.size() > kMaxQuotedErrors) {
    reasons += fmt::format("; and {} more", loaded.errors.size() - kMaxQuotedErrors);
  }
  return fmt::format("the body sent as {} does not load: {}", label, reasons);
}

}  // namespace

SceneFrames::SceneFrames(render::AnimatedScene scene, std::size_t keep) : scene_(std::move(scene)), keep_(keep) {
  assert(keep >= 1);
}

ScenePtr SceneFrames::frame(std::uint32_t n) const {
  if (!scene_.animated()) return scene_.frame(n);
  std::shared_future<ScenePtr> kept;
  std::promise<ScenePtr> building;
  {
    std::lock_guard lock(mu_);
    const auto it = std::find_if(recent_.begin(), recent_.end(), [n](const auto& entry) { return entry.first == n; });
    if (it != recent_.end()) {
      recent_.splice(recent_.begin(), recent_, it);
      kept = it->second;
    } else {
      recent_.emplace_front(n, building.get_future().share());
      // A frame evicted while it builds stays alive for the threads waiting for it.
      while (recent_.size() > keep_) recent_.pop_back();
    }
  }
  if (kept.valid()) return kept.get();  // built, or being built by another thread: waited for
  try {
    ScenePtr scene = scene_.frame(n);
    building.set_value(scene);
    return scene;
  } catch (...) {
    // Not kept: the next lease of this frame tries again.
    {
      std::lock_guard lock(mu_);
      std::erase_if(recent_, [n](const auto& entry) { return entry.first == n; });
    }
    building.set_exception(std::current_exception());
    throw;
  }
}

render::Tile SceneFrames::render(const scene::RenderSettings& settings, const render::TileRect& rect) const {
  const ScenePtr scene = frame(settings.frame);
  return render::render_tile(*scene, settings, rect);
}

std::size_t SceneFrames::kept() const {
  std::lock_guard lock(mu_);
  return recent_.size();
}

SceneCache::SceneCache(std::size_t capacity) : capacity_(capacity) { assert(capacity >= 1); }

FramesPtr SceneCache::find(std::string_view digest) {
  const auto it = index_.find(digest);
  if (it == index_.end()) return nullptr;
  entries_.splice(entries_.begin(), entries_, it->second);
  return it->second->second;
}

void SceneCache::insert(const std::string& digest, FramesPtr scene) {
  assert(scene != nullptr);
  if (const auto it = index_.find(digest); it != index_.end()) {
    it->second->second = std::move(scene);
    entries_.splice(entries_.begin(), entries_, it->second);
    return;
  }
  entries_.emplace_front(digest, std::move(scene));
  index_.emplace(entries_.front().first, entries_.begin());
  while (entries_.size() > capacity_) {
    index_.erase(entries_.back().first);
    entries_.pop_back();
  }
}

bool SceneCache::contains(std::string_view digest) const { return index_.contains(digest); }

namespace {

// ---- binary scene cache ----

constexpr std::array<char, 8> kCacheMagic = {'d', 't', 's', 'c', 'e', 'n', 'e', '\n'};
constexpr std::uint32_t kByteOrderMark = 0x01020304;
constexpr std::size_t kDigestChars = 64;

// Sections, in file order.
enum Section : std::size_t { kDesc, kShapes, kMaterials, kOwners, kTransparent, kSections };

struct CacheHeader {
  std::array<char, 8> magic;
  std::uint32_t version;
  std::uint32_t byte_order;
  std::uint32_t shape_bytes;
  std::uint32_t material_bytes;
  std::array<char, kDigestChars> digest;
  std::array<std::uint64_t, kSections> counts;  // bytes of the description, elements of the others
  std::uint32_t features;                       // bit 0 reflection, bit 1 specular
  std::uint32_t reserved;
  std::array<util::Sha256Digest, kSections> sums;
};
static_assert(std::is_trivially_copyable_v<CacheHeader> && std::is_trivially_copyable_v<accel::Shape> &&
              std::is_trivially_copyable_v<render::MaterialF>);

// A transparent object as stored: its index and whether it is a mesh.
struct TransparentEntry {
  std::uint32_t object;
  std::uint32_t mesh;
};

template <typename T>
std::string_view bytes_of(std::span<const T> v) {
  return {reinterpret_cast<const char*>(v.data()), v.size_bytes()};
}

util::Error cache_error(const std::string& path, std::string problem) {
  return util::Error{std::move(problem), "", path};
}

using File = std::unique_ptr<std::FILE, int (*)(std::FILE*)>;

// Reads `count` elements of a section into `out`, checking its SHA-256.
template <typename T>
util::Status read_section(std::FILE* f, const std::string& path, const char* name, std::uint64_t count,
                          const util::Sha256Digest& sum, std::vector<T>& out) {
  out.resize(count);
  if (count > 0 && std::fread(out.data(), sizeof(T), count, f) != count) {
    return cache_error(path, fmt::format("scene cache file: truncated in its {}", name));
  }
  if (util::sha256_bytes(bytes_of(std::span<const T>(out))) != sum) {
    return cache_error(path, fmt::format("scene cache file: its {} do not match their checksum (corrupt)", name));
  }
  return {};
}

}  // namespace

std::string cached_scene_path(const std::string& dir, std::string_view digest) {
  return (std::filesystem::path(dir) / fmt::format("{}.dtscene", digest)).string();
}

std::size_t prune_scene_cache(const std::string& dir, std::size_t keep) {
  std::error_code ec;
  std::vector<std::pair<std::filesystem::file_time_type, std::filesystem::path>> files;
  for (const auto& entry : std::filesystem::directory_iterator(dir, ec)) {
    if (entry.path().extension() != ".dtscene" || !entry.is_regular_file(ec)) continue;
    const auto when = entry.last_write_time(ec);
    if (!ec) files.emplace_back(when, entry.path());
  }
  if (files.size() <= keep) return 0;
  std::sort(files.begin(), files.end());  // oldest first
  std::size_t removed = 0;
  for (std::size_t i = 0; i < files.size() - keep; ++i) {
    if (std::filesystem::remove(files[i].second, ec) && !ec) ++removed;
  }
  return removed;
}

util::Status write_cached_scene(const std::string& path, std::string_view digest, const scene::SceneDesc& desc,
                                const render::RenderSceneBuilder& builder) {
  assert(desc.objects.empty() && desc.animation == nullptr);
  if (digest.size() != kDigestChars) return cache_error(path, "scene cache file: not a scene digest");
  const render::RenderSceneBuilder::Parts parts = builder.parts();
  std::vector<TransparentEntry> transparent;
  transparent.reserve(parts.transparent.size());
  for (const auto& [object, mesh] : parts.transparent) transparent.push_back({object, mesh ? 1u : 0u});
  const std::string json = scene::canonical_json(desc);

  CacheHeader h{};
  h.magic = kCacheMagic;
  h.version = kCacheVersion;
  h.byte_order = kByteOrderMark;
  h.shape_bytes = sizeof(accel::Shape);
  h.material_bytes = sizeof(render::MaterialF);
  std::copy(digest.begin(), digest.end(), h.digest.begin());
  const std::array<std::string_view, kSections> sections = {json, bytes_of(parts.shapes), bytes_of(parts.materials),
                                                            bytes_of(parts.shape_object),
                                                            bytes_of(std::span<const TransparentEntry>(transparent))};
  h.counts = {json.size(), parts.shapes.size(), parts.materials.size(), parts.shape_object.size(), transparent.size()};
  h.features = (parts.features.reflection ? 1u : 0u) | (parts.features.specular ? 2u : 0u);
  for (std::size_t i = 0; i < kSections; ++i) h.sums[i] = util::sha256_bytes(sections[i]);

  // A temporary file renamed over the target: a reader sees a whole file or none.
  const std::string temporary = fmt::format("{}.tmp.{}", path, ::getpid());
  {
    File f(std::fopen(temporary.c_str(), "wb"), &std::fclose);
    if (!f) return cache_error(temporary, fmt::format("cannot create the scene cache file: {}", std::strerror(errno)));
    bool written = std::fwrite(&h, sizeof h, 1, f.get()) == 1;
    for (const std::string_view section : sections) {
      written =
          written && (section.empty() || std::fwrite(section.data(), 1, section.size(), f.get()) == section.size());
    }
    written = written && std::fflush(f.get()) == 0 && ::fsync(::fileno(f.get())) == 0;
    const int error = errno;
    if (std::fclose(f.release()) != 0 || !written) {
      std::remove(temporary.c_str());
      return cache_error(temporary, fmt::format("cannot write the scene cache file: {}", std::strerror(error)));
    }
  }
  if (std::rename(temporary.c_str(), path.c_str()) != 0) {
    const int error = errno;
    std::remove(temporary.c_str());
    return cache_error(path, fmt::format("cannot rename the scene cache file into place: {}", std::strerror(error)));
  }
  return {};
}

util::Result<FramesPtr> read_cached_scene(const std::string& path, std::string_view digest, accel::Isa isa,
                                          unsigned build_threads) {
  File f(std::fopen(path.c_str(), "rb"), &std::fclose);
  if (!f) return cache_error(path, fmt::format("cannot open the scene cache file: {}", std::strerror(errno)));
  std::error_code ec;
  const std::uint64_t size = std::filesystem::file_size(path, ec);
  if (ec) return cache_error(path, fmt::format("cannot size the scene cache file: {}", ec.message()));
  CacheHeader h{};
  if (std::fread(&h, sizeof h, 1, f.get()) != 1 || h.magic != kCacheMagic) {
    return cache_error(path, "not a dtraced scene cache file");
  }
  if (h.version != kCacheVersion) {
    return cache_error(path, fmt::format("scene cache file of version {}, not {}", h.version, kCacheVersion));
  }
  if (h.byte_order != kByteOrderMark || h.shape_bytes != sizeof(accel::Shape) ||
      h.material_bytes != sizeof(render::MaterialF)) {
    return cache_error(path, "scene cache file of another byte order or layout");
  }
  if (std::string_view(h.digest.data(), h.digest.size()) != digest) {
    return cache_error(path, "scene cache file of another scene (its digest differs)");
  }
  const std::array<std::uint64_t, kSections> limits = {kMaxCachedDescBytes, scene::kMaxObjects + scene::kMaxTriangles,
                                                       scene::kMaxObjects, scene::kMaxObjects + scene::kMaxTriangles,
                                                       scene::kMaxObjects};
  const std::array<std::uint64_t, kSections> element = {1, sizeof(accel::Shape), sizeof(render::MaterialF),
                                                        sizeof(std::uint32_t), sizeof(TransparentEntry)};
  std::uint64_t expected = sizeof h;
  for (std::size_t i = 0; i < kSections; ++i) {
    if (h.counts[i] > limits[i]) {
      return cache_error(path, fmt::format("scene cache file: section {} has {} entries, over its limit of {}", i,
                                           h.counts[i], limits[i]));
    }
    expected += h.counts[i] * element[i];
  }
  if (size != expected) {
    return cache_error(
        path, fmt::format("scene cache file of {} bytes where its header says {} (truncated?)", size, expected));
  }
  std::vector<char> json;
  std::vector<accel::Shape> shapes;
  std::vector<render::MaterialF> materials;
  std::vector<std::uint32_t> owners;
  std::vector<TransparentEntry> stored;
  if (util::Status r = read_section(f.get(), path, "description", h.counts[kDesc], h.sums[kDesc], json); !r)
    return r.error();
  if (util::Status r = read_section(f.get(), path, "shapes", h.counts[kShapes], h.sums[kShapes], shapes); !r)
    return r.error();
  if (util::Status r = read_section(f.get(), path, "materials", h.counts[kMaterials], h.sums[kMaterials], materials);
      !r)
    return r.error();
  if (util::Status r = read_section(f.get(), path, "owners", h.counts[kOwners], h.sums[kOwners], owners); !r)
    return r.error();
  if (util::Status r =
          read_section(f.get(), path, "transparent objects", h.counts[kTransparent], h.sums[kTransparent], stored);
      !r)
    return r.error();
  f.reset();
  scene::LoadOptions options;
  options.allow_mesh_files = false;
  scene::LoadResult loaded = scene::load_scene_string(std::string_view(json.data(), json.size()), path, options);
  if (!loaded.ok() || !loaded.scene->objects.empty() || scene::is_animated(*loaded.scene)) {
    return cache_error(path, "scene cache file: its description is not a static scene's without objects");
  }
  std::vector<std::pair<std::uint32_t, bool>> transparent;
  transparent.reserve(stored.size());
  for (const TransparentEntry& t : stored) transparent.emplace_back(t.object, t.mesh != 0);
  render::SceneFeatures features;
  features.reflection = (h.features & 1u) != 0;
  features.specular = (h.features & 2u) != 0;
  util::Result<render::RenderSceneBuilder> builder = render::RenderSceneBuilder::from_parts(
      std::move(shapes), std::move(materials), std::move(owners), std::move(transparent), features);
  if (!builder) return cache_error(path, fmt::format("scene cache file: {}", builder.error().message));
  return FramesPtr(std::make_shared<const SceneFrames>(
      render::AnimatedScene::still(std::move(*builder).build(*loaded.scene, isa, build_threads))));
}

PreparedScene prepare_scene(std::string_view body, std::string_view digest, accel::Isa isa, unsigned build_threads,
                            const std::string& cache_dir) {
  PreparedScene prepared;
  const std::string label = fmt::format("scene {}", digest);
  const std::string cache_file = cache_dir.empty() ? std::string() : cached_scene_path(cache_dir, digest);
  std::error_code ec;
  if (!cache_file.empty() && std::filesystem::exists(cache_file, ec)) {
    util::Result<FramesPtr> cached = read_cached_scene(cache_file, digest, isa, build_threads);
    if (cached) {
      prepared.scene = std::move(*cached);
      return prepared;
    }
    prepared.warning = fmt::format("{}; loaded the scene from its JSON instead", cached.error().to_string());
  }
  scene::LoadOptions options;
  options.allow_mesh_files = false;
  // A body that is the canonical text itself (what a collector serves) has the digest's SHA-256,
  // and no other text can have it: then the scene needs no second serialisation to be checked,
  // and a static one's objects go straight into the render-ready scene as they are read (the
  // description of a large scene is never held whole).
  if (util::sha256_hex(body) == digest) {
    render::RenderSceneBuilder builder;
    scene::LoadOptions streamed = options;
    streamed.object_sink = &builder;
    scene::LoadResult loaded = scene::load_scene_string(body, label, streamed);
    if (!loaded.ok()) {
      prepared.error = refusal(label, loaded);
      return prepared;
    }
    if (!scene::is_animated(*loaded.scene)) {
      if (!cache_file.empty()) {
        if (const util::Status written = write_cached_scene(cache_file, digest, *loaded.scene, builder); !written) {
          prepared.warning += (prepared.warning.empty() ? "" : "; ") + written.error().to_string();
        }
      }
      prepared.scene = std::make_shared<const SceneFrames>(
          render::AnimatedScene::still(std::move(builder).build(*loaded.scene, isa, build_threads)));
      return prepared;
    }
    // Animated: its frames are built from the description, loaded again below with its objects.
  }
  scene::LoadResult loaded = scene::load_scene_string(body, label, options);
  if (!loaded.ok()) {
    prepared.error = refusal(label, loaded);
    return prepared;
  }
  const std::string actual = scene::scene_digest(*loaded.scene);
  if (actual != digest) {
    prepared.error = fmt::format("the body sent as {} is another scene (its digest is {})", label, actual);
    return prepared;
  }
  prepared.scene =
      std::make_shared<const SceneFrames>(render::AnimatedScene::prepare(*loaded.scene, isa, build_threads));
  return prepared;
}

}  // namespace dtraced::worker
