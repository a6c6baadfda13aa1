#pragma once
// Small PNG plots for the report (OpenCV drawing): line/points with error bars, false-colour map.
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::pipeline {

struct Series {
  std::vector<double> x, y, yerr;
  bool points = false;  ///< markers with error bars instead of a line
};

/// Writes a simple x-y plot with axes, tick labels and a title.
void WritePlot(const std::string& path, const std::vector<Series>& series, const std::string& title,
               const std::string& xlabel, const std::string& ylabel);

/// Writes an image as a false-colour (viridis) PNG, scaled to its maximum, upsampled by `zoom`.
void WriteFalseColour(const std::string& path, const Image& img, int zoom);

}  // namespace raymatch::pipeline
