#pragma once
// The camera model: electrons -> code values (gain, black level, read noise, well capacity,
// bit depth, quantisation). Used by the simulated camera; deterministic per seed and stream.
#include <cstdint>

#include "raymatch/core/image.h"

namespace raymatch::capture {

struct SensorModel {
  int bit_depth = 12;             ///< code values 0 .. 2^bit_depth - 1
  double gain_e_per_dn = 1;       ///< electrons per code value at analogue gain 1
  double black_level_dn = 64;     ///< offset added to every pixel, code values
  double read_noise_e = 6;        ///< Gaussian read noise, electrons (rms)
  double well_capacity_e = 4500;  ///< electrons a pixel holds; more are lost (clipped)
  /// Throws Error naming the field when a value is impossible.
  void Validate() const;
  double max_dn() const { return double((int64_t(1) << bit_depth) - 1); }
};

/// Photo-electrons per pixel (e.g. ray hits, already Poisson) -> code values:
///   dn = clamp(round((min(e, well) + read_noise N(0,1)) x gain / gain_e_per_dn + black), 0, max)
/// with N(0,1) from the counter-based RNG stream (seed, stream, pixel index): the same inputs
/// always give the same frame. The chain is core's ToCodeValues (camera_readout.h), which
/// `simulate` and the sample's generator use too.
Image ExposeSensor(const SensorModel& m, const Image& electrons, double analogue_gain,
                   uint64_t seed, uint32_t stream);

}  // namespace raymatch::capture
