#include "raymatch/capture/sensor_model.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "raymatch/core/error.h"
#include "raymatch/core/rng.h"

namespace raymatch::capture {

void SensorModel::Validate() const {
  auto bad = [](const std::string& key, double v, const std::string& expected) {
    throw Error("camera model: " + key + " = " + std::to_string(v) + ": expected " + expected);
  };
  if (bit_depth < 1 || bit_depth > 16) bad("bit_depth", bit_depth, "1 to 16");
  if (!(gain_e_per_dn > 0) || !std::isfinite(gain_e_per_dn)) bad("gain_e_per_dn", gain_e_per_dn, "> 0");
  if (!(black_level_dn >= 0) || black_level_dn > max_dn()) bad("black_level_dn", black_level_dn, "0 to 2^bit_depth - 1");
  if (!(read_noise_e >= 0) || !std::isfinite(read_noise_e)) bad("read_noise_e", read_noise_e, ">= 0");
  if (!(well_capacity_e > 0) || !std::isfinite(well_capacity_e)) bad("well_capacity_e", well_capacity_e, "> 0");
}

Image ExposeSensor(const SensorModel& m, const Image& electrons, double analogue_gain,
                   uint64_t seed, uint32_t stream) {
  Image dn(electrons.width, electrons.height);
  const double scale = analogue_gain / m.gain_e_per_dn, top = m.max_dn();
  for (size_t i = 0; i < electrons.size(); ++i) {
    RayRng rng(seed, stream, i);
    // Box-Muller; 1 - U is in (0, 1], so the log is finite.
    const double g = std::sqrt(-2 * std::log(1 - rng.Uniform())) * std::cos(2 * M_PI * rng.Uniform());
    const double e = std::min(double(electrons.pixels[i]), m.well_capacity_e) + m.read_noise_e * g;
    dn.pixels[i] = float(std::clamp(std::round(e * scale + m.black_level_dn), 0.0, top));
  }
  return dn;
}

}  // namespace raymatch::capture
