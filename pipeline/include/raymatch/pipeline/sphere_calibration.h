#pragma once
// `raymatch calibrate sphere`: a spherical drop of known shape as a calibration object (the
// paper's use of drops). Fits planes of its focus scan jointly for the drop's five parameters
// (x, y, z, radius, index) and the microscope's nuisances that no image through the objective
// shows directly: the illumination beyond the objective's NA (the light field's soft edge:
// half-angle, width and the tilt of its axis) and the camera's Gaussian PSF, with the exposure
// profiled per image. Writes them into a copy of the calibration file, which the simulator and fits
// then use (docs/calibration.md, "Sphere calibration").
#include <functional>
#include <string>
#include <vector>

namespace raymatch::pipeline {

struct SphereCalibrationOptions {
  std::string scan_folder;  ///< experiment folder: metadata.toml (scan, dark, nominal size)
  std::string base;         ///< calibration to extend: its light field must be cut at the NA
  std::string output;       ///< calibration file to write (base + edge + PSF)
  std::string work_dir;     ///< fit files and report (default: <output stem>_sphere/)
  /// Defocus values (um) of the scan's planes to fit jointly; empty: the two planes nearest
  /// -R/2 and +R/2 (R the nominal radius): one on each side of the drop, which separates z,
  /// radius and index (one defocused image alone has a valley between them).
  std::vector<double> planes_um;
  std::vector<double> fractions{0.0625, 0.25};  ///< ray fractions of the fit's levels
  double ray_factor = 1;
  /// Free the edge width (default: fixed at its start, 1 deg). On the sample, width, half-angle
  /// and tilt are one weakly determined direction from two planes: with the width free, two
  /// runs differing only in their template noise ended 0.9 deg apart in width (20 Cramer-Rao
  /// bounds) and 0.6 deg in half-angle, the drop's index 2 sigma off; fixed, every drop
  /// parameter within 1 sigma (docs/calibration.md, "Sphere calibration").
  bool fit_width = false;
  /// Free the PSF sigma (else fixed at its start: 0.21 lambda / NA with the rays, 0.05 lambda /
  /// NA with the wave model).
  bool fit_psf = true;
  bool fit_tilt = true;  ///< free the edge axis' tilt [x, y] (else fixed at 0)
  /// The fit's image model: "rays" (the tracer, with a Gaussian PSF standing in for the
  /// objective's diffraction too) or "mie" (the exact wave image of the sphere,
  /// docs/wave-optics.md: the PSF is then the camera's own blur beyond diffraction).
  std::string optics = "rays";
  uint64_t seed = 5;
  int threads = 0;
  bool progress = false;
  std::function<void(const std::string&)> say;  ///< one-line messages (may be empty)
};

struct SphereCalibrationValue {
  std::string key;
  double value = 0, sigma = 0, cramer_rao = 0;
  bool at_bound = false;
};

struct SphereCalibrationResult {
  std::vector<SphereCalibrationValue> values;  ///< the fit's parameters, in fit-file order
  double edge_half_angle_deg = 0, edge_width_deg = 0, psf_sigma_um = 0;
  double edge_tilt_deg[2] = {0, 0};
  std::string status, goodness;  ///< the fit's status and goodness-of-fit verdict
  bool mismatch = false;
  std::string report;  ///< the fit's report.html
  double seconds = 0;
  std::string Brief() const;  ///< a few lines for the terminal
};

/// Runs the sphere calibration; throws raymatch::Error on bad input (a base without a light
/// field cut at the NA, planes not in the scan, ...).
SphereCalibrationResult CalibrateSphere(const SphereCalibrationOptions& options);

}  // namespace raymatch::pipeline
