#include "filter.h"

#include <algorithm>
#include <cmath>

namespace raymatch::compare {

Plane ToPlane(const Image& img, double scale) {
  Plane p(img.width, img.height);
  for (size_t i = 0; i < img.size(); ++i) p.v[i] = double(img.pixels[i]) * scale;
  return p;
}

Image FromPlane(const Plane& p) {
  Image img(p.width, p.height);
  for (size_t i = 0; i < p.v.size(); ++i) img.pixels[i] = float(p.v[i]);
  return img;
}

std::vector<double> GaussianKernel(double sigma) {
  const int r = int(std::ceil(3 * sigma));
  std::vector<double> k(2 * r + 1);
  double s = 0;
  for (int i = -r; i <= r; ++i) s += k[i + r] = std::exp(-double(i) * i / (2 * sigma * sigma));
  for (double& x : k) x /= s;
  return k;
}

Plane FilterReplicate(const Plane& p, const std::vector<double>& kernel) {
  const int r = int(kernel.size()) / 2;
  const int w = p.width, h = p.height;
  // Rows first into tmp, then columns. Index clamping is replicate padding.
  Plane tmp(w, h), out(w, h);
  std::vector<double> line(size_t(w) + 2 * r);
  for (int y = 0; y < h; ++y) {
    const double* row = &p.v[size_t(y) * w];
    for (int i = 0; i < w + 2 * r; ++i) line[i] = row[std::clamp(i - r, 0, w - 1)];
    double* o = &tmp.v[size_t(y) * w];
    for (int x = 0; x < w; ++x) {
      double s = 0;
      for (size_t t = 0; t < kernel.size(); ++t) s += kernel[t] * line[x + t];
      o[x] = s;
    }
  }
  std::vector<double> acc(w);
  for (int y = 0; y < h; ++y) {
    std::fill(acc.begin(), acc.end(), 0.0);
    for (size_t t = 0; t < kernel.size(); ++t) {
      const int yy = std::clamp(y + int(t) - r, 0, h - 1);
      const double* src = &tmp.v[size_t(yy) * w];
      const double kt = kernel[t];
      for (int x = 0; x < w; ++x) acc[x] += kt * src[x];
    }
    std::copy(acc.begin(), acc.end(), out.v.begin() + size_t(y) * w);
  }
  return out;
}

Plane Downsample2(const Plane& p) {
  const int w = (p.width + 1) / 2, h = (p.height + 1) / 2;
  Plane out(w, h);
  for (int y = 0; y < h; ++y) {
    const int y0 = 2 * y, y1 = std::min(2 * y + 1, p.height - 1);  // replicate: n -> n-1
    for (int x = 0; x < w; ++x) {
      const int x0 = 2 * x, x1 = std::min(2 * x + 1, p.width - 1);
      out.at(x, y) = 0.25 * (p.at(x0, y0) + p.at(x1, y0) + p.at(x0, y1) + p.at(x1, y1));
    }
  }
  return out;
}

}  // namespace raymatch::compare
