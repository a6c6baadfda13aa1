// CW-SSIM (Sampat et al., IEEE TIP 18, 2385 (2009)) as their cwssim_index.m computes it, on a
// complex steerable pyramid built in the frequency domain as Portilla & Simoncelli's
// buildSCFpyr: log-radial raised-cosine high/low-pass masks, one-sided angular masks
// cos^(K-1) (so bands are analytic/complex), and low-pass downsampling by cropping the centred
// spectrum. The masks are read from the same lookup tables as buildSCFpyr's (256 samples per
// octave radially, 1024 per pi in angle) with pointOp's linear interpolation.
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

// matlabPyrTools' masks are lookup tables read by pointOp: linear interpolation, the index
// truncated toward zero and held inside the table. Using the same tables (rather than the
// closed forms they sample) keeps raymatch within ~1e-10 of cwssim_index instead of ~1e-6.
struct Table {
  std::vector<double> y;
  double origin = 0, increment = 1;
  double operator()(double v) const {
    const double pos = (v - origin) / increment;
    const int index = std::clamp(int(pos), 0, int(y.size()) - 2);
    return y[index] + (y[index + 1] - y[index]) * (pos - index);
  }
};

// rcosFn(1, -1/2, [0 1]) with the square roots buildSCFpyr takes: the high-pass amplitude
// |cos X| (0 at log2 r = -1 rising to 1 at 0) or the low-pass sqrt(1 - cos^2 X), 256
// samples over the octave plus a repeated sample at each end. `octaves_down` shifts the
// transition as buildSCFpyrLevs does at each level.
Table RadialTable(bool high_pass, int octaves_down) {
  constexpr int kSz = 256;
  Table t;
  std::vector<double> x;
  for (int k = -kSz - 1; k <= 1; ++k) {
    const double xk = M_PI * k / (2 * kSz);
    const double yk = std::sqrt(std::pow(std::cos(xk), 2));
    t.y.push_back(high_pass ? yk : std::sqrt(1.0 - yk * yk));
    x.push_back(-0.5 + (2 / M_PI) * (xk + M_PI / 4) - octaves_down);
  }
  t.y.front() = t.y[1];
  t.y.back() = t.y[t.y.size() - 2];
  t.origin = x[0];
  t.increment = x[1] - x[0];
  return t;
}

// buildSCFpyrLevs' angular lobe 2 sqrt(c) cos^order(X), kept where the angle wrapped to
// [-pi, pi) is within pi/2 of the band's direction (one lobe: analytic bands), tabulated at
// pi/1024 over [-2 pi, pi] and read at (angle - pi k / K).
Table AngularTable(int orientations, int k) {
  constexpr int kLut = 1024;
  const int order = orientations - 1;
  const double c = std::pow(2.0, 2 * order) * std::pow(std::tgamma(order + 1), 2) /
                   (orientations * std::tgamma(2 * order + 1));
  Table t;
  for (int i = -(2 * kLut + 1); i <= kLut + 1; ++i) {
    const double x = M_PI * i / kLut;
    const double a = M_PI + x, alfa = a - std::floor(a / (2 * M_PI)) * 2 * M_PI - M_PI;
    t.y.push_back(std::abs(alfa) < M_PI / 2 ? 2 * std::sqrt(c) * std::pow(std::cos(x), order)
                                            : 0.0);
  }
  const double x0 = M_PI * -(2 * kLut + 1) / kLut, x1 = M_PI * -(2 * kLut) / kLut;
  t.origin = x0 + M_PI * k / orientations;
  t.increment = x1 - x0;
  return t;
}

}  // namespace

void CwSsimOptions::Validate() const {
  Require(data_range > 0 && std::isfinite(data_range), "CW-SSIM: data_range (L) must be > 0");
  Require(level >= 0 && level <= 20, "CW-SSIM: level must be 0 (auto) or 1..20");
  Require(orientations >= 1 && orientations <= 16,
          "CW-SSIM: orientations must be 1..16 (buildSCFpyr's order 0..15)");
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
      if (x == cx && y == cy)
        r = 1.0 / (s.w / 2.0);  // as buildSCFpyr: the DC takes its neighbour's radius
      s.log_rad[size_t(y) * s.w + x] = std::log2(r);
      s.angle[size_t(y) * s.w + x] = std::atan2(yr, xr);
    }
  // lo0: first low-pass (transition from log2 r = -1 to 0).
  const Table lo0 = RadialTable(false, 0);
  for (size_t i = 0; i < s.v.size(); ++i) s.v[i] *= lo0(s.log_rad[i]);
  const int K = o.orientations;
  for (int lev = 1;; ++lev) {
    // This level's octave: high-pass for its bands, low-pass before the next crop.
    const Table hi = RadialTable(true, lev), lo = RadialTable(false, lev);
    if (lev == level) {
      CwSsimBands b;
      b.width = s.w, b.height = s.h, b.band_rows = s.h;
      for (int k = 0; k < K; ++k) {
        std::vector<cd> band(s.v.size());
        // The factor (-i)^(K-1) that buildSCFpyrLevs puts on every band is left out: a
        // common unit phase cancels in |sum c1 c2*| and |c|^2.
        const Table angular = AngularTable(K, k);
        for (size_t i = 0; i < s.v.size(); ++i)
          band[i] = s.v[i] * angular(s.angle[i]) * hi(s.log_rad[i]);
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
        n.v.push_back(s.v[i] * lo(s.log_rad[i]));
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
  // cwssim_index: filter2(ones(M)/M^2, ., 'valid'), so the map is (h-M+1) x (w-M+1) and is
  // pooled with fspecial('gaussian', map size, band rows / 4), normalised to sum 1.
  const int M = o.window, w = a.width - M + 1, h = a.height - M + 1;
  if (w < 1 || h < 1) {
    throw CompareError(FailureKind::kInvalidInput,
                       "CW-SSIM: the band at level " + std::to_string(level) + " (" +
                           std::to_string(a.width) + "x" + std::to_string(a.height) +
                           " after the guard band) is smaller than the " + std::to_string(M) + "x" +
                           std::to_string(M) + " window");
  }
  std::vector<double> gw(size_t(w) * h);
  double gs = 0;
  const double sig = a.band_rows / 4.0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      const double dx = x - (w - 1) / 2.0, dy = y - (h - 1) / 2.0;
      gs += gw[size_t(y) * w + x] = std::exp(-(dx * dx + dy * dy) / (2 * sig * sig));
    }
  // Mean over each M x M window lying wholly inside the band (separable running sums).
  auto box = [&](const std::vector<double>& f) {
    std::vector<double> rows(size_t(w) * a.height), out(size_t(w) * h);
    for (int y = 0; y < a.height; ++y)
      for (int x = 0; x < w; ++x) {
        double s = 0;
        for (int d = 0; d < M; ++d) s += f[size_t(y) * a.width + x + d];
        rows[size_t(y) * w + x] = s;
      }
    for (int y = 0; y < h; ++y)
      for (int x = 0; x < w; ++x) {
        double s = 0;
        for (int d = 0; d < M; ++d) s += rows[size_t(y + d) * w + x];
        out[size_t(y) * w + x] = s / (M * M);
      }
    return out;
  };
  double total = 0;
  const size_t n = size_t(a.width) * a.height;
  for (size_t k = 0; k < a.re.size(); ++k) {
    std::vector<double> cr(n), ci(n), vv(n);
    for (size_t i = 0; i < n; ++i) {
      const cd x(a.re[k][i], a.im[k][i]), y(b.re[k][i], b.im[k][i]);
      const cd c = x * std::conj(y);
      cr[i] = c.real(), ci[i] = c.imag(), vv[i] = std::norm(x) + std::norm(y);
    }
    const auto br = box(cr), bi = box(ci), bv = box(vv);
    double s = 0;
    for (size_t i = 0; i < gw.size(); ++i) {
      // Both bands exactly zero over the window with K = 0: cwssim_index gives NaN (0/0);
      // the bands are identical there, so this scores 1 and no output is ever NaN.
      const double den = bv[i] + o.k;
      s += gw[i] / gs * (den > 0 ? (2 * std::hypot(br[i], bi[i]) + o.k) / den : 1.0);
    }
    r.per_orientation.push_back(s);
    total += s;
  }
  r.cw_ssim = total / double(a.re.size());
  return r;
}

int CwSsimLevelFor(const CwSsimOptions& o, int width, int height) {
  return o.level > 0 ? o.level : std::max(1, MaxCwSsimLevel(width, height) - 1);
}

CwSsimResult CwSsim(const Image& a, const Image& b, const CwSsimOptions& o) {
  o.Validate();
  CheckComparable(a, b, "CW-SSIM");
  const int max_level = MaxCwSsimLevel(a.width, a.height);
  const int level = CwSsimLevelFor(o, a.width, a.height);
  return CwSsimFromBands(ComputeCwSsimBands(a, o, level), ComputeCwSsimBands(b, o, level), o, level,
                         max_level);
}

}  // namespace raymatch::compare
