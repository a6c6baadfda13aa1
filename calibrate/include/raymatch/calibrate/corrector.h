#pragma once
// Corrector ring transmissions from a flat-field iris series (the paper's angular corrector; the
// signal is linear in the transmissions):
// S_k = g sum_j T_j w_kj, with w_kj the light of illumination k through zone j.
#include <string>
#include <vector>

#include "raymatch/calibrate/inputs.h"
#include "raymatch/core/calibration_file.h"

namespace raymatch::calibrate {

struct CorrectorOptions {
  int zones = 9;           ///< central disc + rings, equal widths in radius to 1.02 x the NA edge
  double distance_mm = 0;  ///< corrector plane from the focal plane; 0 = working distance
  double smoothness = 0;   ///< weight of a second-difference penalty on T (0 = none)
};

/// The linear least-squares problem and its solution (also usable directly, e.g. in tests).
struct TransmissionFit {
  std::vector<double> transmissions, sigma;  ///< per zone; T_0 = 1 (sigma 0)
  double gain = 0, gain_sigma = 0;
  std::vector<double> model, residual;  ///< per flat field (photons per pixel)
  double reduced_chi2 = 0;
  int dof = 0;                    ///< flat fields less the free transmissions and the gain
  double chi2_z = 0;              ///< chi^2 as a normal deviate (Wilson-Hilferty), 0 without dof
  bool mismatch = false;          ///< chi^2 above 1 + 3 sqrt(2 / dof) per degree of freedom
  double sigma_scale = 1;         ///< factor applied to the uncertainties: sqrt(reduced chi^2) when
                                  ///< chi^2 is 3 sd above or below its expectation, else 1
  std::string verdict;            ///< why sigma_scale is not 1 (empty when it is)
  std::vector<int> undetermined;  ///< zones no flat field illuminates
  std::string message;
};

/// Fits T (T_0 = 1, bounds [0, 1.2]) and g to S_k = g sum_j T_j W[k][j] with standard
/// deviations sigma_k (Ceres). Zones with no light in any flat field are undetermined: they are
/// held at the previous zone's value and listed. Uncertainties from the covariance (J^T J)^-1
/// of the sigma-weighted residuals, scaled by the reduced chi^2 when that is 3 standard
/// deviations above 1 (model mismatch) or below it (stated noise overstated): sigma_scale.
TransmissionFit FitTransmissions(const std::vector<std::vector<double>>& W,
                                 const std::vector<double>& S, const std::vector<double>& sigma,
                                 double smoothness);

/// Zone index of a direction with direction-cosine radius s (sin theta), or -1 beyond the rim.
int CorrectorZone(double s, double na, int zones);

struct CorrectorSummary {
  CalibrationData data;  ///< input calibration (if any) with the corrector added
  TransmissionFit fit;
  std::vector<double> signal;                ///< S_k, photons per pixel
  std::vector<std::vector<double>> weights;  ///< W[k][j]
  std::vector<std::string> warnings;
  std::string BriefReport() const;
};

/// Runs the corrector calibration; `base` (may be null) is an existing calibration file's data
/// (light field, optics) that the result extends.
CorrectorSummary CalibrateCorrector(const FlatFieldInput& input, const CorrectorOptions& options,
                                    const CalibrationData* base);

}  // namespace raymatch::calibrate
