#pragma once
// A light field's angular map for tests, as `raymatch calibrate lightfield` writes one through
// an objective: n x n cells over direction cosines (u, v) in [-extent, extent] (u along +x,
// v along +y, rows from the top), value(u, v) inside the cut at `na` and 0 beyond it.
#include <cmath>

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

}  // namespace raymatch::testing
