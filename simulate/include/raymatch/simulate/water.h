#pragma once
// Refractive index of water from the IAPWS R9-97 formulation (Harvey, Gallagher, Levelt Sengers,
// J. Phys. Chem. Ref. Data 27, 761 (1998)). The index is relative to
// vacuum. Valid for 261.15-773.15 K, 0-1060 kg/m^3, 0.2-1.1 um; outside that range the same
// formula is extrapolated and `in_range` is false so callers can warn.

#include <vector>

namespace raymatch::simulate {

struct WaterIndex {
  double n = 0;
  bool in_range = true;
};

/// IAPWS R9-97 index for temperature T (K), density rho (kg/m^3), vacuum wavelength (um).
WaterIndex WaterRefractiveIndex(double temperature_K, double density_kg_m3, double wavelength_um);

/// Density of air-free water at 101.325 kPa, Tanaka et al., Metrologia 38, 301 (2001), eq. 1;
/// valid 0-40 degC (273.15-313.15 K).
double WaterDensityTanaka(double temperature_K);

/// A water density field's index at wavelength `to_um` as an affine function of its index at
/// `from_um`: n_to ~ offset + scale n_from, by least squares over the given states (density and
/// temperature pairs); max_error is the largest residual over them. At fixed wavelength IAPWS
/// R9-97 is close to linear in density, so the map is close to exact: over 900-1060 kg/m^3,
/// 280-340 K and 0.40-0.53 um against 0.462 um the residual stays below 1e-5 (tested).
struct AffineIndexMap {
  double offset = 0, scale = 1, max_error = 0;
};
AffineIndexMap WaterIndexMap(const std::vector<double>& density_kg_m3,
                             const std::vector<double>& temperature_K, double from_um,
                             double to_um);

/// WaterIndexMap tabulated at 129 wavelengths over [lo_um, hi_um] and interpolated linearly: for
/// nodes h apart the interpolation errs by at most h^2 / 8 max|d^2 n / d lambda^2| (water: below
/// 1 um^-2 above 0.3 um, so 1.3e-7 over a 0.13 um span). A ray of wavelength lambda sees
/// offset + scale n of the field.
class WaterMapTable {
 public:
  WaterMapTable() = default;
  WaterMapTable(const std::vector<double>& density_kg_m3, const std::vector<double>& temperature_K,
                double from_um, double lo_um, double hi_um);
  AffineIndexMap At(double lambda_um) const;
  double max_error() const { return max_error_; }  ///< largest residual at any node
  bool empty() const { return node_.empty(); }

 private:
  double lo_ = 0, step_ = 0;
  std::vector<AffineIndexMap> node_;
  double max_error_ = 0;
};

}  // namespace raymatch::simulate
