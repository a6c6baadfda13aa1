#pragma once
// Private double-precision planes and the few filters the measures need.
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::compare {

struct Plane {
  int width = 0, height = 0;
  std::vector<double> v;  ///< Row-major.
  Plane() = default;
  Plane(int w, int h, double fill = 0) : width(w), height(h), v(size_t(w) * h, fill) {}
  double& at(int x, int y) { return v[size_t(y) * width + x]; }
  double at(int x, int y) const { return v[size_t(y) * width + x]; }
};

Plane ToPlane(const Image& img, double scale = 1.0);
Image FromPlane(const Plane& p);

/// fspecial('gaussian', [n 1], sigma) with n = 2*ceil(3 sigma)+1, normalised to sum 1.
std::vector<double> GaussianKernel(double sigma);

/// Separable correlation with an odd symmetric kernel, replicate padding, output the size of
/// the input (MATLAB imfilter(..., 'replicate', 'same')).
Plane FilterReplicate(const Plane& p, const std::vector<double>& kernel);

/// multissim's downsampling: the 2x2 mean of each pixel and its right/lower neighbours (the
/// last row/column replicated), keeping every second sample from the first.
Plane Downsample2(const Plane& p);

}  // namespace raymatch::compare
