#include "raymatch/calibrate/corrector.h"

#include <ceres/ceres.h>

#include <Eigen/Dense>
#include <cmath>
#include <iomanip>
#include <sstream>

#include "raymatch/calibrate/lightfield.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/provenance.h"

namespace raymatch::calibrate {

namespace {

struct SignalResidual {
  std::vector<double> w;
  double s, sigma;
  bool operator()(const double* const* p, double* r) const {
    const double* T = p[0];
    double m = 0;
    for (size_t j = 0; j < w.size(); ++j) m += T[j] * w[j];
    r[0] = (s - p[1][0] * m) / sigma;
    return true;
  }
};

struct SmoothResidual {
  int j;
  double weight;
  template <class T>
  bool operator()(T const* const* p, T* r) const {
    const T* t = p[0];
    r[0] = T(weight) * (t[j - 1] - 2.0 * t[j] + t[j + 1]);
    return true;
  }
};

}  // namespace

int CorrectorZone(double s, double na, int zones) {
  if (s >= 1) return -1;
  const double t = s / std::sqrt(1 - s * s), edge = 1.02 * na / std::sqrt(1 - na * na);
  const int z = int(t / edge * zones);
  return z < zones ? z : -1;
}

TransmissionFit FitTransmissions(const std::vector<std::vector<double>>& W,
                                 const std::vector<double>& S, const std::vector<double>& sg,
                                 double smoothness) {
  const size_t K = W.size(), J = W.at(0).size();
  TransmissionFit f;
  f.transmissions.assign(J, 1.0);
  double colmax = 0;
  std::vector<double> col(J, 0);
  for (size_t j = 0; j < J; ++j) {
    for (size_t k = 0; k < K; ++k) col[j] += W[k][j];
    colmax = std::max(colmax, col[j]);
  }
  if (!(colmax > 0) || !(col[0] > 1e-3 * colmax))
    throw Error("the flat fields carry no light through the central zone: nothing to fit");
  std::vector<int> fixed = {0};
  for (size_t j = 1; j < J; ++j)
    if (col[j] < 1e-3 * colmax) f.undetermined.push_back(int(j)), fixed.push_back(int(j));
  ceres::Problem prob;
  double* T = f.transmissions.data();
  double g = S[0] / std::max(1e-300, [&] {
               double m = 0;
               for (size_t j = 0; j < J; ++j) m += W[0][j];
               return m;
             }());
  for (size_t k = 0; k < K; ++k) {
    auto* cost = new ceres::DynamicNumericDiffCostFunction<SignalResidual>(
        new SignalResidual{W[k], S[k], sg[k]});
    cost->AddParameterBlock(int(J));
    cost->AddParameterBlock(1);
    cost->SetNumResiduals(1);
    prob.AddResidualBlock(cost, nullptr, T, &g);
  }
  if (smoothness > 0)
    for (size_t j = 1; j + 1 < J; ++j) {
      auto* c = new ceres::DynamicAutoDiffCostFunction<SmoothResidual, 4>(
          new SmoothResidual{int(j), smoothness});
      c->AddParameterBlock(int(J));
      c->SetNumResiduals(1);
      prob.AddResidualBlock(c, nullptr, T);
    }
  prob.SetManifold(T, new ceres::SubsetManifold(int(J), fixed));
  for (size_t j = 0; j < J; ++j) {
    prob.SetParameterLowerBound(T, int(j), 0.0);
    prob.SetParameterUpperBound(T, int(j), 1.2);
  }
  prob.SetParameterLowerBound(&g, 0, 0.0);
  ceres::Solver::Options so;
  so.max_num_iterations = 200;
  so.function_tolerance = 1e-14;
  so.parameter_tolerance = 1e-12;
  ceres::Solver::Summary sum;
  ceres::Solve(so, &prob, &sum);
  if (!sum.IsSolutionUsable()) throw Error("corrector fit failed: " + sum.BriefReport());
  // Undetermined zones take the previous zone's value.
  for (int j : f.undetermined) T[j] = T[j - 1];
  f.gain = g;
  double chi2 = 0;
  for (size_t k = 0; k < K; ++k) {
    double m = 0;
    for (size_t j = 0; j < J; ++j) m += T[j] * W[k][j];
    f.model.push_back(g * m);
    f.residual.push_back(S[k] - g * m);
    chi2 += std::pow((S[k] - g * m) / sg[k], 2);
  }
  const int dof = int(K) - int(J - fixed.size()) - 1;
  f.reduced_chi2 = dof > 0 ? chi2 / dof : 0;
  f.dof = dof;
  // Covariance of the free parameters (T_j not fixed, and g) from the analytic Jacobian of
  // the weighted residuals, (J^T J)^-1, scaled by the reduced chi^2 when it exceeds 1.
  f.sigma.assign(J, 0.0);
  std::vector<int> free;
  for (size_t j = 0; j < J; ++j)
    if (!std::count(fixed.begin(), fixed.end(), int(j))) free.push_back(int(j));
  const int P = int(free.size()) + 1;
  const int rows = int(K) + (smoothness > 0 ? int(J) - 2 : 0);
  Eigen::MatrixXd Jm = Eigen::MatrixXd::Zero(rows, P);
  for (size_t k = 0; k < K; ++k) {
    double m = 0;
    for (size_t j = 0; j < J; ++j) m += T[j] * W[k][j];
    for (int q = 0; q < P - 1; ++q) Jm(int(k), q) = g * W[k][free[q]] / sg[k];
    Jm(int(k), P - 1) = g * m / sg[k];  // derivative with respect to ln g (commensurate scale)
  }
  if (smoothness > 0)
    for (size_t j = 1; j + 1 < J; ++j)
      for (int q = 0; q < P - 1; ++q) {
        const int fj = free[q];
        const double c = fj == int(j) - 1 || fj == int(j) + 1 ? 1.0 : fj == int(j) ? -2.0 : 0.0;
        Jm(int(K + j - 1), q) = smoothness * c;
      }
  const Eigen::MatrixXd info = Jm.transpose() * Jm;
  Eigen::FullPivLU<Eigen::MatrixXd> lu(info);
  if (lu.isInvertible()) {
    // With the sigma_k known, chi^2 says something only when it is significantly away from its
    // expectation: above 1 + 3 sqrt(2 / dof), the model does not describe the flat fields (or
    // the noise is underestimated) and the uncertainties are inflated by it; 3 standard
    // deviations below (Wilson-Hilferty normal approximation of chi^2 / dof), the stated noise
    // of the flat-field signals overstates their scatter and the uncertainties are scaled down
    // by it (the Birge ratio, both ways: uncertainties that match the scatter).
    const bool mismatch = dof > 0 && f.reduced_chi2 > 1 + 3 * std::sqrt(2.0 / dof);
    f.mismatch = mismatch;
    const double a = dof > 0 ? 2.0 / (9.0 * dof) : 0;
    f.chi2_z = dof > 0 ? (std::cbrt(f.reduced_chi2) - (1 - a)) / std::sqrt(a) : 0;
    const bool overstated = dof > 0 && f.chi2_z < -3;
    f.sigma_scale = mismatch || overstated ? std::sqrt(f.reduced_chi2) : 1.0;
    const Eigen::MatrixXd cov = lu.inverse() * (f.sigma_scale * f.sigma_scale);
    if (mismatch)
      f.verdict =
          "chi^2 above its expectation: the model does not describe the flat fields within "
          "their noise; uncertainties inflated by sqrt(reduced chi^2)";
    else if (overstated)
      f.verdict =
          "chi^2 below its expectation (z " + std::to_string(f.chi2_z).substr(0, 5) +
          "): the flat fields scatter less than their stated noise; uncertainties scaled by "
          "sqrt(reduced chi^2)";
    for (int q = 0; q < P - 1; ++q) f.sigma[free[q]] = std::sqrt(std::max(0.0, cov(q, q)));
    f.gain_sigma = g * std::sqrt(std::max(0.0, cov(P - 1, P - 1)));
  }
  std::ostringstream msg;
  msg << "fitted " << J - fixed.size() << " of " << J << " zone transmissions from " << K
      << " flat fields";
  if (std::count(fixed.begin(), fixed.end(), 0))
    msg << " (zone 0, the central disc, fixed at 1: the gain carries the overall level)";
  msg << "; reduced chi^2 " << f.reduced_chi2;
  if (!f.verdict.empty())
    msg << " (" << f.verdict << ")";
  else if (dof > 0)
    msg << " for " << dof << " degrees of freedom (" << std::fixed << std::setprecision(1)
        << f.chi2_z << " standard deviations from its expectation: consistent with the flat "
        << "fields' stated noise)" << std::defaultfloat << std::setprecision(6);
  for (int j : f.undetermined)
    msg << "; zone " << j << " receives no light in any flat field: undetermined (held at zone "
        << j - 1 << "'s value)";
  if (dof <= 0) msg << "; as many unknowns as flat fields: add iris settings or smoothness";
  f.message = msg.str();
  return f;
}

CorrectorSummary CalibrateCorrector(const FlatFieldInput& in, const CorrectorOptions& o,
                                    const CalibrationData* base) {
  CorrectorSummary s;
  if (base) s.data = *base;
  const double M = in.optics.magnification(), p = in.camera.pixel_pitch_um / M,
               na = in.optics.acceptance_sin();  // NA / n: a sine in the medium
  Image dark;
  if (!in.dark.empty()) dark = ReadImage(in.dark);
  const Image* dk = dark.empty() ? nullptr : &dark;
  std::vector<double> sigma;
  for (const FlatImage& fl : in.flats) {
    size_t sat = 0;
    const Image flat = LoadPhotons(fl.file, dk, in.camera, &sat);
    if (sat) s.warnings.push_back(fl.file + ": " + std::to_string(sat) + " saturated pixels");
    const PixelStats st = ComputeStats(flat);
    const Image cone = LoadPhotons(fl.cone, dk, in.camera, &sat);
    if (cone.width != flat.width || cone.height != flat.height)
      throw Error(FileLocation{fl.cone}, "cone image size differs from its flat field");
    double cx, cy;
    Centroid(cone, p, 0.25, &cx, &cy, nullptr);
    // The apex is the pinhole at the object plane. An iris-limited (or NA-limited) cone is
    // centred on the optical axis, so the cone's centroid gives the apex's lateral position.
    // The light through zone j is the cone image's photons in the annulus that zone's angles
    // cover on the plane h = cone_dz_um beyond the apex (r = h tan theta, exact for the ideal
    // objective). Summing photons, not a resampled angular map, keeps every photon: the
    // pinhole's size and the blur spill light past the NA radius, and that light (which did pass
    // the aperture) is counted in the outermost zone. Pixels are split 4x4 at zone boundaries.
    const double h = fl.cone_dz_um, tna = na / std::sqrt(1 - na * na);
    const double r_max = h * tna + 0.5 * in.pinhole_diameter_um + 3 * p;
    std::vector<double> w(o.zones, 0.0);
    double var = 0;  // variance of the summed photons: shot noise + read noise (+ the dark's)
    const double rn2 = (dk ? 2 : 1) * (std::pow(in.camera.read_noise_e, 2) +
                                       std::pow(in.camera.gain_e_per_dn, 2) / 12);
    for (int row = 0; row < cone.height; ++row)
      for (int col = 0; col < cone.width; ++col) {
        const double X = PixX(col, cone.width, p) - cx, Y = PixY(row, cone.height, p) - cy;
        if (std::hypot(X, Y) > r_max) continue;
        const double e = cone.at(col, row);
        var += std::max(0.0, e) + rn2;
        for (int a = 0; a < 4; ++a)
          for (int b = 0; b < 4; ++b) {
            const double t = std::hypot(X + (a - 1.5) / 4 * p, Y + (b - 1.5) / 4 * p) / h;
            const int z = CorrectorZone(t / std::sqrt(1 + t * t), na, o.zones);
            w[z >= 0 ? z : o.zones - 1] += e / 16 / fl.cone_exposure;
          }
      }
    double total = 0;
    for (double x : w) total += x;
    if (!(total > 0))
      throw Error(FileLocation{fl.cone}, "no light inside the NA circle of the cone image");
    s.weights.push_back(w);
    s.signal.push_back(st.mean / fl.exposure);
    // sigma_k: the flat mean's noise (shot + read, over its pixels) and the relative noise of
    // the cone's light, which scales the whole model row (effective-variance approximation).
    const double rel_flat =
        std::sqrt((std::max(st.mean, 1.0) + rn2) / st.count) / std::max(st.mean, 1e-300);
    const double rel_cone = std::sqrt(var) / fl.cone_exposure / total;
    sigma.push_back(st.mean / fl.exposure * std::hypot(rel_flat, rel_cone));
  }
  s.fit = FitTransmissions(s.weights, s.signal, sigma, o.smoothness);
  CalibrationData& d = s.data;
  const double dist = o.distance_mm > 0 ? o.distance_mm : in.optics.working_distance_mm;
  d.corrector_distance_mm = dist;
  d.ring_outer_mm.clear();
  const double edge = dist * 1.02 * na / std::sqrt(1 - na * na);
  for (int j = 0; j < o.zones; ++j) d.ring_outer_mm.push_back(edge * (j + 1) / o.zones);
  d.transmissions = s.fit.transmissions;
  d.transmission_sigma = s.fit.sigma;
  if (!base || d.objective_focal_mm == 0) {
    d.objective_focal_mm = in.optics.objective_focal_mm;
    d.working_distance_mm = in.optics.working_distance_mm;
    d.na = in.optics.na;
    d.tube_focal_mm = in.optics.tube_focal_mm;
    d.pixel_pitch_um = in.camera.pixel_pitch_um;
    d.wavelength_um = in.optics.wavelength_um;
  }
  nlohmann::json prov = ProvenanceJson();
  for (auto& [k, v] : d.provenance.items())
    if (!prov.contains(k)) prov[k] = v;
  std::string inputs;
  for (const FlatImage& fl : in.flats) inputs += FileChecksum(fl.file) + " " + fl.file + "; ";
  prov["corrector_inputs"] = inputs;
  d.provenance = prov;
  return s;
}

std::string CorrectorSummary::BriefReport() const {
  std::ostringstream os;
  os.precision(4);
  os << fit.message << "\n  zone  T        sigma\n";
  for (size_t j = 0; j < fit.transmissions.size(); ++j) {
    os << "  " << j << "     " << fit.transmissions[j] << "   ";
    if (fit.sigma[j] > 0)
      os << fit.sigma[j] << "\n";
    else
      os << "(fixed or undetermined)\n";
  }
  return os.str();  // warnings are separate (apps print them to stderr)
}

}  // namespace raymatch::calibrate
