#include "collector/output_files.h"

#include <sys/stat.h>

#include <filesystem>

#include <fmt/format.h>

#include "image/gif_io.h"
#include "image/image_io.h"
#include "util/file.h"

namespace dtraced::collector {

util::Result<void, Refusal> check_output_free(std::string_view output, const std::map<JobId, JobRecord>& jobs,
                                              const std::string& output_dir) {
  if (output.empty()) return {};
  for (const auto& [id, job] : jobs) {
    if (job.output != output) continue;
    return Refusal{http::Status::conflict,
                   util::Error(fmt::format("output name \"{}\" is held by job {} ({}); choose another name", output, id,
                                           protocol::to_string(job.state)),
                               "/output"),
                   {}};
  }
  const std::string path = (std::filesystem::path(output_dir) / std::string(output)).string();
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0) {
    return Refusal{
        http::Status::conflict,
        util::Error(fmt::format("output name \"{}\": the file {} exists and is never overwritten; choose another name",
                                output, path),
                    "/output"),
        {}};
  }
  return {};
}

util::Status write_output_file(const std::string& path, const std::string& bytes) {
  util::Result<util::NewFile> written = util::write_file_new(path, bytes);
  if (!written) return written.error();
  if (*written == util::NewFile::kWritten) return {};
  // One byte more than ours, so that a longer file is not taken for ours.
  const util::Result<std::string> there = util::read_file_limited(path, bytes.size() + 1);
  if (there && *there == bytes) return {};
  return util::Error(
      "a different file of this name exists and is kept (images are never overwritten); the job's pixels are "
      "kept too (dtraced fetch): move the file away and the image is written at the next attempt",
      "", path);
}

util::Status write_output_image(const std::string& path, const image::ImageRGBf& img,
                                const image::WriteOptions& options) {
  const std::optional<image::ImageFormat> format = image::format_from_path(path);
  if (!format) return util::Error(fmt::format("unsupported format (use {})", image::extension_list()), "", path);
  util::Result<std::string> bytes = image::encode_image(*format, img, options);
  if (!bytes) return bytes.error();
  return write_output_file(path, *bytes);
}

util::Status write_output_image(const std::string& path, const image::ImageRGBf& img, int png_bit_depth) {
  return write_output_image(path, img, image::WriteOptions{.png_bit_depth = png_bit_depth});
}

bool is_gif_sequence(const JobRecord& job) {
  return job.frames_total > 1 && image::format_from_path(job.output) == image::ImageFormat::kGif;
}

util::Result<std::string> sequence_gif(StoreReader& reader, const GifJob& job) {
  image::GifOptions options;
  options.fps = job.settings.fps;
  options.display = job.settings.display;
  const std::uint32_t width = job.crop ? job.crop->width : job.settings.width;
  const std::uint32_t height = job.crop ? job.crop->height : job.settings.height;
  auto encoder = image::GifEncoder::create(width, height, options);
  if (!encoder) return std::move(encoder).error();
  for (std::uint32_t f = 0; f < job.frames; ++f) {
    auto frame = reader.frame_image(job.id, job.settings, job.tile_size, job.crop, f);
    if (!frame) return std::move(frame).error();
    if (util::Status added = encoder->add_frame(frame->image); !added) return added.error();
  }
  auto bytes = encoder->finish();
  if (!bytes) return std::move(bytes).error();
  return std::string(bytes->begin(), bytes->end());
}

}  // namespace dtraced::collector
