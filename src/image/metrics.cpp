#include "image/metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include <fmt/format.h>

#include "image/image_io.h"

namespace dtraced::image {
namespace {

// What a display shows for a linear value: the sRGB code value, clamped to [0, 1].
double displayed(float linear) { return std::clamp(static_cast<double>(linear_to_srgb(linear)), 0.0, 1.0); }

}  // namespace

util::Result<ImageDiff> compare_images(const ImageRGBf& a, const ImageRGBf& b) {
  if (!a.is_consistent() || !b.is_consistent()) {
    return util::Error("compare: an image is inconsistent (pixel count does not match its size)");
  }
  if (a.width != b.width || a.height != b.height) {
    return util::Error(
        fmt::format("compare: image sizes differ: {}x{} vs {}x{}", a.width, a.height, b.width, b.height));
  }

  ImageDiff diff;
  // Sums in double: a 16384^2 image has 8e8 terms, far beyond what float accumulates faithfully.
  double sum_sq = 0.0, sum_sq_display = 0.0, sum_rel = 0.0;
  std::uint64_t counted = 0;
  for (std::size_t i = 0; i < a.rgb.size(); ++i) {
    const float va = a.rgb[i], vb = b.rgb[i];
    if (!std::isfinite(va) || !std::isfinite(vb)) {
      ++diff.nonfinite;
      continue;
    }
    const double d = static_cast<double>(va) - static_cast<double>(vb);
    sum_sq += d * d;
    sum_rel += d * d / (static_cast<double>(vb) * static_cast<double>(vb) + kRelMseEpsilon);
    diff.max_abs = std::max(diff.max_abs, std::abs(d));
    const double dd = displayed(va) - displayed(vb);
    sum_sq_display += dd * dd;
    ++counted;
  }
  if (counted > 0) {
    diff.mse = sum_sq / static_cast<double>(counted);
    diff.rel_mse = sum_rel / static_cast<double>(counted);
    const double mse_display = sum_sq_display / static_cast<double>(counted);
    diff.psnr_db = mse_display > 0.0 ? 10.0 * std::log10(1.0 / mse_display) : std::numeric_limits<double>::infinity();
  } else {
    diff.psnr_db = std::numeric_limits<double>::infinity();
  }
  diff.rmse = std::sqrt(diff.mse);
  return diff;
}

std::uint64_t count_nonfinite(const ImageRGBf& img) {
  return static_cast<std::uint64_t>(
      std::count_if(img.rgb.begin(), img.rgb.end(), [](float v) { return !std::isfinite(v); }));
}

}  // namespace dtraced::image
