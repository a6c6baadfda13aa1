#pragma once
// A camera's read-out: photoelectrons -> code values (DN), as a raw frame stores them.
#include <cstddef>
#include <cstdint>

#include "raymatch/core/image.h"

namespace raymatch {

/// The read-out chain of a scientific camera (EMVA 1288's linear model): photoelectrons are
/// clipped at the full well, Gaussian read noise is added, the result is divided by the gain,
/// offset by the dark level, rounded and clipped to the converter's range [0, 2^bits - 1].
/// Detected photons are taken as photoelectrons (quantum efficiency 1: the simulated counts are
/// already the detected photons).
struct CameraReadout {
  double gain_e_per_dn = 1;    ///< electrons per code value
  double dark_dn = 0;          ///< offset (dark level) in code values
  double read_noise_e = 0;     ///< rms read noise, electrons
  double well_capacity_e = 0;  ///< full-well capacity, electrons (0: no limit)
  int bit_depth = 16;          ///< converter bits: code values 0 .. 2^bits - 1
  double max_code() const { return double((uint64_t(1) << bit_depth) - 1); }
};

/// What a read-out did to a frame: pixels that reached the full well or the top code value
/// (saturated), and pixels at code value 0 (where anything below zero was clipped: a fit must
/// leave both kinds out).
struct ReadoutCounts {
  size_t saturated = 0;
  size_t clipped_low = 0;
};

/// Code values of a frame of photoelectron counts. The read noise of pixel i is drawn from the
/// counter-based stream (seed, stream, i), so the frame does not depend on thread counts.
Image ToCodeValues(const Image& electrons, const CameraReadout& camera, uint64_t seed,
                   uint32_t stream, ReadoutCounts* counts = nullptr);

}  // namespace raymatch
