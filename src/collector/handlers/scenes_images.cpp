// GET /v1/scenes/{digest} and GET /v1/jobs/{id}/image: a scene from memory or, off the loop, the store;
// an image from the store, off the loop.
#include <algorithm>
#include <memory>
#include <optional>
#include <string>
#include <utility>

#include <fmt/format.h>

#include "collector/handlers.h"
#include "util/log.h"

namespace dtraced::collector {

async::Awaitable<http::Response> get_scene(Context& c, std::string digest) {
  if (const auto it = c.scenes.find(digest); it != c.scenes.end()) {
    if (std::shared_ptr<const std::string> json = it->second.lock()) co_return json_answer(http::Status::ok, *json);
  }
  // In an optional: on_pool needs a default-constructible result.
  auto fetch = [&reader = c.reader, digest] { return std::optional(reader.scene(digest)); };
  std::optional<util::Result<std::optional<std::string>>> fetched = co_await async::on_pool(c.pool, std::move(fetch));
  if (!fetched->ok()) {
    util::log_error("collector: cannot read scene {}: {}", digest, fetched->error().message);
    co_return respond(busy("the store could not be read; retry later"));
  }
  std::optional<std::string>& json = fetched->value();
  if (!json) co_return http::make_error(http::Status::not_found, fmt::format("no such scene: {}", digest));
  co_return json_answer(http::Status::ok, std::move(*json));
}

async::Awaitable<http::Response> get_job_image(Context& c, JobId id, image::ImageFormat format,
                                               std::optional<std::uint32_t> frame) {
  const JobRecord* job = c.find_job(id);
  if (job == nullptr) co_return respond(job_not_found(id));
  // Without ?frame, a sequence shows the frame being rendered (the last once all are written).
  std::uint32_t frame_index = std::min(job->frames_written, job->frames_total - 1);
  if (frame) {
    const std::optional<std::uint32_t> index = frame_index_of(job->settings, *frame);
    if (!index) {
      co_return http::make_error(
          http::Status::not_found,
          job->frames_total > 1
              ? fmt::format("job {} renders frames {} to {} every {}; not frame {}", id, job->settings.frames->first,
                            job->settings.frames->last, job->settings.frames->step, *frame)
              : fmt::format("job {} renders frame {} only; not frame {}", id, job->settings.frame, *frame));
    }
    frame_index = *index;
  }
  // PNG at the job's bit depth and display transform, as its output files are written.
  const image::WriteOptions options{.png_bit_depth = static_cast<int>(job->png_bit_depth),
                                    .display = job->settings.display};
  // Every frame from the store, black where no tile is stored yet (the collector keeps no
  // framebuffer), read and encoded on the pool.
  auto assemble = [&reader = c.reader, id, settings = job->settings, tile_size = job->tile_size, crop = job->crop,
                   frame_index, options, format] {
    return std::optional(reader.encode_image(id, settings, tile_size, crop, frame_index, options, format));
  };
  // In an optional: on_pool needs a default-constructible result.
  std::optional<util::Result<std::string>> encoded = co_await async::on_pool(c.pool, std::move(assemble));
  // Deleted while its tiles were read: what was read may be incomplete.
  if (c.find_job(id) == nullptr) co_return respond(job_not_found(id));
  if (!encoded->ok()) {
    const std::string why = encoded->error().to_string();
    util::log_error("collector: job {}: cannot produce its image: {}", id, why);
    co_return http::make_error(http::Status::internal_server_error, "cannot produce the image: " + why);
  }
  co_return http::make_binary_response(http::Status::ok, std::move(encoded->value()),
                                       image::format_info(format).content_type);
}

}  // namespace dtraced::collector
