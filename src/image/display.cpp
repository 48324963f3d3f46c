#include "image/display.h"

#include <algorithm>
#include <cmath>

#include "math/det_math.h"

namespace dtraced::image {
namespace {

// Every curve maps x <= 0 and NaN to 0 (the negated tests below catch NaN too), +inf to 1.
double tone(ToneCurve curve, double x) {
  if (!(x > 0.0)) return 0.0;
  switch (curve) {
    case ToneCurve::kClamp:
      return std::min(x, 1.0);
    case ToneCurve::kReinhard:
      return std::isinf(x) ? 1.0 : x / (1.0 + x);
    case ToneCurve::kFilmic: {
      // Narkowicz 2016, "ACES Filmic Tone Mapping Curve". The fit exceeds 1 above x ~ 7.2 (its
      // limit is 2.51 / 2.43); it is monotone on x >= 0, so clipping keeps it monotone.
      if (std::isinf(x)) return 1.0;
      const double y = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14);
      return std::clamp(y, 0.0, 1.0);
    }
  }
  return 0.0;
}

}  // namespace

float display_value(const DisplayTransform& display, float linear) {
  // The identity is exactly the old clip, in float, so existing outputs keep their bytes.
  if (display.is_identity()) return linear > 0.0f ? std::min(linear, 1.0f) : 0.0f;
  const double exposed = static_cast<double>(linear) * math::det::exp2(display.exposure);
  return static_cast<float>(tone(display.tone, exposed));
}

}  // namespace dtraced::image
