// The illumination pulse's time profile ([exposure], scene.h ExposureSpec): reading it and
// drawing emission times.
#include <algorithm>
#include <boost/math/special_functions/erf.hpp>
#include <cmath>
#include <fstream>
#include <sstream>

#include "raymatch/core/error.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::simulate {

namespace {

constexpr double kFwhmPerSigma = 2.3548200450309493;  // 2 sqrt(2 ln 2)
constexpr double kGaussianCutFwhm = 3;                // the Gaussian is drawn within +-3 FWHM

/// Time (us) and relative power from a CSV file: two numbers per line, an optional header.
void ReadProfileCsv(const std::string& path, std::vector<double>* t, std::vector<double>* p) {
  std::ifstream in(path);
  if (!in) throw Error(FileLocation{path}, "cannot open the pulse profile");
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    std::replace(line.begin(), line.end(), ',', ' ');
    std::istringstream ss(line);
    double a, b;
    if (!(ss >> a >> b)) {
      if (t->empty() && n == 1) continue;  // header
      throw Error(FileLocation{path, n, 1}, "expected two numbers 'time_us,relative_power'");
    }
    if (!std::isfinite(a) || !std::isfinite(b) || b < 0)
      throw Error(FileLocation{path, n, 1}, "expected a finite time and a power >= 0");
    if (!t->empty() && !(a > t->back()))
      throw Error(FileLocation{path, n, 1}, "times must increase from line to line");
    t->push_back(a);
    p->push_back(b);
  }
  if (t->size() < 2) throw Error(FileLocation{path}, "a pulse profile needs at least two lines");
}

}  // namespace

double ExposureSpec::max_offset_us() const {
  switch (shape) {
    case PulseShape::kTopHat:
      return duration_us / 2;
    case PulseShape::kGaussian:
      return kGaussianCutFwhm * fwhm_us;
    case PulseShape::kFile:
      return std::max(-time_us.front(), time_us.back());
    default:
      return 0;
  }
}

double ExposureSpec::Offset(double u) const {
  switch (shape) {
    case PulseShape::kTopHat:
      return (u - 0.5) * duration_us;
    case PulseShape::kGaussian: {
      // Inverse CDF of the normal distribution cut at +-a sigma: u -> Phi^-1(Phi(-a) + u (1 -
      // 2 Phi(-a))), with Phi^-1(q) = sqrt(2) erf^-1(2 q - 1).
      const double sigma = fwhm_us / kFwhmPerSigma, a = kGaussianCutFwhm * kFwhmPerSigma;
      const double lo = 0.5 * std::erfc(a / std::sqrt(2.0));
      const double q = lo + u * (1 - 2 * lo);
      return sigma * std::sqrt(2.0) * boost::math::erf_inv(2 * q - 1);
    }
    case PulseShape::kFile: {
      // Piecewise-linear power: find the segment holding the energy u E, then solve the
      // trapezoid's quadratic for the time within it.
      const double target = u * cumulative.back();
      size_t k =
          std::upper_bound(cumulative.begin(), cumulative.end(), target) - cumulative.begin();
      k = std::clamp<size_t>(k, 1, time_us.size() - 1);
      const double h = time_us[k] - time_us[k - 1], p0 = power[k - 1], p1 = power[k];
      const double e = target - cumulative[k - 1];  // energy into the segment
      const double slope = (p1 - p0) / h;  // p(x) = p0 + slope x, E(x) = p0 x + slope x^2/2
      double x;
      if (std::abs(slope) * h < 1e-12 * std::max(p0, p1))
        x = p0 > 0 ? e / p0 : 0;
      else  // the root of slope/2 x^2 + p0 x - e = 0 in [0, h], in the cancellation-free form
        x = 2 * e / (p0 + std::sqrt(std::max(0.0, p0 * p0 + 2 * slope * e)));
      return time_us[k - 1] + std::clamp(x, 0.0, h);
    }
    default:
      return 0;
  }
}

ExposureSpec TabulatedExposure(const std::string& path) {
  ExposureSpec e;
  e.shape = PulseShape::kFile;
  e.file = path;
  std::vector<double> t, p;
  ReadProfileCsv(path, &t, &p);
  // Energy per segment (trapezoids) and the power-weighted mean time (exact for linear power).
  double energy = 0, moment = 0;
  e.cumulative = {0};
  for (size_t k = 1; k < t.size(); ++k) {
    const double h = t[k] - t[k - 1];
    energy += 0.5 * h * (p[k - 1] + p[k]);
    moment += h * (p[k - 1] * (2 * t[k - 1] + t[k]) + p[k] * (t[k - 1] + 2 * t[k])) / 6;
    e.cumulative.push_back(energy);
  }
  if (!(energy > 0)) throw Error(FileLocation{path}, "the pulse profile has no power");
  const double centre = moment / energy;
  for (double& v : t) v -= centre;
  e.time_us = std::move(t);
  e.power = std::move(p);
  return e;
}

}  // namespace raymatch::simulate
