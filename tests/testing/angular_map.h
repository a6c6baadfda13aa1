#pragma once
// A light field's angular map for tests, as `raymatch calibrate lightfield` writes one through
// an objective: n x n cells over direction cosines (u, v) in [-extent, extent] (u along +x,
// v along +y, rows from the top), value(u, v) inside the cut at `na` and 0 beyond it.
#include <cmath>

#include "raymatch/core/calibration_file.h"
#include "raymatch/core/image.h"

namespace raymatch::testing {

template <class Value>
Image NaCutAngularMap(int n, double extent, double na, Value value) {
  Image map(n, n);
  for (int y = 0; y < n; ++y)
    for (int x = 0; x < n; ++x) {
      const double u = (2 * (x + 0.5) / n - 1) * extent, v = (1 - 2 * (y + 0.5) / n) * extent;
      map.at(x, y) = std::hypot(u, v) < na ? float(value(u, v)) : 0.f;
    }
  return map;
}

/// The sample's optics (objective 10 mm at NA 0.42, tube lens 200 mm, 462 nm) with camera pixels
/// of `pixel_pitch_um` and a 64 x 64 light field value(u, v) over +-0.5, cut at the NA.
template <class Value>
CalibrationData NaCutCalibration(Value value, double pixel_pitch_um) {
  CalibrationData c;
  c.angular_extent = 0.5;
  c.na_limit = 0.42;
  c.angular_map = NaCutAngularMap(64, c.angular_extent, c.na_limit, value);
  c.objective_focal_mm = 10, c.working_distance_mm = 20, c.na = 0.42, c.tube_focal_mm = 200;
  c.pixel_pitch_um = pixel_pitch_um, c.wavelength_um = 0.462;
  return c;
}

}  // namespace raymatch::testing
