#pragma once
// Calibration inputs: image folders with a metadata.toml (docs/calibration.md, "Inputs").
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::calibrate {

struct CameraInfo {
  double pixel_pitch_um = 0;  ///< sensor pitch
  int bit_depth = 16;         ///< data bits; saturation at 2^bit_depth - 1
  double gain_e_per_dn = 1;   ///< photons (electrons) per code value
  double well_capacity_e = 0;
  double read_noise_e = 0;
};

struct OpticsInfo {
  double objective_focal_mm = 0, na = 0, working_distance_mm = 0, tube_focal_mm = 0;
  double wavelength_um = 0.462;
  /// Index of the medium the objective looked into during calibration ([optics] medium_index,
  /// default 1: a dry objective in air/vacuum). NA = medium_index x sin(theta_max).
  double medium_index = 1.0;
  double magnification() const { return tube_focal_mm / objective_focal_mm; }
  /// sin of the largest accepted angle to the axis in that medium: NA / n (docs/conventions.md).
  double acceptance_sin() const { return na / medium_index; }
};

struct ConeImage {
  std::string file;
  double dz_um = 0;  ///< focus this far beyond the pinhole
};

struct LightFieldInput {
  std::string folder, pinhole, dark;
  double pinhole_diameter_um = 0;
  std::vector<ConeImage> cones;
  /// mrcal path instead of pinhole + cones: a camera focused at infinity with this model and
  /// its images ([[direction]] entries) of the source (docs/calibration.md).
  std::string camera_model;
  std::vector<std::string> direction_images;
  double field_radius_um = 0;  ///< uniform disc field at the object plane; 0 = not measured
  /// Optional flat-field image (no object, same illumination): its binned pattern becomes the
  /// light field's spatial map (relative irradiance over the view).
  std::string flat;
  int flat_bin_px = 8;
  CameraInfo camera;
  OpticsInfo optics;
};

struct FlatImage {
  std::string file, cone;
  double cone_dz_um = 0;
  /// Relative exposures (lamp power x exposure time, any unit common to the series): the flat's
  /// signal and the cone's light are divided by them, so each cone image can be exposed well.
  double exposure = 1, cone_exposure = 1;
};

struct FlatFieldInput {
  std::string folder, dark;
  double pinhole_diameter_um = 0;
  std::vector<FlatImage> flats;
  CameraInfo camera;
  OpticsInfo optics;
};

/// Strict readers of <folder>/metadata.toml (file:line:col errors, unknown keys rejected).
LightFieldInput ReadLightFieldInput(const std::string& folder);
FlatFieldInput ReadFlatFieldInput(const std::string& folder);

/// A camera image converted to photons: (raw - dark) x gain. Counts raw pixels at or above the
/// saturation level (2^bit_depth - 1) and throws Error for a blank image (no pixel more than
/// 5 read-noise sigmas above the dark level) or a size different from the dark frame.
Image LoadPhotons(const std::string& file, const Image* dark, const CameraInfo& cam,
                  size_t* saturated);

}  // namespace raymatch::calibrate
