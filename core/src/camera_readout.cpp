#include "raymatch/core/camera_readout.h"

#include <algorithm>
#include <cmath>

#include "raymatch/core/rng.h"

namespace raymatch {

Image ToCodeValues(const Image& electrons, const CameraReadout& camera, uint64_t seed,
                   uint32_t stream, ReadoutCounts* counts) {
  Image dn(electrons.width, electrons.height);
  const double top = camera.max_code();
  const double well = camera.well_capacity_e > 0 ? camera.well_capacity_e : HUGE_VAL;
  ReadoutCounts c;
  for (size_t i = 0; i < electrons.size(); ++i) {
    RayRng rng(seed, stream, i);
    // Box-Muller: a standard normal from two uniforms (1 - u keeps the logarithm finite).
    const double u1 = rng.Uniform(), u2 = rng.Uniform();
    const double g = std::sqrt(-2 * std::log(1 - u1)) * std::cos(2 * M_PI * u2);
    const double full = std::max(0.0, double(electrons.pixels[i]));
    const double e = std::min(full, well) + camera.read_noise_e * g;
    const double v = std::round(e / camera.gain_e_per_dn + camera.dark_dn);
    if (full >= well || v >= top) ++c.saturated;
    if (v <= 0) ++c.clipped_low;
    dn.pixels[i] = float(std::clamp(v, 0.0, top));
  }
  if (counts) *counts = c;
  return dn;
}

}  // namespace raymatch
