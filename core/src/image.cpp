#include "raymatch/core/image.h"

#include <algorithm>

#include "raymatch/core/vec.h"

namespace raymatch {

PixelStats ComputeStats(const Image& img) {
  PixelStats s;
  s.count = img.size();
  if (img.empty()) return s;
  double sum = 0;
  s.min = s.max = img.pixels[0];
  for (float v : img.pixels) {
    sum += v;
    s.min = std::min<double>(s.min, v);
    s.max = std::max<double>(s.max, v);
  }
  s.mean = sum / s.count;
  double ss = 0;
  for (float v : img.pixels) ss += (v - s.mean) * (v - s.mean);
  s.variance = s.count > 1 ? ss / (s.count - 1) : 0;
  return s;
}

Mat3 RotationFromEulerDeg(double ax, double by, double cz) {
  const double d = M_PI / 180;
  const double ca = std::cos(ax * d), sa = std::sin(ax * d), cb = std::cos(by * d),
               sb = std::sin(by * d), cc = std::cos(cz * d), sc = std::sin(cz * d);
  Mat3 r;
  // Rz * Ry * Rx
  r.m[0][0] = cc * cb;
  r.m[0][1] = cc * sb * sa - sc * ca;
  r.m[0][2] = cc * sb * ca + sc * sa;
  r.m[1][0] = sc * cb;
  r.m[1][1] = sc * sb * sa + cc * ca;
  r.m[1][2] = sc * sb * ca - cc * sa;
  r.m[2][0] = -sb;
  r.m[2][1] = cb * sa;
  r.m[2][2] = cb * ca;
  return r;
}

double BorderMedian(const Image& img) {
  std::vector<float> v;
  const int bw = std::max(1, std::min(img.width, img.height) / 8);
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x)
      if (x < bw || y < bw || x >= img.width - bw || y >= img.height - bw)
        v.push_back(img.at(x, y));
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

}  // namespace raymatch
