#pragma once
// The calibration file: one human-readable TOML file plus binary sidecars (a float32 TIFF of
// the angular light-field map), written by `raymatch calibrate` and read by the simulator
// (docs/calibration-format.md). Either the light field or the corrector may be absent.
#include <array>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch {

struct CalibrationData {
  // Light field: angular radiance over direction cosines (u, v) in
  // [-angular_extent, angular_extent]^2, columns = u increasing, rows = v decreasing from the top
  // (docs/conventions.md); spatially uniform field: a disc of field_radius_um at the object plane
  // (0 = not measured: the simulator sizes it to cover the view).
  Image angular_map;  ///< empty when the file has no light field
  double angular_extent = 0;
  double field_radius_um = 0;
  double na_limit = 0;             ///< the measured map is cut at this NA (the objective's;
                                   ///< 0 = not cut, e.g. measured with an mrcal camera)
  double cone_half_angle_deg = 0;  ///< fitted edge half-angle of the cone (informational)
  // Optional spatial map (relative irradiance at the object plane, from a flat-field image) over
  // a rectangle field_size_um centred on the optical axis; columns x increasing, rows y
  // decreasing from the top (object-plane orientation, docs/conventions.md). Empty = uniform.
  Image spatial_map;
  double field_size_um[2] = {0, 0};
  std::string light_field_note;  ///< e.g. "measured up to NA 0.42; beyond: extrapolated"
  // The light field beyond na_limit, which no image through the objective shows: a soft edge
  // (1 - tanh((theta - edge_half_angle_deg) / edge_width_deg)) / 2 continuing the map's ring 3
  // map pixels inside the cut outwards (docs/calibration-format.md). 0 = none (the map as it is),
  // set by `raymatch calibrate sphere` from a drop of known shape.
  double edge_half_angle_deg = 0, edge_width_deg = 0;
  /// The edge's axis tilted from the optical axis, [x, y] degrees (direction cosines sin x, sin y).
  std::array<double, 2> edge_tilt_deg{0, 0};
  // Camera: the Gaussian PSF's sigma at the object plane (um), 0 = none/not calibrated.
  double psf_sigma_um = 0;
  /// 1-sigma uncertainties of calibrated scene values, by the fit key they set (e.g.
  /// "light_field_edge.half_angle_deg", "camera.psf_sigma_um"; table [uncertainty], written by
  /// `raymatch calibrate sphere`): a fit's `prior = "calibration"` reads them.
  std::map<std::string, double> key_sigma;
  // Corrector: central disc + rings (empty when not calibrated).
  std::vector<double> ring_outer_mm, transmissions, transmission_sigma;
  double corrector_distance_mm = 0;  ///< plane distance from the focal plane
  // Optics.
  double objective_focal_mm = 0, working_distance_mm = 0, na = 0, tube_focal_mm = 0;
  double pixel_pitch_um = 0, wavelength_um = 0;
  nlohmann::json provenance;  ///< version, date, command line, input checksums
  /// The sidecar images ReadCalibrationFile read (angular and spatial maps); not written.
  std::vector<std::string> sidecar_files;

  bool has_light_field() const { return !angular_map.empty(); }
  bool has_corrector() const { return !transmissions.empty(); }
};

/// Reads a calibration file strictly (unknown keys and bad values are "file:line:col" errors)
/// with its sidecars, which are resolved relative to the file.
CalibrationData ReadCalibrationFile(const std::string& path);

class TomlReader;
/// The light field edge's tilt [x, y] in degrees (each within 10) from `key` of a calibration
/// file or a scene's [light_field_edge] table; a bad value is a "file:line:col" error of `key`.
std::array<double, 2> ReadEdgeTiltDeg(TomlReader& table, const std::string& key);

/// Writes the TOML file and its sidecars (<stem>.angular.tif, <stem>.spatial.tif): all go to
/// temporaries and are renamed into place only when all are complete (nothing half-written).
void WriteCalibrationFile(const std::string& path, const CalibrationData& data);

}  // namespace raymatch
