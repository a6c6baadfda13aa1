// What a ray draws besides its path: its emission time within the pulse ([exposure]) and its
// wavelength within the spectrum ([source] spectrum), and how an object's index follows the
// wavelength (scene.h: ExposureSpec, SpectrumSpec, Dispersion).
#include <algorithm>
#include <boost/math/special_functions/erf.hpp>
#include <cmath>
#include <fstream>
#include <sstream>

#include "raymatch/core/error.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/water.h"

namespace raymatch::simulate {

namespace {

constexpr double kFwhmPerSigma = 2.3548200450309493;  // 2 sqrt(2 ln 2)
constexpr double kGaussianCutFwhm = 3;                // Gaussians are drawn within +-3 FWHM

}  // namespace

const char* SpectrumTypeName(SpectrumType t) {
  static const char* names[] = {"none", "gaussian", "lines", "file"};  // SpectrumType order
  return names[int(t)];
}

const char* PulseName(PulseShape s) {
  static const char* names[] = {"none", "tophat", "gaussian", "file"};  // PulseShape order
  return names[int(s)];
}

double PiecewiseLinear::Sample(double u) const {
  // Find the segment holding the integral u P, then solve the trapezoid's quadratic in it.
  const double target = u * cumulative.back();
  size_t k = std::upper_bound(cumulative.begin(), cumulative.end(), target) - cumulative.begin();
  k = std::clamp<size_t>(k, 1, x.size() - 1);
  const double h = x[k] - x[k - 1], p0 = p[k - 1], p1 = p[k];
  const double e = target - cumulative[k - 1];  // integral into the segment
  const double slope = (p1 - p0) / h;           // p(s) = p0 + slope s, E(s) = p0 s + slope s^2/2
  double s;
  if (std::abs(slope) * h < 1e-12 * std::max(p0, p1))
    s = p0 > 0 ? e / p0 : 0;
  else  // the root of slope/2 s^2 + p0 s - e = 0 in [0, h], in the cancellation-free form
    s = 2 * e / (p0 + std::sqrt(std::max(0.0, p0 * p0 + 2 * slope * e)));
  return x[k - 1] + std::clamp(s, 0.0, h);
}

PiecewiseLinear ReadPiecewiseLinearCsv(const std::string& path, const std::string& what) {
  std::ifstream in(path);
  if (!in) throw Error(FileLocation{path}, "cannot open the " + what + " file");
  PiecewiseLinear t;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    std::replace(line.begin(), line.end(), ',', ' ');
    std::istringstream ss(line);
    double a, b, q = 1;
    if (!(ss >> a >> b)) {
      if (t.x.empty() && n == 1) continue;  // header
      throw Error(FileLocation{path, n, 1}, "expected two or three numbers '" + what + "'");
    }
    if (!(ss >> q)) q = 1;
    if (!std::isfinite(a) || !std::isfinite(b) || !std::isfinite(q) || b < 0 || q < 0)
      throw Error(FileLocation{path, n, 1}, "expected finite numbers, powers >= 0");
    if (!t.x.empty() && !(a > t.x.back()))
      throw Error(FileLocation{path, n, 1}, "the first column must increase from line to line");
    t.x.push_back(a);
    t.p.push_back(b * q);
  }
  if (t.x.size() < 2) throw Error(FileLocation{path}, "needs at least two lines: " + what);
  // Integral per segment (trapezoids) and the first moment (exact for linear p).
  double total = 0, moment = 0;
  t.cumulative = {0};
  for (size_t k = 1; k < t.x.size(); ++k) {
    const double h = t.x[k] - t.x[k - 1], x0 = t.x[k - 1], x1 = t.x[k];
    total += 0.5 * h * (t.p[k - 1] + t.p[k]);
    moment += h * (t.p[k - 1] * (2 * x0 + x1) + t.p[k] * (x0 + 2 * x1)) / 6;
    t.cumulative.push_back(total);
  }
  if (!(total > 0)) throw Error(FileLocation{path}, "all powers are zero: " + what);
  t.mean = moment / total;
  return t;
}

double TruncatedGaussianSample(double center, double fwhm, double u) {
  // Inverse CDF of the normal distribution cut at +-a sigma: u -> Phi^-1(Phi(-a) + u (1 -
  // 2 Phi(-a))), with Phi^-1(q) = sqrt(2) erf^-1(2 q - 1).
  const double sigma = fwhm / kFwhmPerSigma;
  static const double lo = 0.5 * std::erfc(kGaussianCutFwhm * kFwhmPerSigma / std::sqrt(2.0));
  const double q = lo + u * (1 - 2 * lo);
  return center + sigma * std::sqrt(2.0) * boost::math::erf_inv(2 * q - 1);
}

double ExposureSpec::max_offset_us() const {
  switch (shape) {
    case PulseShape::kTopHat:
      return duration_us / 2;
    case PulseShape::kGaussian:
      return kGaussianCutFwhm * fwhm_us;
    case PulseShape::kFile:
      return std::max(-profile.x.front(), profile.x.back());
    default:
      return 0;
  }
}

double ExposureSpec::Offset(double u) const {
  switch (shape) {
    case PulseShape::kTopHat:
      return (u - 0.5) * duration_us;
    case PulseShape::kGaussian:
      return TruncatedGaussianSample(0, fwhm_us, u);
    case PulseShape::kFile:
      return profile.Sample(u);
    default:
      return 0;
  }
}

ExposureSpec TabulatedExposure(const std::string& path) {
  ExposureSpec e;
  e.shape = PulseShape::kFile;
  e.file = path;
  e.profile = ReadPiecewiseLinearCsv(path, "time_us,relative_power");
  for (double& t : e.profile.x) t -= e.profile.mean;  // times from the power-weighted mean
  e.profile.mean = 0;
  return e;
}

double SpectrumSpec::Sample(double u) const {
  switch (type) {
    case SpectrumType::kGaussian:
      return TruncatedGaussianSample(center_um, fwhm_um, u);
    case SpectrumType::kLines: {
      double c = 0;
      for (size_t k = 0; k + 1 < weights.size(); ++k)
        if (u < (c += weights[k])) return wavelengths_um[k];
      return wavelengths_um.back();
    }
    case SpectrumType::kFile:
      return table.Sample(u);
    default:
      return center_um;
  }
}

double SpectrumSpec::mean_um() const {
  switch (type) {
    case SpectrumType::kLines: {
      double m = 0;
      for (size_t k = 0; k < weights.size(); ++k) m += weights[k] * wavelengths_um[k];
      return m;
    }
    case SpectrumType::kFile:
      return table.mean;
    default:
      return center_um;
  }
}

double Dispersion::IndexAt(double l) const {
  switch (law) {
    case DispersionLaw::kWater:
      return WaterRefractiveIndex(temperature_K, density_kg_m3, l).n;
    case DispersionLaw::kCauchy: {
      double n = 0, l2k = 1;
      for (double c : coefficients) n += c / l2k, l2k *= l * l;
      return n;
    }
    case DispersionLaw::kSellmeier: {
      double n2 = 1;
      for (size_t k = 0; k < sellmeier_b.size(); ++k)
        n2 += sellmeier_b[k] * l * l / (l * l - sellmeier_c_um2[k]);
      return std::sqrt(n2);
    }
    default:
      return 0;
  }
}

}  // namespace raymatch::simulate
