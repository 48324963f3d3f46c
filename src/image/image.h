// dtraced::image float images.
//
// Owns: ImageRGBf, the in-memory picture every layer exchanges (rendered tiles, assembled frames,
// reference images), and kMaxImageSide, the one bound on image dimensions that readers enforce
// on untrusted input and that sizes the file-read limit in image_io.
//
// Pixels are interleaved linear RGB floats (scene-referred: values above 1 and, for broken
// renders, NaN or infinity may appear), row 0 at the top, x growing to the right.
//
// Thread safety: a plain value type. Concurrent reads are safe; a writer needs exclusive access.
#pragma once

#include <cassert>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace dtraced::image {

// Largest width or height accepted anywhere. 16384^2 RGB floats is already 3 GiB; the bound is
// there so a hostile header cannot make a reader allocate without limit.
inline constexpr std::uint32_t kMaxImageSide = 16384;

struct ImageRGBf {
  std::uint32_t width = 0, height = 0;
  std::vector<float> rgb;  // interleaved linear RGB, width * height * 3 values, row 0 = top

  ImageRGBf() = default;
  // Zero-filled (black). Callers holding untrusted sizes check them against kMaxImageSide first:
  // the assert below is for programming errors and vanishes in release builds.
  ImageRGBf(std::uint32_t w, std::uint32_t h) : width(w), height(h), rgb(std::size_t{w} * h * 3, 0.0f) {
    assert(w <= kMaxImageSide && h <= kMaxImageSide);
  }

  // The three floats of pixel (x, y); x < width, y < height.
  float* pixel(std::uint32_t x, std::uint32_t y) {
    assert(x < width && y < height);
    return rgb.data() + (std::size_t{y} * width + x) * 3;
  }
  const float* pixel(std::uint32_t x, std::uint32_t y) const {
    assert(x < width && y < height);
    return rgb.data() + (std::size_t{y} * width + x) * 3;
  }

  // True when the members agree: both sides within kMaxImageSide and rgb holding exactly
  // width * height * 3 values. The fields are public, so writers and metrics check this rather
  // than trusting whoever filled them in.
  bool is_consistent() const {
    return width <= kMaxImageSide && height <= kMaxImageSide && rgb.size() == std::size_t{width} * height * 3;
  }
};

}  // namespace dtraced::image
