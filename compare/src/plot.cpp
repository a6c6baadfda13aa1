#include "raymatch/compare/plot.h"

#include <algorithm>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "bgr_png.h"
#include "raymatch/core/image_io.h"

namespace raymatch::compare {

namespace {

/// A tick label with enough significant digits to tell ticks `step` apart (22.95, 23, 23.05
/// rather than 23, 23, 23).
std::string Num(double v, double step) {
  int digits = 3;
  if (step > 0 && v != 0)
    digits = std::clamp(int(std::ceil(std::log10(std::abs(v) / step))) + 2, 3, 10);
  std::ostringstream os;
  os.precision(digits);
  os << v;
  return os.str();
}

}  // namespace

void WritePlot(const std::string& path, const std::vector<Series>& series, const std::string& title,
               const std::string& xlabel, const std::string& ylabel) {
  const int W = 560, H = 360, l = 70, r = 20, t = 36, b = 50;
  cv::Mat m(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
  double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
  for (const Series& s : series)
    for (size_t i = 0; i < s.x.size(); ++i) {
      const double e = s.yerr.empty() ? 0 : s.yerr[i];
      x0 = std::min(x0, s.x[i]), x1 = std::max(x1, s.x[i]);
      y0 = std::min(y0, s.y[i] - e), y1 = std::max(y1, s.y[i] + e);
    }
  if (!(x1 > x0)) x1 = x0 + 1;
  if (!(y1 > y0)) y1 = y0 + 1;
  const double pad = 0.05 * (y1 - y0);
  y0 -= pad, y1 += pad;
  auto X = [&](double x) { return int(l + (x - x0) / (x1 - x0) * (W - l - r)); };
  auto Y = [&](double y) { return int(H - b - (y - y0) / (y1 - y0) * (H - t - b)); };
  cv::rectangle(m, cv::Point(l, t), cv::Point(W - r, H - b), cv::Scalar(0, 0, 0), 1);
  for (int k = 0; k <= 4; ++k) {
    const double xv = x0 + k * (x1 - x0) / 4, yv = y0 + k * (y1 - y0) / 4;
    cv::putText(m, Num(xv, (x1 - x0) / 4), cv::Point(X(xv) - 12, H - b + 18), cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0));
    cv::putText(m, Num(yv, (y1 - y0) / 4), cv::Point(4, Y(yv) + 4), cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(0, 0, 0));
    cv::line(m, cv::Point(l, Y(yv)), cv::Point(W - r, Y(yv)), cv::Scalar(225, 225, 225), 1);
  }
  const cv::Scalar colours[] = {cv::Scalar(180, 90, 30), cv::Scalar(40, 40, 200), cv::Scalar(40, 150, 40)};
  for (size_t si = 0; si < series.size(); ++si) {
    const Series& s = series[si];
    const cv::Scalar c = colours[si % 3];
    for (size_t i = 0; i < s.x.size(); ++i) {
      if (s.points) {
        cv::circle(m, cv::Point(X(s.x[i]), Y(s.y[i])), 4, c, cv::FILLED);
        if (!s.yerr.empty())
          cv::line(m, cv::Point(X(s.x[i]), Y(s.y[i] - s.yerr[i])), cv::Point(X(s.x[i]), Y(s.y[i] + s.yerr[i])), c, 2);
      } else if (i > 0) {
        cv::line(m, cv::Point(X(s.x[i - 1]), Y(s.y[i - 1])), cv::Point(X(s.x[i]), Y(s.y[i])), c, 2);
      }
    }
  }
  cv::putText(m, title, cv::Point(l, 22), cv::FONT_HERSHEY_SIMPLEX, 0.55, cv::Scalar(0, 0, 0), 1);
  cv::putText(m, xlabel, cv::Point(W / 2 - 40, H - 12), cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0));
  cv::putText(m, ylabel, cv::Point(4, t - 8), cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0));
  WriteBgrPng(path, m);
}

void WriteFalseColour(const std::string& path, const Image& img, int zoom) {
  double mx = 0;
  for (float v : img.pixels) mx = std::max(mx, double(v));
  WriteFalseColour(path, img, 0.0, mx, zoom);
}

void WriteFalseColour(const std::string& path, const Image& img, double lo, double hi, int zoom) {
  cv::Mat g(img.height, img.width, CV_8U);
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x)
      g.at<uchar>(y, x) =
          cv::saturate_cast<uchar>(hi > lo ? (img.at(x, y) - lo) / (hi - lo) * 255 : 0);
  cv::Mat c, big;
  cv::applyColorMap(g, c, cv::COLORMAP_VIRIDIS);
  cv::resize(c, big, cv::Size(img.width * zoom, img.height * zoom), 0, 0, cv::INTER_NEAREST);
  WriteBgrPng(path, big);
}

void WriteDivergingMap(const std::string& path, const Image& img, double limit, int zoom) {
  cv::Mat c(img.height, img.width, CV_8UC3);
  for (int y = 0; y < img.height; ++y)
    for (int x = 0; x < img.width; ++x) {
      const double v = limit > 0 ? std::clamp(img.at(x, y) / limit, -1.0, 1.0) : 0.0;
      const double a = 1 - std::abs(v);  // white at 0, full colour at the limit
      // BGR: positive towards red (180, 30, 30 in RGB), negative towards blue (30, 70, 180).
      const cv::Vec3d end = v >= 0 ? cv::Vec3d(30, 30, 180) : cv::Vec3d(180, 70, 30);
      const cv::Vec3d px = end + (cv::Vec3d(255, 255, 255) - end) * a;
      c.at<cv::Vec3b>(y, x) = cv::Vec3b(cv::saturate_cast<uchar>(px[0]),
                                        cv::saturate_cast<uchar>(px[1]),
                                        cv::saturate_cast<uchar>(px[2]));
    }
  cv::Mat big;
  cv::resize(c, big, cv::Size(img.width * zoom, img.height * zoom), 0, 0, cv::INTER_NEAREST);
  WriteBgrPng(path, big);
}

}  // namespace raymatch::compare
