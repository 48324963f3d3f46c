// dtraced::image display transform: how linear radiance becomes the picture an 8- or 16-bit
// file shows (PNG, PPM, GIF). PFM and EXR stay linear and ignore it.
//
// Owns: the exposure (in stops) and the tone curve applied before the sRGB encoding, their names
// in scene files, flags and job settings, and their limits.
//
// Plain values and pure functions: thread-safe.
#pragma once

#include <array>
#include <optional>
#include <string_view>

namespace dtraced::image {

// clamp: the linear value clipped to [0, 1] (what every output did before tone curves existed);
// reinhard: x / (1 + x); filmic: a fit of the ACES reference rendering transform (Narkowicz).
enum class ToneCurve { kClamp, kReinhard, kFilmic };
inline constexpr std::array<std::string_view, 3> kToneCurveNames = {"clamp", "reinhard", "filmic"};
inline std::string_view to_string(ToneCurve t) { return kToneCurveNames[static_cast<std::size_t>(t)]; }
inline std::optional<ToneCurve> tone_curve_from_string(std::string_view name) {
  for (std::size_t i = 0; i < kToneCurveNames.size(); ++i) {
    if (kToneCurveNames[i] == name) return static_cast<ToneCurve>(i);
  }
  return std::nullopt;
}

inline constexpr double kMaxExposureStops = 32;  // exposure in [-32, 32]

struct DisplayTransform {
  double exposure = 0;  // stops: the linear value is multiplied by 2^exposure first
  ToneCurve tone = ToneCurve::kClamp;
  bool operator==(const DisplayTransform&) const = default;
  bool is_identity() const { return exposure == 0 && tone == ToneCurve::kClamp; }
};

// The displayed value in [0, 1] of one linear channel value, before the sRGB curve: the value times
// 2^exposure, then the tone curve. clamp: min(max(x, 0), 1); reinhard: x / (1 + x) for x > 0;
// filmic: x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14) clipped to [0, 1] (Narkowicz's ACES fit,
// reaching 1 near x = 7.2). Every curve sends NaN and x <= 0 to 0 and +infinity to 1. The identity
// transform returns exactly what the 8-bit writers clipped to before transforms existed.
float display_value(const DisplayTransform& display, float linear);

}  // namespace dtraced::image
