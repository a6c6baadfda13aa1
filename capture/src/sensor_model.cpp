#include "raymatch/capture/sensor_model.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "raymatch/core/camera_readout.h"
#include "raymatch/core/error.h"

namespace raymatch::capture {

void SensorModel::Validate() const {
  auto bad = [](const std::string& key, double v, const std::string& expected) {
    throw Error("camera model: " + key + " = " + std::to_string(v) + ": expected " + expected);
  };
  if (bit_depth < 1 || bit_depth > 16) bad("bit_depth", bit_depth, "1 to 16");
  if (!(gain_e_per_dn > 0) || !std::isfinite(gain_e_per_dn))
    bad("gain_e_per_dn", gain_e_per_dn, "> 0");
  if (!(black_level_dn >= 0) || black_level_dn > max_dn())
    bad("black_level_dn", black_level_dn, "0 to 2^bit_depth - 1");
  if (!(read_noise_e >= 0) || !std::isfinite(read_noise_e))
    bad("read_noise_e", read_noise_e, ">= 0");
  if (!(well_capacity_e > 0) || !std::isfinite(well_capacity_e))
    bad("well_capacity_e", well_capacity_e, "> 0");
}

Image ExposeSensor(const SensorModel& m, const Image& electrons, double analogue_gain,
                   uint64_t seed, uint32_t stream) {
  // The read-out chain is core's (camera_readout.h); analogue gain divides the electrons per DN.
  CameraReadout c;
  c.gain_e_per_dn = m.gain_e_per_dn / analogue_gain, c.dark_dn = m.black_level_dn;
  c.read_noise_e = m.read_noise_e, c.well_capacity_e = m.well_capacity_e, c.bit_depth = m.bit_depth;
  return ToCodeValues(electrons, c, seed, stream);
}

}  // namespace raymatch::capture
