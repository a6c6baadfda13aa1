#include "raymatch/simulate/water.h"

#include <algorithm>
#include <cmath>

namespace raymatch::simulate {

WaterIndex WaterRefractiveIndex(double T, double rho, double lambda_um) {
  constexpr double a0 = 0.244257733, a1 = 9.74634476e-3, a2 = -3.73234996e-3, a3 = 2.68678472e-4,
                   a4 = 1.58920570e-3, a5 = 2.45934259e-3, a6 = 0.900704920, a7 = -1.66626219e-2;
  constexpr double lam_uv = 0.2292020, lam_ir = 5.432937;
  const double rr = rho / 1000.0, tr = T / 273.15, lr = lambda_um / 0.589, l2 = lr * lr;
  const double rhs = a0 + a1 * rr + a2 * tr + a3 * l2 * tr + a4 / l2 + a5 / (l2 - lam_uv * lam_uv) +
                     a6 / (l2 - lam_ir * lam_ir) + a7 * rr * rr;
  const double A = rr * rhs;
  WaterIndex out;
  out.n = std::sqrt((1 + 2 * A) / (1 - A));
  out.in_range =
      T >= 261.15 && T <= 773.15 && rho >= 0 && rho <= 1060 && lambda_um >= 0.2 && lambda_um <= 1.1;
  return out;
}

double WaterDensityTanaka(double T) {
  constexpr double a1 = -3.983035, a2 = 301.797, a3 = 522528.9, a4 = 69.34881, a5 = 999.974950;
  const double t = T - 273.15;
  return a5 * (1 - (t + a1) * (t + a1) * (t + a2) / (a3 * (t + a4)));
}

namespace {

/// The indices of the states at one wavelength.
std::vector<double> IndicesAt(const std::vector<double>& rho, const std::vector<double>& T,
                              double lambda_um) {
  std::vector<double> n(rho.size());
  for (size_t i = 0; i < rho.size(); ++i) n[i] = WaterRefractiveIndex(T[i], rho[i], lambda_um).n;
  return n;
}

/// y ~ offset + scale x by least squares, with the largest residual.
AffineIndexMap AffineFit(const std::vector<double>& x, const std::vector<double>& y) {
  const size_t m = x.size();
  double mx = 0, my = 0;
  for (size_t i = 0; i < m; ++i) mx += x[i] / double(m), my += y[i] / double(m);
  double sxx = 0, sxy = 0;
  for (size_t i = 0; i < m; ++i) sxx += (x[i] - mx) * (x[i] - mx), sxy += (x[i] - mx) * (y[i] - my);
  AffineIndexMap map;
  // One state (a uniform grid): a pure offset, exact.
  map.scale = sxx > 1e-24 * double(m) ? sxy / sxx : 1.0;
  map.offset = my - map.scale * mx;
  for (size_t i = 0; i < m; ++i)
    map.max_error = std::max(map.max_error, std::abs(map.offset + map.scale * x[i] - y[i]));
  return map;
}

}  // namespace

AffineIndexMap WaterIndexMap(const std::vector<double>& rho, const std::vector<double>& T,
                             double from_um, double to_um) {
  return AffineFit(IndicesAt(rho, T, from_um), IndicesAt(rho, T, to_um));
}

WaterMapTable::WaterMapTable(const std::vector<double>& rho, const std::vector<double>& T,
                             double from_um, double lo_um, double hi_um) {
  constexpr int kNodes = 129;
  lo_ = lo_um;
  step_ = hi_um > lo_um ? (hi_um - lo_um) / (kNodes - 1) : 0;
  const std::vector<double> from = IndicesAt(rho, T, from_um);  // the grid's own, once
  for (int k = 0; k < (step_ > 0 ? kNodes : 1); ++k) {
    node_.push_back(AffineFit(from, IndicesAt(rho, T, lo_um + k * step_)));
    max_error_ = std::max(max_error_, node_.back().max_error);
  }
}

AffineIndexMap WaterMapTable::At(double lambda_um) const {
  if (node_.size() < 2) return node_.empty() ? AffineIndexMap() : node_[0];
  const double u = std::clamp((lambda_um - lo_) / step_, 0.0, double(node_.size() - 1));
  const size_t k = std::min(size_t(u), node_.size() - 2);
  const double w = u - double(k);
  const AffineIndexMap &a = node_[k], &b = node_[k + 1];
  AffineIndexMap m;
  m.offset = a.offset + (b.offset - a.offset) * w;
  m.scale = a.scale + (b.scale - a.scale) * w;
  return m;
}

}  // namespace raymatch::simulate
