// dtraced::image sequences: the file names of an image sequence, from a printf-like pattern.
//
// Owns: the pattern syntax of output paths ("out/snow-%04d.png": one %d or %0Nd, N in 1..9, with
// "%%" for a literal '%'), the path of each frame, and the refusal of a path that would write two
// frames of a sequence to one file.
//
// Pure functions of their arguments: thread-safe.
#pragma once

#include <cstdint>
#include <string>
#include <string_view>

#include "util/result.h"

namespace dtraced::image {

// A path split around its frame number: prefix + number (zero-padded to `width` digits) + suffix.
// Without a number (has_number false) the path is prefix + suffix. "%%" is already unescaped in
// both parts.
struct SequencePattern {
  std::string prefix, suffix;
  int width = 0;  // 0 for %d (no padding), else N of %0Nd
  bool has_number = false;
  bool operator==(const SequencePattern&) const = default;
};

// Splits `path` around its one %d or %0Nd (N 1..9). "%%" is a literal '%'. A second number, any
// other '%' sequence (%5d, %x, %010d, a lone % at the end) or an empty path is an error naming the
// path and the position.
util::Result<SequencePattern> parse_sequence_pattern(std::string_view path);

// The file of frame `frame`: prefix + decimal frame (at least `width` digits) + suffix; prefix +
// suffix when the pattern has no number. Frames wider than the padding simply print all digits
// ("%02d" gives "100" for frame 100), so distinct frames always give distinct names.
std::string frame_path(const SequencePattern& pattern, std::uint32_t frame);

// Whether `path` can hold a sequence of `count` frames: a valid pattern, a known image extension,
// and, when count > 1, a frame number in the name, unless the format is GIF (one file holds the
// whole animation). Errors name the path (util::Error::file) and the problem.
util::Status check_sequence_path(std::string_view path, std::uint32_t count);

}  // namespace dtraced::image
