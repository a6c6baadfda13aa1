// MSE, PSNR, SSIM, MS-SSIM and the Poisson measures. Everything is computed in double:
// SSIM's variance terms are differences of nearly equal numbers (E[x^2] - E[x]^2), and float
// would cost about four digits on bright, smooth images.
#include "raymatch/compare/measures.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "filter.h"

namespace raymatch::compare {

namespace {

std::string SizeText(const Image& img) {
  return std::to_string(img.width) + "x" + std::to_string(img.height);
}

void CheckFinite(const Image& img, const std::string& what) {
  for (size_t i = 0; i < img.size(); ++i) {
    if (!std::isfinite(img.pixels[i])) {
      throw CompareError(FailureKind::kInvalidInput,
                         what + ": pixel (" + std::to_string(i % img.width) + ", " +
                             std::to_string(i / img.width) + ") is NaN or infinite");
    }
  }
}

void Require(bool ok, const std::string& message) {
  if (!ok) throw CompareError(FailureKind::kInvalidInput, message);
}

}  // namespace

void CheckComparable(const Image& a, const Image& b, const std::string& what) {
  if (a.empty() || b.empty())
    throw CompareError(FailureKind::kInvalidInput, what + ": an image is empty");
  if (a.width != b.width || a.height != b.height) {
    throw CompareError(FailureKind::kSizeMismatch,
                       what + ": sizes differ (" + SizeText(a) + " vs " + SizeText(b) + " pixels)");
  }
  CheckFinite(a, what + " (first image)");
  CheckFinite(b, what + " (second image)");
}

double MeanSquaredError(const Image& a, const Image& b) {
  CheckComparable(a, b, "MSE");
  double s = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    const double d = double(a.pixels[i]) - double(b.pixels[i]);
    s += d * d;
  }
  return s / double(a.size());
}

double PeakSignalToNoiseRatio(const Image& a, const Image& b, double data_range) {
  Require(data_range > 0 && std::isfinite(data_range), "PSNR: data_range must be > 0");
  const double mse = MeanSquaredError(a, b);
  if (mse <= 0) return kPsnrCapDb;
  return std::min(kPsnrCapDb, 10.0 * std::log10(data_range * data_range / mse));
}

// ---------------------------------------------------------------------------------------------

void SsimOptions::Validate() const {
  Require(data_range > 0 && std::isfinite(data_range),
          "SSIM: data_range (L) must be given and > 0");
  Require(sigma > 0 && sigma < 100, "SSIM: sigma must be in (0, 100) pixels");
  Require(k1 > 0 && k2 > 0, "SSIM: k1 and k2 must be > 0");
}

namespace {

/// Luminance and contrast-structure maps of MATLAB's ssim (replicate padding, 'same' size).
struct SsimMaps {
  std::vector<double> l, cs;
};

/// `clamp_variance`: multissim guards the variances against rounding below 0 (MATLAB's ssim
/// does not).
SsimMaps ComputeSsimMaps(const Plane& x, const Plane& y, double sigma, double c1, double c2,
                         bool clamp_variance = false) {
  const std::vector<double> k = GaussianKernel(sigma);
  const size_t n = x.v.size();
  Plane xx = x, yy = y, xy = x;
  for (size_t i = 0; i < n; ++i) {
    xx.v[i] = x.v[i] * x.v[i];
    yy.v[i] = y.v[i] * y.v[i];
    xy.v[i] = x.v[i] * y.v[i];
  }
  const Plane mx = FilterReplicate(x, k), my = FilterReplicate(y, k);
  const Plane sxx = FilterReplicate(xx, k), syy = FilterReplicate(yy, k),
              sxy = FilterReplicate(xy, k);
  SsimMaps m;
  m.l.resize(n);
  m.cs.resize(n);
  for (size_t i = 0; i < n; ++i) {
    const double mux = mx.v[i], muy = my.v[i];
    double vx = sxx.v[i] - mux * mux, vy = syy.v[i] - muy * muy;
    if (clamp_variance) vx = std::max(vx, 0.0), vy = std::max(vy, 0.0);
    const double cov = sxy.v[i] - mux * muy;
    m.l[i] = (2 * mux * muy + c1) / (mux * mux + muy * muy + c1);
    m.cs[i] = (2 * cov + c2) / (vx + vy + c2);
  }
  return m;
}

double Mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return v.empty() ? 0.0 : s / double(v.size());
}

}  // namespace

SsimResult Ssim(const Image& a, const Image& b, const SsimOptions& options) {
  options.Validate();
  CheckComparable(a, b, "SSIM");
  const double c1 = std::pow(options.k1 * options.data_range, 2);
  const double c2 = std::pow(options.k2 * options.data_range, 2);
  const SsimMaps m = ComputeSsimMaps(ToPlane(a), ToPlane(b), options.sigma, c1, c2);
  SsimResult r;
  double s = 0;
  for (size_t i = 0; i < m.l.size(); ++i) s += m.l[i] * m.cs[i];
  r.ssim = s / double(m.l.size());
  r.mean_luminance = Mean(m.l);
  r.mean_cs = Mean(m.cs);
  if (options.keep_map) {
    r.map = Image(a.width, a.height);
    for (size_t i = 0; i < m.l.size(); ++i) r.map.pixels[i] = float(m.l[i] * m.cs[i]);
  }
  return r;
}

// ---------------------------------------------------------------------------------------------

void MsSsimOptions::Validate() const {
  Require(data_range > 0 && std::isfinite(data_range),
          "MS-SSIM: data_range (L) must be given and > 0");
  Require(sigma > 0 && sigma < 100, "MS-SSIM: sigma must be in (0, 100) pixels");
  Require(num_scales >= 0 && num_scales <= 30, "MS-SSIM: num_scales must be 0 (auto) or 1..30");
  Require(k1 > 0 && k2 > 0, "MS-SSIM: k1 and k2 must be > 0");
  if (weights == MsSsimWeights::kCustom) {
    Require(!custom_weights.empty(), "MS-SSIM: custom weights requested but none given");
    for (double w : custom_weights)
      Require(w >= 0 && std::isfinite(w), "MS-SSIM: custom weights must be >= 0");
  }
}

int MaxMsSsimScales(int width, int height) {
  int m = 1;
  for (int w = width, h = height; w > 1 && h > 1 && m < 30; w = (w + 1) / 2, h = (h + 1) / 2) ++m;
  return m;
}

const char* MsSsimWeightsName(MsSsimWeights w) {
  switch (w) {
    case MsSsimWeights::kMatlab:
      return "matlab";
    case MsSsimWeights::kWang2003:
      return "wang2003";
    case MsSsimWeights::kCustom:
      return "custom";
  }
  return "?";
}

int MsSsimScalesFor(const MsSsimOptions& options, int width, int height) {
  return options.num_scales > 0 ? options.num_scales
                                : std::max(1, MaxMsSsimScales(width, height) - 1);
}

std::vector<double> MsSsimScaleWeights(MsSsimWeights kind, int num_scales,
                                       const std::vector<double>& custom) {
  Require(num_scales >= 1, "MS-SSIM: need at least one scale");
  std::vector<double> w(num_scales);
  switch (kind) {
    case MsSsimWeights::kMatlab: {
      // fspecial('gaussian', [1 M], 1): exp(-x^2/2) at x = j - (M-1)/2.
      for (int j = 0; j < num_scales; ++j) {
        const double x = j - (num_scales - 1) / 2.0;
        w[j] = std::exp(-x * x / 2);
      }
      break;
    }
    case MsSsimWeights::kWang2003: {
      static const double kWang[5] = {0.0448, 0.2856, 0.3001, 0.2363, 0.1333};
      Require(num_scales <= 5, "MS-SSIM: Wang 2003 weights exist for at most 5 scales (got " +
                                   std::to_string(num_scales) + ")");
      for (int j = 0; j < num_scales; ++j) w[j] = kWang[j];
      break;
    }
    case MsSsimWeights::kCustom:
      Require(int(custom.size()) == num_scales, "MS-SSIM: " + std::to_string(custom.size()) +
                                                    " custom weights for " +
                                                    std::to_string(num_scales) + " scales");
      w = custom;
      break;
  }
  double s = 0;
  for (double x : w) s += x;
  Require(s > 0, "MS-SSIM: weights sum to zero");
  for (double& x : w) x /= s;
  return w;
}

Image DownsampleByTwo(const Image& img) {
  const Plane p = Downsample2(ToPlane(img));
  return FromPlane(p);
}

MsSsimResult MsSsim(const Image& a, const Image& b, const MsSsimOptions& options) {
  options.Validate();
  CheckComparable(a, b, "MS-SSIM");
  MsSsimResult r;
  r.max_scales = MaxMsSsimScales(a.width, a.height);
  r.num_scales = MsSsimScalesFor(options, a.width, a.height);
  Require(r.num_scales <= r.max_scales,
          "MS-SSIM: " + std::to_string(r.num_scales) + " scales are too many for a " + SizeText(a) +
              " image (at most " + std::to_string(r.max_scales) +
              ": every scale but the last must be at least 2x2 pixels)");
  const std::vector<double> w =
      MsSsimScaleWeights(options.weights, r.num_scales, options.custom_weights);
  const double c1 = std::pow(options.k1 * options.data_range, 2);
  const double c2 = std::pow(options.k2 * options.data_range, 2);
  Plane x = ToPlane(a), y = ToPlane(b);
  r.ms_ssim = 1;
  for (int j = 0; j < r.num_scales; ++j) {
    const SsimMaps m = ComputeSsimMaps(x, y, options.sigma, c1, c2, /*clamp_variance=*/true);
    MsSsimScale s;
    s.width = x.width;
    s.height = x.height;
    s.weight = w[j];
    double cs = 0, ss = 0;
    for (size_t i = 0; i < m.l.size(); ++i) {
      cs += std::min(m.cs[i], 1.0);
      ss += std::min(m.l[i] * m.cs[i], 1.0);
    }
    s.cs = cs / double(m.l.size());
    s.ssim = ss / double(m.l.size());
    r.scales.push_back(s);
    double term = (j + 1 < r.num_scales) ? s.cs : s.ssim;
    // A negative mean to a fractional power has no real value: multissim counts it as 0
    // (anti-correlated images score 0); an integer power (weight 1 or 0) is taken as it is.
    if (w[j] != std::floor(w[j])) term = std::max(term, 0.0);
    r.ms_ssim *= std::pow(term, w[j]);
    if (j + 1 < r.num_scales) {
      x = Downsample2(x);
      y = Downsample2(y);
    }
  }
  return r;
}

// ---------------------------------------------------------------------------------------------

PoissonResult PoissonMeasures(const Image& counts_a, const Image& counts_b) {
  CheckComparable(counts_a, counts_b, "Poisson measures");
  PoissonResult r;
  double chi2 = 0, dev = 0;
  for (size_t i = 0; i < counts_a.size(); ++i) {
    double a = counts_a.pixels[i], b = counts_b.pixels[i];
    if (a < 0 || b < 0) ++r.clamped_pixels;
    a = std::max(a, 0.0);
    b = std::max(b, 0.0);
    const double s = a + b;
    if (s <= 0) continue;
    chi2 += (a - b) * (a - b) / s;
    const double m = s / 2;
    double d = 0;
    if (a > 0) d += a * std::log(a / m);
    if (b > 0) d += b * std::log(b / m);
    dev += 2 * d;
  }
  r.chi2_per_pixel = chi2 / double(counts_a.size());
  r.deviance_per_pixel = dev / double(counts_a.size());
  return r;
}

}  // namespace raymatch::compare
