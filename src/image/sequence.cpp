#include "image/sequence.h"

#include <fmt/format.h>

#include "image/image_io.h"

namespace dtraced::image {
namespace {

constexpr std::string_view kPatternHelp = "use one %d or %0Nd (N 1..9) for the frame number, %% for a literal %";

util::Error pattern_error(std::string_view path, std::string message) {
  return util::Error(std::move(message), "", std::string(path));
}

}  // namespace

util::Result<SequencePattern> parse_sequence_pattern(std::string_view path) {
  if (path.empty()) return util::Error(fmt::format("the output path is empty"));
  SequencePattern out;
  std::string* part = &out.prefix;  // where literal characters go: the prefix until the number
  for (std::size_t i = 0; i < path.size(); ++i) {
    if (path[i] != '%') {
      *part += path[i];
      continue;
    }
    const std::size_t start = i;
    if (i + 1 < path.size() && path[i + 1] == '%') {
      *part += '%';
      ++i;
      continue;
    }
    int width = 0;
    std::size_t j = i + 1;
    if (j < path.size() && path[j] == '0') {
      // %0Nd: exactly one digit N in 1..9; anything else after "%0" is malformed (reported below).
      const bool digit = j + 2 < path.size() && path[j + 1] >= '1' && path[j + 1] <= '9' && path[j + 2] == 'd';
      if (digit) width = path[j + 1] - '0';
      j = digit ? j + 2 : path.size();
    }
    if (j >= path.size() || path[j] != 'd') {
      return pattern_error(
          path, fmt::format("'%' at position {} does not start a frame number ({})", start + 1, kPatternHelp));
    }
    if (out.has_number) {
      return pattern_error(
          path, fmt::format("a second frame number at position {} (only one is allowed; {})", start + 1, kPatternHelp));
    }
    out.has_number = true;
    out.width = width;
    part = &out.suffix;
    i = j;
  }
  return out;
}

std::string frame_path(const SequencePattern& pattern, std::uint32_t frame) {
  if (!pattern.has_number) return pattern.prefix + pattern.suffix;
  return fmt::format("{}{:0{}}{}", pattern.prefix, frame, pattern.width, pattern.suffix);
}

util::Status check_sequence_path(std::string_view path, std::uint32_t count) {
  util::Result<SequencePattern> pattern = parse_sequence_pattern(path);
  if (!pattern) return pattern.error();
  const std::string first = frame_path(*pattern, 0);
  const std::optional<ImageFormat> format = format_from_path(first);
  if (!format) {
    return pattern_error(path, fmt::format("unknown image format (supported extensions: {})", extension_list()));
  }
  if (count > 1 && !pattern->has_number && *format != ImageFormat::kGif) {
    return pattern_error(path, fmt::format("{} frames would all be written to this one file; put a frame number "
                                           "in the name (e.g. out-%04d{}) or write a .gif",
                                           count, format_info(*format).extension));
  }
  return {};
}

}  // namespace dtraced::image
