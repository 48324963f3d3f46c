// dtraced::collector output files: a finished image never replaces another file, and two jobs
// never hold one output name.
//
// Owns: the rule that decides whether a submitted output name is free (no job the collector
// knows holds it, and no file of that name is in the output directory), and the one step that
// writes a finished image: encoded in memory, then written under its name only if that name is
// free (util::write_file_new), so a finished image is never overwritten, by another job or by
// anything else. A file already there with the very same bytes counts as written: a collector
// killed after writing an image and before recording the job done writes it again at restart,
// and renders are deterministic.
//
// Thread safety: pure functions, apart from the file system and the store: check_output_free
// reads the output directory (one stat, on the loop), write_output_image and write_output_file
// write it and sequence_gif reads the store through the StoreReader (on the thread pool).
#pragma once

#include <map>
#include <optional>
#include <string>
#include <string_view>

#include "collector/jobs.h"
#include "collector/refusal.h"
#include "collector/store_reader.h"
#include "image/image.h"
#include "image/image_io.h"
#include "util/result.h"

namespace dtraced::collector {

// 409 (/output) naming the job that holds `output` when a job of `jobs` has it as its effective
// output name (whatever its state: a cancelled job may come back), or naming the file when
// `output_dir`/`output` exists. An empty `output` (the default job-ID.png, unknown before the
// job is stored) is not checked here: write_output_image still never overwrites it.
util::Result<void, Refusal> check_output_free(std::string_view output, const std::map<JobId, JobRecord>& jobs,
                                              const std::string& output_dir);

// Writes `img` to `path` in the format its extension names, never replacing a file. A file of
// that name with other bytes is an error naming the path that says it is kept and how to free
// the name; the caller keeps the pixels (stored tiles) and tries again later.
util::Status write_output_image(const std::string& path, const image::ImageRGBf& img,
                                const image::WriteOptions& options);
util::Status write_output_image(const std::string& path, const image::ImageRGBf& img, int png_bit_depth);
// The same rule for bytes already encoded (a sequence's GIF).
util::Status write_output_file(const std::string& path, const std::string& bytes);

// A job of several frames whose output is a .gif: one file holds the whole sequence, written when
// the last frame is complete; no file per frame.
bool is_gif_sequence(const JobRecord& job);

// What sequence_gif needs of a job (a copy: it runs on the thread pool).
struct GifJob {
  JobId id = 0;
  scene::RenderSettings settings;  // fps and display transform included
  std::uint32_t tile_size = 0;
  std::uint32_t frames = 0;
  std::optional<scene::TileRect> crop{};  // the pixels each frame shows, or whole frames
};
// The animated GIF of a job's frames, assembled from the store one frame at a time (in memory:
// one float frame and the compressed bytes so far).
util::Result<std::string> sequence_gif(StoreReader& reader, const GifJob& job);

}  // namespace dtraced::collector
