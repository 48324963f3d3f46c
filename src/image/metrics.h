// dtraced::image error metrics between two images of the same size.
//
// Owns: the numbers golden-image tests and the collector use to decide whether two renders agree.
// Two spaces on purpose:
//   - mse, rmse and max_abs are scene-referred: computed on the linear float values as stored,
//     over every channel of every pixel, unclamped.
//   - rel_mse is scene-referred and relative to b, the reference: the mean of
//     (a - b)^2 / (b^2 + kRelMseEpsilon) over every channel of every pixel, the relative MSE of
//     rendering research (Rousselle et al.; pbrt's error reports), where epsilon keeps black
//     pixels from dominating.
//   - psnr_db is display-referred: each value is taken through the sRGB curve and clamped to
//     [0, 1] first, i.e. it measures the picture a viewer would see from an 8/16-bit file, where
//     differences in the darks weigh more and differences above white vanish. PSNR is
//     10 log10(1 / MSE_display) dB, +infinity when the displayed images are identical (printing
//     "inf" is the caller's job).
// Non-finite values (NaN, infinity) would turn every statistic into NaN, so positions where
// either image holds one are counted in `nonfinite` and left out of the other figures, which
// average over the remaining positions. A comparison that gates on these numbers must also
// require nonfinite == 0.
//
// Thread safety: pure functions of their arguments.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "image/image.h"
#include "util/result.h"

namespace dtraced::image {

inline constexpr double kRelMseEpsilon = 0.01;

struct ImageDiff {
  double mse = 0.0;             // mean squared difference of linear values
  double rmse = 0.0;            // sqrt(mse)
  double rel_mse = 0.0;         // mean (a - b)^2 / (b^2 + kRelMseEpsilon): b is the reference
  double psnr_db = 0.0;         // display-referred (sRGB, clamped), +inf when identical on display
  double max_abs = 0.0;         // largest absolute difference of linear values
  std::uint64_t nonfinite = 0;  // channel values where a or b is NaN or infinite (excluded above)
};

// `b` is the reference for rel_mse; every other figure is symmetric.
// Fails when the sizes differ or an image is inconsistent. Two empty images compare as
// identical.
util::Result<ImageDiff> compare_images(const ImageRGBf& a, const ImageRGBf& b);

// Number of channel values (not pixels) that are NaN or infinite.
std::uint64_t count_nonfinite(const ImageRGBf& img);

}  // namespace dtraced::image
