// CW-SSIM (Sampat et al., IEEE TIP 18, 2385 (2009)) on a complex steerable pyramid built in
// the frequency domain as Portilla & Simoncelli's buildSCFpyr: log-radial raised-cosine
// high/low-pass masks, one-sided angular masks cos^(K-1) (so bands are analytic/complex), and
// low-pass downsampling by cropping the centred spectrum.
#include <cmath>
#include <complex>
#include <opencv2/core.hpp>

#include "filter.h"
#include "raymatch/compare/measures.h"

namespace raymatch::compare {

namespace {

using cd = std::complex<double>;

struct Spectrum {  // centred (fftshifted) spectrum with its log-radius and angle grids
  int w = 0, h = 0;
  std::vector<cd> v;
  std::vector<double> log_rad, angle;
};

void Require(bool ok, const std::string& m) {
  if (!ok) throw CompareError(FailureKind::kInvalidInput, m);
}

// MATLAB-style centre (1-based ceil((n+0.5)/2)) as a 0-based index: floor(n/2).
int Ctr(int n) { return n / 2; }

std::vector<cd> Fft2Shifted(const Plane& p) {
  cv::Mat m(p.height, p.width, CV_64F, const_cast<double*>(p.v.data())), f;
  cv::dft(m, f, cv::DFT_COMPLEX_OUTPUT);
  std::vector<cd> out(p.v.size());
  for (int y = 0; y < p.height; ++y)
    for (int x = 0; x < p.width; ++x) {
      const cv::Vec2d c = f.at<cv::Vec2d>(y, x);
      const int sy = (y + Ctr(p.height)) % p.height, sx = (x + Ctr(p.width)) % p.width;
      out[size_t(sy) * p.width + sx] = cd(c[0], c[1]);
    }
  return out;
}

std::vector<cd> Ifft2Unshift(const std::vector<cd>& s, int w, int h) {
  cv::Mat f(h, w, CV_64FC2), o;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const int sy = (y + Ctr(h)) % h, sx = (x + Ctr(w)) % w;
      const cd c = s[size_t(sy) * w + sx];
      f.at<cv::Vec2d>(y, x) = cv::Vec2d(c.real(), c.imag());
    }
  cv::dft(f, o, cv::DFT_INVERSE | cv::DFT_SCALE | cv::DFT_COMPLEX_OUTPUT);
  std::vector<cd> out(size_t(w) * h);
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const cv::Vec2d c = o.at<cv::Vec2d>(y, x);
      out[size_t(y) * w + x] = cd(c[0], c[1]);
    }
  return out;
}

// Raised-cosine transition on log2 radius from `lo` to lo + 1: high-pass amplitude
// sqrt((1 - cos(pi t)) / 2) = sin(pi t / 2) and low-pass cos(pi t / 2), t in [0, 1].
double Hi(double x, double lo) { return std::sin(M_PI / 2 * std::clamp(x - lo, 0.0, 1.0)); }
double Lo(double x, double lo) { return std::cos(M_PI / 2 * std::clamp(x - lo, 0.0, 1.0)); }

}  // namespace

void CwSsimOptions::Validate() const {
  Require(data_range > 0 && std::isfinite(data_range), "CW-SSIM: data_range (L) must be > 0");
  Require(level >= 0 && level <= 20, "CW-SSIM: level must be 0 (auto) or 1..20");
  Require(orientations >= 1 && orientations <= 32, "CW-SSIM: orientations must be 1..32");
  Require(guard_band >= 0, "CW-SSIM: guard_band must be >= 0");
  Require(k >= 0, "CW-SSIM: k must be >= 0");
  Require(window >= 1 && window % 2 == 1, "CW-SSIM: window must be odd and >= 1");
}

int MaxCwSsimLevel(int width, int height) {
  return std::max(1, int(std::floor(std::log2(std::min(width, height)))) - 2);
}

CwSsimBands ComputeCwSsimBands(const Image& img, const CwSsimOptions& o, int level) {
  o.Validate();
  Require(level >= 1 && level <= MaxCwSsimLevel(img.width, img.height),
          "CW-SSIM: level " + std::to_string(level) + " exceeds the maximum " +
              std::to_string(MaxCwSsimLevel(img.width, img.height)) + " for this image size");
  const Plane p = ToPlane(img, 255.0 / o.data_range);
  Spectrum s;
  s.w = p.width, s.h = p.height;
  s.v = Fft2Shifted(p);
  s.log_rad.resize(s.v.size());
  s.angle.resize(s.v.size());
  const int cx = Ctr(s.w), cy = Ctr(s.h);
  for (int y = 0; y < s.h; ++y)
    for (int x = 0; x < s.w; ++x) {
      const double xr = (x - cx) / (s.w / 2.0), yr = (y - cy) / (s.h / 2.0);
      double r = std::sqrt(xr * xr + yr * yr);
      if (x == cx && y == cy) r = 1.0 / (s.w / 2.0);  // as buildSCFpyr: the DC takes its neighbour's radius
      s.log_rad[size_t(y) * s.w + x] = std::log2(r);
      s.angle[size_t(y) * s.w + x] = std::atan2(yr, xr);
    }
  // lo0: first low-pass (transition from log2 r = -1 to 0).
  for (size_t i = 0; i < s.v.size(); ++i) s.v[i] *= Lo(s.log_rad[i], -1.0);
  const int K = o.orientations, order = K - 1;
  const double c = std::pow(2.0, 2 * order) * std::pow(std::tgamma(order + 1), 2) /
                   (K * std::tgamma(2 * order + 1));
  const double amp = 2 * std::sqrt(c);
  for (int lev = 1;; ++lev) {
    const double lo = -1.0 - lev;  // this octave's transition
    if (lev == level) {
      CwSsimBands b;
      b.width = s.w, b.height = s.h;
      for (int k = 0; k < K; ++k) {
        std::vector<cd> band(s.v.size());
        const double a0 = M_PI * k / K;
        for (size_t i = 0; i < s.v.size(); ++i) {
          const double t = s.angle[i] - a0;  // one-sided: no wrap-around, as buildSCFpyr's LUT
          const double am = std::abs(t) < M_PI / 2 ? amp * std::pow(std::cos(t), order) : 0.0;
          band[i] = s.v[i] * am * Hi(s.log_rad[i], lo);
        }
        const std::vector<cd> sp = Ifft2Unshift(band, s.w, s.h);
        // Guard band, in full-resolution pixels, scaled to this level.
        const int g = o.guard_band >> (level - 1);
        const int w = s.w - 2 * g, h = s.h - 2 * g;
        Require(w > 0 && h > 0, "CW-SSIM: guard band larger than the band");
        std::vector<double> re(size_t(w) * h), im(size_t(w) * h);
        for (int y = 0; y < h; ++y)
          for (int x = 0; x < w; ++x) {
            const cd v = sp[size_t(y + g) * s.w + x + g];
            re[size_t(y) * w + x] = v.real(), im[size_t(y) * w + x] = v.imag();
          }
        b.re.push_back(std::move(re));
        b.im.push_back(std::move(im));
      }
      b.width -= 2 * (o.guard_band >> (level - 1));
      b.height -= 2 * (o.guard_band >> (level - 1));
      return b;
    }
    // Low-pass and crop the centre: lodims = ceil((dims - 0.5) / 2).
    const int lw = int(std::ceil((s.w - 0.5) / 2)), lh = int(std::ceil((s.h - 0.5) / 2));
    const int x0 = Ctr(s.w) - Ctr(lw), y0 = Ctr(s.h) - Ctr(lh);
    Spectrum n;
    n.w = lw, n.h = lh;
    for (int y = 0; y < lh; ++y)
      for (int x = 0; x < lw; ++x) {
        const size_t i = size_t(y + y0) * s.w + x + x0;
        n.v.push_back(s.v[i] * Lo(s.log_rad[i], lo));
        n.log_rad.push_back(s.log_rad[i]);
        n.angle.push_back(s.angle[i]);
      }
    s = std::move(n);
  }
}

CwSsimResult CwSsimFromBands(const CwSsimBands& a, const CwSsimBands& b, const CwSsimOptions& o,
                             int level, int max_level) {
  if (a.width != b.width || a.height != b.height || a.re.size() != b.re.size())
    throw CompareError(FailureKind::kSizeMismatch, "CW-SSIM: bands of different sizes");
  CwSsimResult r;
  r.level = level;
  r.max_level = max_level;
  const int w = a.width, h = a.height, M = o.window, rad = M / 2;
  // Gaussian weights over the band: fspecial('gaussian', size, rows/4), normalised.
  std::vector<double> gw(size_t(w) * h);
  double gs = 0;
  const double sig = h / 4.0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x)
      gs += gw[size_t(y) * w + x] = std::exp(-(std::pow(x - (w - 1) / 2.0, 2) + std::pow(y - (h - 1) / 2.0, 2)) / (2 * sig * sig));
  // Box-filter sums ('same', zero padding: filter2(ones(M)/M^2, .)).
  auto box = [&](const std::vector<double>& f) {
    std::vector<double> out(f.size(), 0.0);
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        double s = 0;
        for (int dy = -rad; dy <= rad; ++dy)
          for (int dx = -rad; dx <= rad; ++dx) {
            const int yy = y + dy, xx = x + dx;
            if (yy >= 0 && yy < h && xx >= 0 && xx < w) s += f[size_t(yy) * w + xx];
          }
        out[size_t(y) * w + x] = s / (M * M);
      }
    return out;
  };
  double total = 0;
  for (size_t k = 0; k < a.re.size(); ++k) {
    std::vector<double> cr(w * size_t(h)), ci(cr.size()), vv(cr.size());
    for (size_t i = 0; i < cr.size(); ++i) {
      const cd x(a.re[k][i], a.im[k][i]), y(b.re[k][i], b.im[k][i]);
      const cd c = x * std::conj(y);
      cr[i] = c.real(), ci[i] = c.imag(), vv[i] = std::norm(x) + std::norm(y);
    }
    const auto br = box(cr), bi = box(ci), bv = box(vv);
    double s = 0;
    for (size_t i = 0; i < cr.size(); ++i) {
      const double den = bv[i] + o.k;  // both bands zero with k = 0: identical, score 1
      s += gw[i] / gs * (den > 0 ? (2 * std::hypot(br[i], bi[i]) + o.k) / den : 1.0);
    }
    r.per_orientation.push_back(s);
    total += s;
  }
  r.cw_ssim = total / double(a.re.size());
  return r;
}

CwSsimResult CwSsim(const Image& a, const Image& b, const CwSsimOptions& o) {
  o.Validate();
  CheckComparable(a, b, "CW-SSIM");
  const int max_level = MaxCwSsimLevel(a.width, a.height);
  const int level = o.level > 0 ? o.level : std::max(1, max_level - 1);
  return CwSsimFromBands(ComputeCwSsimBands(a, o, level), ComputeCwSsimBands(b, o, level), o,
                         level, max_level);
}

}  // namespace raymatch::compare
