#pragma once
// Refractive index of water from the IAPWS R9-97 formulation (Harvey, Gallagher, Levelt Sengers,
// J. Phys. Chem. Ref. Data 27, 761 (1998)); REFERENCE.md section 4. The index is relative to
// vacuum. Valid for 261.15-773.15 K, 0-1060 kg/m^3, 0.2-1.1 um; outside that range the same
// formula is extrapolated and `in_range` is false so callers can warn.

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

}  // namespace raymatch::simulate
