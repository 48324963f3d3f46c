// The document, its camera and render block, and the entry points (load.h); the objects and
// lights are load_objects.cpp's.
#include "scene/load.h"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cmath>
#include <condition_variable>
#include <cstring>
#include <deque>
#include <exception>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <memory>
#include <mutex>
#include <optional>
#include <thread>
#include <utility>
#include <vector>

#include <boost/json/monotonic_resource.hpp>
#include <boost/json/object.hpp>
#include <boost/json/value.hpp>
#include <fmt/format.h>

#include "jsonio/parse.h"
#include "math/vec.h"
#include "scene/animation.h"
#include "scene/load_animation.h"
#include "scene/load_objects.h"
#include "scene/scene_json.h"
#include "util/file.h"
#include "util/huge_pages.h"

namespace dtraced::scene {
namespace {

namespace json = boost::json;
using detail::kKeyAliases;
using detail::SceneReader;
using jsonio::Need;
using jsonio::Path;

constexpr std::array<std::string_view, 4> kTopKeys = {"camera", "render", "scene_objects", "scene_lights"};
constexpr std::array<std::string_view, 4> kCameraKeys = {"position", "look_at", "up", "fov"};

void read_camera(SceneReader& s, const json::value& v, const Path& at, Camera& camera) {
  jsonio::Reader& r = s.r;
  const json::object* o = r.object(v, at);
  if (o == nullptr) return;
  jsonio::Fields f(r, *o, at, kCameraKeys, kKeyAliases);
  const std::size_t errors_before = r.error_count();
  const auto vec3 = [&r](const json::value& value, const Path& p) { return read_vec3(r, value, p); };
  s.index = 0;
  detail::read_animatable(s, f, "position", camera.position, Need::kOptional, Target::kCameraPosition, vec3);
  detail::read_animatable(s, f, "look_at", camera.look_at, Need::kOptional, Target::kCameraLookAt, vec3);
  detail::read_animatable(s, f, "up", camera.up, Need::kOptional, Target::kCameraUp, vec3);
  detail::read_animatable(s, f, "fov", camera.fov_deg, Need::kOptional, Target::kCameraFov,
                          [&r](const json::value& value, const Path& p) {
                            const auto d = read_float(r, value, p);
                            if (d && !(*d > 0 && *d < 180)) {
                              r.error(p, fmt::format("must be in the open interval (0, 180) (got {})", *d));
                              return std::optional<double>();
                            }
                            return d;
                          });
  if (r.error_count() != errors_before) return;  // the geometry checks need every vector
  // The camera at t = 0 (an animated camera is checked at its other times by check_camera_times).
  if (const auto problem = camera_problem(camera)) r.error(f.path(problem->key), std::string(problem->message));
}

// An animated camera, at every key time of its tracks and at every frame of the scene's own range
// (render.frames, or the one frame render.frame): other times fall back (animation.h).
void check_camera_times(SceneReader& s, const SceneDesc& scene) {
  std::vector<double> times;
  for (const Track& track : scene.animation->tracks) {
    if (track.target > Target::kCameraFov) break;  // sorted: the camera's tracks come first
    for (const Key& key : track.keys) times.push_back(key.t + track.offset);
  }
  if (times.empty()) return;
  const FrameRange frames = scene.render.frames.value_or(FrameRange{scene.render.frame, scene.render.frame, 1});
  for (std::uint32_t i = 0; i < frames.count(); ++i) times.push_back(frames.at(i) / scene.render.fps);
  for (const double t : times) {
    const Camera camera = animated_camera(scene, t);
    if (const auto problem = camera_problem(camera)) {
      const Path root;
      const Path camera_at = root.key("camera");
      s.r.error(camera_at.key(problem->key),
                fmt::format("at t = {} s (frame {}): {}", t, t * scene.render.fps, problem->message));
      return;
    }
  }
}

void read_render(SceneReader& s, const json::value& v, const Path& at, RenderSettings& render) {
  const json::object* o = s.r.object(v, at);
  if (o == nullptr) return;
  jsonio::Fields f(s.r, *o, at, kRenderKeys, kKeyAliases);
  read_render_settings(f, render, Need::kOptional);
  // The background is a radiance like a light's emission: the same bound (load_objects.cpp).
  const Path background = f.path("background");
  for (std::size_t i = 0; i < 3; ++i) {
    if (render.background[i] > kMaxRadiance) {
      s.r.error(background.index(i), fmt::format("must be at most 2^120 ({:g}), or shading overflows (got {})",
                                                 kMaxRadiance, render.background[i]));
    }
  }
}

// "scene_objects" or "scene_lights": each element read by `read` (nullopt after its errors), and
// a warning when there is none.
template <typename T, typename Read>
void read_list(SceneReader& s, jsonio::Fields& root, std::string_view key, std::size_t limit, std::string_view what,
               std::vector<T>& out, Read read, std::string_view when_empty) {
  const json::value* v = root.get(key, Need::kRequired);
  if (v == nullptr) return;
  const Path at = root.path(key);
  const json::array* list = s.r.array(*v, at, limit, what);
  if (list == nullptr) return;
  out.reserve(list->size());
  for (std::size_t i = 0; i < list->size(); ++i) {
    s.index = static_cast<std::uint32_t>(i);  // the owner of the element's tracks
    if (auto element = read(s, (*list)[i], at.index(i))) out.push_back(std::move(*element));
  }
  if (list->empty()) s.warning(at, std::string(when_empty));
}

// The keys of `v`'s objects, nested ones too.
std::size_t key_count(const json::value& v) {
  std::size_t n = 0;
  if (const json::object* o = v.if_object()) {
    n += o->size();
    for (const auto& kv : *o) n += key_count(kv.value());
  } else if (const json::array* a = v.if_array()) {
    for (const json::value& e : *a) n += key_count(e);
  }
  return n;
}

// The parser's errors (duplicate keys) at most: one place is kept for the syntax error, which
// matters more than any duplicate key before it.
std::size_t max_parse_errors(const LoadOptions& options) { return options.max_errors > 0 ? options.max_errors - 1 : 0; }

// The elements of "scene_objects", read while the file was parsed (jsonio::StrictParser), so the
// document never holds them all: a reader of their own keeps their errors, warnings and tracks
// apart until read_scene puts them where reading them in place would have.
struct StreamedObjects {
  StreamedObjects(const std::string& file, const LoadOptions& options)
      : s(file, options), sink(options.object_sink), max_duplicates(max_parse_errors(options)) {}
  SceneReader s;
  ObjectSink* sink = nullptr;  // LoadOptions::object_sink: the objects go there, not to `objects`
  std::vector<Object> objects;
  std::size_t count = 0;  // elements met, also past kMaxObjects
  std::size_t kept = 0;   // valid objects, in `objects` or given to the sink
  std::size_t room = 0;   // objects.capacity(), or what the sink was last asked to reserve
  // The size of the whole text (0: unknown) and how much of it came before the piece being
  // parsed: the objects seen per byte so far predict how many there are in all.
  std::uint64_t total_bytes = 0;
  std::uint64_t bytes_before_piece = 0;
  // Where the values of elements read by read_object are built, the first 64 KiB of each.
  static constexpr std::size_t kValueBuffer = std::size_t(64) << 10;
  std::unique_ptr<unsigned char[]> value_buffer = std::make_unique_for_overwrite<unsigned char[]>(kValueBuffer);
  // The duplicate keys of the elements (the parser leaves them to us: StrictParser::
  // record_elements), at most max_duplicates, each with its element's index.
  std::size_t max_duplicates;
  util::Errors duplicates;
  std::vector<std::size_t> duplicate_elements;

  // Element `i`, recorded by the parser from `from` to `to` in `log`: a sphere of the common shape
  // is read from the events (detail::read_plain_sphere: it has no duplicate key); any other
  // element, or a sphere with a problem, is built into a value, checked for duplicate keys and
  // read by read_object, which reports its problems.
  void read(std::size_t i, const jsonio::EventLog& log, jsonio::EventLog::Mark from, jsonio::EventLog::Mark to) {
    if (i < kMaxObjects) {
      if (std::optional<Object> sphere = detail::read_plain_sphere(log, from, to)) {
        ++count;
        keep(i, std::move(sphere));
        return;
      }
    }
    if (i >= kMaxObjects) {
      add_duplicates(i, log, from, to);
      ++count;
      return;  // one error at the end, as for a document
    }
    // A fresh arena for each value (Boost 1.81's release() would keep its grown block size).
    json::monotonic_resource arena(value_buffer.get(), kValueBuffer);
    std::size_t keys = 0;
    const json::value v = log.build(from, to, &arena, &keys);
    // The value keeps one of duplicate keys: counting its keys is cheaper than looking for
    // duplicates in the events (200k boxes: that took the reader thread 20-25 % longer).
    if (key_count(v) != keys) add_duplicates(i, log, from, to);
    read(i, v);
  }

  void read(std::size_t i, const json::value& v) {
    ++count;
    if (i >= kMaxObjects) return;  // one error at the end, as for a document
    const Path root;
    const Path at = root.key("scene_objects");
    s.index = static_cast<std::uint32_t>(i);
    keep(i, detail::read_object(s, v, at.index(i)));
  }

  void add_duplicates(std::size_t i, const jsonio::EventLog& log, jsonio::EventLog::Mark from,
                      jsonio::EventLog::Mark to) {
    if (duplicates.size() >= max_duplicates) return;
    if (log.duplicate_keys(from, to, element_path(i), max_duplicates, duplicates)) {
      duplicate_elements.resize(duplicates.size(), i);
    }
  }
  static std::string element_path(std::size_t i) { return fmt::format("/scene_objects/{}", i); }

  // The end of reading element `i`: `element` read (nullopt: it had problems, reported).
  void keep(std::size_t i, std::optional<Object> element) {
    if (s.r.failed()) {
      std::vector<Object>().swap(objects);  // the scene will not load: keep no memory for it
    } else if (element) {
      if (kept == room) grow();
      ++kept;
      if (sink != nullptr) {
        sink->add(i, *element);
      } else {
        objects.push_back(std::move(*element));
      }
    }
  }

  // Room for every object the text predicts: one allocation where doubling made ~20 (each
  // copying all the objects so far, and with old and new arrays alive at once, peaking at 1.5x).
  // The prediction over-counts (the objects so far are counted against the bytes before the
  // current piece, not those parsed), and pages of the array never written cost no memory.
  void grow() {
    constexpr std::uint64_t kMinSample = 8ull << 20;  // bytes: the piece's lag is then <= 1/8
    std::size_t want = std::max<std::size_t>(16, 2 * room);
    if (total_bytes > 0 && bytes_before_piece >= kMinSample) {
      const double per_byte = double(kept) / double(bytes_before_piece);
      const double predicted = per_byte * double(total_bytes) * 1.02 + 1024;
      want = std::max(kept + 1, std::size_t(std::min(predicted, double(kMaxObjects))));
      if (want <= kept) want = 2 * room;  // more than predicted after all
    }
    room = std::min(want, kMaxObjects);
    if (sink != nullptr) {
      sink->reserve(room);
      return;
    }
    objects.reserve(room);
    util::advise_huge_pages_for(objects);  // first touches are costly page faults (util/huge_pages.h)
  }
};

std::optional<SceneDesc> read_scene(SceneReader& s, const json::value& root_value, StreamedObjects* streamed) {
  const Path root;
  const json::object* root_obj = s.r.object(root_value, root);
  if (root_obj == nullptr) return std::nullopt;
  jsonio::Fields f(s.r, *root_obj, root, kTopKeys, kKeyAliases);

  SceneDesc scene;
  if (const json::value* v = f.get("camera", Need::kRequired)) read_camera(s, *v, f.path("camera"), scene.camera);
  if (const json::value* v = f.get("render", Need::kOptional)) read_render(s, *v, f.path("render"), scene.render);
  if (streamed != nullptr) {
    // The document holds an empty array under the key; the elements were read already.
    f.get("scene_objects", Need::kRequired);
    const Path at = f.path("scene_objects");
    s.r.absorb(streamed->s.r);
    if (streamed->count > kMaxObjects) {
      s.r.error(at, fmt::format("too many {}: {} (limit {})", "objects", streamed->count, kMaxObjects));
    }
    for (util::Error& w : streamed->s.warnings) s.warnings.push_back(std::move(w));
    for (Track& t : streamed->s.animation.tracks) s.animation.tracks.push_back(std::move(t));
    s.triangles += streamed->s.triangles;
    scene.objects = std::move(streamed->objects);
    if (streamed->count == 0) s.warning(at, "the scene has no objects: it renders as the background only");
  } else {
    read_list(s, f, "scene_objects", kMaxObjects, "objects", scene.objects, detail::read_object,
              "the scene has no objects: it renders as the background only");
  }
  read_list(s, f, "scene_lights", kMaxLights, "lights", scene.lights, detail::read_light,
            "the scene has no lights: only reflections of the background will show");
  if (s.r.failed()) return std::nullopt;
  if (ObjectSink* sink = s.options.object_sink; sink != nullptr && !scene.objects.empty()) {
    // Read from the document (not streamed): handed over now, the same objects in the same order.
    sink->reserve(scene.objects.size());
    for (std::size_t i = 0; i < scene.objects.size(); ++i) sink->add(i, scene.objects[i]);
    std::vector<Object>().swap(scene.objects);
  }
  if (!s.animation.tracks.empty()) {
    sort_tracks(s.animation);
    scene.animation = std::make_shared<const Animation>(std::move(s.animation));
    check_camera_times(s, scene);
    if (s.r.failed()) return std::nullopt;
  }
  return scene;
}

}  // namespace

std::string format_errors(const util::Errors& errors) {
  std::string out;
  for (const util::Error& e : errors) {
    out += e.to_string();
    out += '\n';
  }
  return out;
}

namespace {

// Bytes per read of a scene file. A piece is copied from the page cache and then parsed while it
// is still in the core's cache: 256 KiB pieces took the parser thread about 3 % less CPU than
// 1 MiB ones (1M spheres, 20 alternated pairs; 128 KiB gained nothing more).
// Mapping the file instead (8 MiB windows, MAP_POPULATE, parsed in place) lost: the parser thread
// then takes the cache misses that read()'s copy took, on its first touch of the text, plus the
// mapping's page-table work (CPU 1.15x over 8 alternated pairs, and the window adds 7 MiB RSS).
constexpr std::size_t kReadPiece = std::size_t(1) << 18;

// The objects' half of a load, on a thread of its own for a large text: the parser (the calling
// thread) records the events of each element of "scene_objects" in the log of a batch (no value
// is built), and the reader thread turns whole batches into objects, in order, while the parser
// reads on; the reader thread also converts the doubles, so the two threads share the work. Every
// object is read by the one StreamedObjects::read, in file order, so the objects, errors, warnings
// and tracks are the same as reading them inline, which is what a small text does
// (LoadOptions::parallel_min_bytes).
class ObjectPipeline {
 public:
  // Declared before the parser, so that the logs outlive its use of them.
  explicit ObjectPipeline(StreamedObjects& streamed) : streamed_(streamed) {}
  // The elements of "scene_objects" go from `parser` to the pipeline; `threaded`: they are
  // recorded in batches and read on a thread of the pipeline's own.
  void attach(jsonio::StrictParser& parser, bool threaded) {
    parser_ = &parser;
    parser.record_elements(
        "scene_objects", &inline_log_,
        [this](std::size_t i, const jsonio::EventLog& log, jsonio::EventLog::Mark begin) { element(i, log, begin); });
    if (!threaded) return;
    for (auto& b : batches_) free_.push_back(b.get());
    start_batch();
    reader_ = std::thread([this] { run(); });
  }
  ~ObjectPipeline() { stop_reader(); }
  ObjectPipeline(const ObjectPipeline&) = delete;
  ObjectPipeline& operator=(const ObjectPipeline&) = delete;

  // Parser thread: one element, from `begin` to the end of `log` (the filling batch's when
  // threaded).
  void element(std::size_t i, const jsonio::EventLog& log, jsonio::EventLog::Mark begin) {
    if (!reader_.joinable()) {
      streamed_.read(i, log, begin, log.mark());
      reuse(inline_log_);
      return;
    }
    if (filling_->spans.empty()) filling_->first = i;
    filling_->spans.push_back({begin, log.mark()});
    filling_->bytes_before_piece.push_back(bytes_before_piece_);
    if (filling_->spans.size() == kBatchElements) {
      submit();
      start_batch();
    }
  }
  // Parser thread: the log the parser writes the next events to.
  const jsonio::EventLog& log_being_written() const { return reader_.joinable() ? filling_->log : inline_log_; }
  // Parser thread: the bytes before the piece being parsed now (StreamedObjects::grow).
  void bytes_before_piece(std::uint64_t bytes) {
    if (!reader_.joinable()) streamed_.bytes_before_piece = bytes;
    bytes_before_piece_ = bytes;
  }
  // Parser thread: every element has been given; returns once all are read, and throws here what
  // reading them threw on the reader thread (std::bad_alloc), as reading inline would have.
  void finish() {
    stop_reader();
    if (error_) std::rethrow_exception(std::exchange(error_, nullptr));
  }

 private:
  void stop_reader() {
    if (!reader_.joinable()) return;
    if (!filling_->spans.empty()) {
      submit();
    } else {
      std::lock_guard lock(mutex_);
      free_.push_back(filling_);  // unused
    }
    filling_ = nullptr;
    {
      std::lock_guard lock(mutex_);
      done_ = true;
    }
    ready_cv_.notify_one();
    reader_.join();
  }

  // A log is kept for the next elements, its memory too, unless an element (an inline mesh) made
  // it large: that memory is returned rather than held to the end of the load.
  static void reuse(jsonio::EventLog& log) {
    constexpr std::size_t kKeepTextBytes = std::size_t(16) << 20;  // 2048 spheres: about 0.5 MiB
    if (log.mark().text > kKeepTextBytes) {
      log = jsonio::EventLog(log.converts_doubles());
    } else {
      log.clear();
    }
  }

  static constexpr std::size_t kBatchElements = 2048;
  static constexpr std::size_t kBatches = 3;  // one filling, one being read, one spare
  // A batch's log keeps its memory batch after batch (its pages stay mapped).
  struct Batch {
    jsonio::EventLog log;
    // Where each element starts and ends in `log` (after a syntax error, the log goes on with
    // the events of an element never completed).
    std::vector<std::pair<jsonio::EventLog::Mark, jsonio::EventLog::Mark>> spans;
    std::size_t first = 0;                          // index of the first element in "scene_objects"
    std::vector<std::uint64_t> bytes_before_piece;  // per element, when it was parsed
  };

  // The next elements are recorded in a free batch's log (waiting for the reader to free one).
  void start_batch() {
    std::unique_lock lock(mutex_);
    free_cv_.wait(lock, [this] { return !free_.empty(); });
    filling_ = free_.back();
    free_.pop_back();
    parser_->set_event_log(&filling_->log);
  }
  void submit() {
    {
      std::lock_guard lock(mutex_);
      ready_.push_back(filling_);
    }
    ready_cv_.notify_one();
  }
  // Reader thread.
  void run() {
    for (;;) {
      Batch* b = nullptr;
      {
        std::unique_lock lock(mutex_);
        ready_cv_.wait(lock, [this] { return !ready_.empty() || done_; });
        if (ready_.empty()) return;  // done, and every batch read
        b = ready_.front();
        ready_.pop_front();
      }
      // After a throw the remaining batches are only released, so that the parser never waits
      // for a free batch that does not come; finish() throws the error on the parser thread.
      if (!error_) {
        try {
          for (std::size_t k = 0; k < b->spans.size(); ++k) {
            streamed_.bytes_before_piece = b->bytes_before_piece[k];
            streamed_.read(b->first + k, b->log, b->spans[k].first, b->spans[k].second);
          }
        } catch (...) {
          error_ = std::current_exception();
        }
      }
      reuse(b->log);
      b->spans.clear();
      b->bytes_before_piece.clear();
      {
        std::lock_guard lock(mutex_);
        free_.push_back(b);
      }
      free_cv_.notify_one();
    }
  }

  StreamedObjects& streamed_;  // touched only by the reader thread while it runs
  jsonio::StrictParser* parser_ = nullptr;
  // Not threaded: one element at a time, its doubles converted by the parser (there is no other
  // thread to leave them to).
  jsonio::EventLog inline_log_{/* convert_doubles = */ true};
  std::array<std::unique_ptr<Batch>, kBatches> batches_ = {std::make_unique<Batch>(), std::make_unique<Batch>(),
                                                           std::make_unique<Batch>()};
  Batch* filling_ = nullptr;  // parser thread
  std::uint64_t bytes_before_piece_ = 0;
  std::mutex mutex_;  // guards free_, ready_, done_
  std::condition_variable free_cv_, ready_cv_;
  std::vector<Batch*> free_;
  std::deque<Batch*> ready_;
  bool done_ = false;
  std::exception_ptr error_;  // written by the reader thread, read after it is joined
  std::thread reader_;
};

// The parser a feed writes to, counting the bytes for StreamedObjects::grow.
struct Feeder {
  jsonio::StrictParser& parser;
  ObjectPipeline& pipeline;
  std::uint64_t bytes = 0;
  bool write(std::string_view piece) {
    pipeline.bytes_before_piece(bytes);
    bytes += piece.size();
    return parser.write(piece);
  }
};

// Parses the text that `feed` writes into the parser (returning an error that ends the load, e.g.
// an unreadable file) and reads the scene from it, the objects as they are parsed.
template <typename Feed>
LoadResult load_streaming(const std::string& file_name, const LoadOptions& options, std::uint64_t total_bytes,
                          Feed feed) {
  SceneReader s(file_name, options);
  StreamedObjects streamed(file_name, options);
  streamed.total_bytes = total_bytes;
  std::optional<SceneDesc> scene;
  {
    // The parsed tree (everything but the objects) lives only for this block. Duplicate keys do
    // not stop validation: the rest of the file still gets checked. One place is kept for the
    // syntax error, which matters more than any duplicate key before it.
    json::monotonic_resource arena;
    ObjectPipeline pipeline(streamed);
    jsonio::StrictParser parser(kMaxJsonDepth, max_parse_errors(options), &arena);
    pipeline.attach(parser, total_bytes >= options.parallel_min_bytes);
    Feeder feeder{parser, pipeline};
    if (std::optional<util::Error> failed = feed(feeder)) {
      LoadResult result;
      result.errors.push_back(std::move(*failed));
      return result;
    }
    jsonio::Document doc = parser.finish();
    // The duplicate keys of an element a syntax error cut short, from its log before the reader
    // thread is given that log.
    util::Errors cut_short;
    std::size_t cut_index = 0;
    if (const auto open = parser.open_element()) {
      const jsonio::EventLog& log = pipeline.log_being_written();
      cut_index = open->second;
      log.duplicate_keys(open->first, log.mark(), StreamedObjects::element_path(cut_index), max_parse_errors(options),
                         cut_short);
    }
    pipeline.finish();  // every object read before the document is
    // The parser's duplicate keys and the elements', in document order (the parser's own in the
    // gaps between elements: StrictParser::error_elements), at most as many as the parser keeps;
    // then the syntax error.
    streamed.duplicate_elements.resize(streamed.duplicate_elements.size() + cut_short.size(), cut_index);
    std::move(cut_short.begin(), cut_short.end(), std::back_inserter(streamed.duplicates));
    const std::vector<std::size_t>& outside = parser.error_elements();
    std::size_t reported = 0, k = 0, j = 0;
    const auto report = [&](util::Error& e) {
      if (reported++ < max_parse_errors(options)) s.r.error(std::move(e.path), std::move(e.message));
    };
    while (k < outside.size() || j < streamed.duplicates.size()) {
      if (j == streamed.duplicates.size() || (k < outside.size() && outside[k] <= streamed.duplicate_elements[j])) {
        report(doc.errors[k++]);
      } else {
        report(streamed.duplicates[j++]);
      }
    }
    for (; k < doc.errors.size(); ++k) s.r.error(std::move(doc.errors[k].path), std::move(doc.errors[k].message));
    // After a syntax error only that error is reported, as when the document is read whole.
    if (doc.parsed) scene = read_scene(s, doc.value, parser.split_seen() ? &streamed : nullptr);
  }
  LoadResult result;
  if (!s.r.failed()) result.scene = std::move(scene);
  result.errors = s.r.take_errors();
  result.warnings = std::move(s.warnings);
  return result;
}

}  // namespace

LoadResult load_scene_string(std::string_view text, const std::string& file_name, const LoadOptions& options) {
  if (text.size() > options.max_bytes) {
    LoadResult result;
    result.errors.push_back(
        {fmt::format("{} is {} bytes, larger than the limit of {} bytes", "scene", text.size(), options.max_bytes), "",
         file_name});
    return result;
  }
  return load_streaming(file_name, options, text.size(), [text](Feeder& feeder) -> std::optional<util::Error> {
    // In pieces, as a file is read: StreamedObjects::grow predicts the count from the first ones.
    for (std::size_t at = 0; at < text.size(); at += kReadPiece) {
      if (!feeder.write(text.substr(at, kReadPiece))) break;  // finish() reports it
    }
    return std::nullopt;
  });
}

LoadResult load_scene_file(const std::string& path, const LoadOptions& options) {
  // Mesh files are named relative to the scene file, wherever the process runs from.
  LoadOptions with_base = options;
  with_base.base_dir = std::filesystem::path(path).parent_path().string();
  // Only a regular file: a directory opens and then fails to read, and a pipe or a device could
  // block the load for ever.
  std::error_code status_error;
  const std::filesystem::file_status status = std::filesystem::status(path, status_error);
  if (!status_error && std::filesystem::exists(status) && !std::filesystem::is_regular_file(status)) {
    LoadResult result;
    result.errors.push_back({std::filesystem::is_directory(status)
                                 ? std::string("is a directory, not a scene file")
                                 : std::string("is not a regular file (a pipe, socket or device?)"),
                             "", path});
    return result;
  }
  // Read and parsed a piece at a time: a 10M-sphere file is 3 GB, and its text is never held.
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    LoadResult result;
    result.errors.push_back({fmt::format("cannot open: {}", std::strerror(errno)), "", path});
    return result;
  }
  std::error_code size_error;
  const std::uintmax_t size = std::filesystem::file_size(path, size_error);  // a hint only
  return load_streaming(
      path, with_base, size_error ? 0 : std::uint64_t(size), [&](Feeder& feeder) -> std::optional<util::Error> {
        std::vector<char> buffer(kReadPiece);
        std::uint64_t total = 0;
        while (in) {
          in.read(buffer.data(), std::streamsize(buffer.size()));
          const auto got = static_cast<std::size_t>(in.gcount());
          total += got;
          if (total > options.max_bytes) {
            return util::Error(fmt::format("file is larger than the limit of {} bytes", options.max_bytes), "", path);
          }
          if (got > 0 && !feeder.write(std::string_view(buffer.data(), got))) break;  // finish() reports it
        }
        if (in.bad()) return util::Error(fmt::format("read error after {} bytes", total), "", path);
        return std::nullopt;
      });
}

}  // namespace dtraced::scene
