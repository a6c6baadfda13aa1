#pragma once
// Small PNG plots for the report (OpenCV drawing): line/points with error bars, false-colour map.
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::compare {

struct Series {
  std::vector<double> x, y, yerr;
  bool points = false;  ///< markers with error bars instead of a line
};

/// Writes a simple x-y plot with axes, tick labels and a title.
void WritePlot(const std::string& path, const std::vector<Series>& series, const std::string& title,
               const std::string& xlabel, const std::string& ylabel);

/// Writes an image as a false-colour (viridis) PNG, scaled to its maximum, upsampled by `zoom`.
void WriteFalseColour(const std::string& path, const Image& img, int zoom);

/// The same mapped linearly from [lo, hi] (values outside clamp to the ends).
void WriteFalseColour(const std::string& path, const Image& img, double lo, double hi, int zoom);

/// A diverging map for signed data (e.g. residuals in standard deviations): -limit blue,
/// 0 white, +limit red, clamped; upsampled by `zoom`.
void WriteDivergingMap(const std::string& path, const Image& img, double limit, int zoom);

}  // namespace raymatch::compare
