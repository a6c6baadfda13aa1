#pragma once
// A single-channel float image, row-major, row 0 at the top (as TIFF/PNG store it).
// Pixel (x, y) covers [x, x+1) x [y, y+1) in pixel units; its centre is at (x+0.5, y+0.5).
#include <cstddef>
#include <string>
#include <vector>

namespace raymatch {

struct Image {
  int width = 0;
  int height = 0;
  std::vector<float> pixels;  ///< width*height values, row-major.

  Image() = default;
  Image(int w, int h, float fill = 0.f) : width(w), height(h), pixels(size_t(w) * h, fill) {}
  float& at(int x, int y) { return pixels[size_t(y) * width + x]; }
  float at(int x, int y) const { return pixels[size_t(y) * width + x]; }
  size_t size() const { return pixels.size(); }
  bool empty() const { return pixels.empty(); }
};

/// Mean and (unbiased) variance over all pixels.
struct PixelStats {
  double mean = 0, variance = 0, min = 0, max = 0;
  size_t count = 0;
};
PixelStats ComputeStats(const Image& img);

/// Median of a border frame 1/8 of the smaller side wide (at least 1 pixel): the background
/// level of an image whose object sits in the middle (a whole-image median would be pulled
/// down by the object's dark pixels). 0 for an empty image.
double BorderMedian(const Image& img);

}  // namespace raymatch
