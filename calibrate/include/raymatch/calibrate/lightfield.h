#pragma once
// Light-field source from a pinhole image and light-cone images (paper section II.A, Fig. 1b).
#include <string>
#include <vector>

#include "raymatch/calibrate/inputs.h"
#include "raymatch/core/calibration_file.h"

namespace raymatch::calibrate {

struct LightFieldOptions {
  int map_size = 64;  ///< angular map cells per side
  double extent = 0;  ///< half-width in direction cosines; 0 = min(1, 1.15 NA)
  /// Parametric extrapolation beyond the objective NA, where nothing is measured: the mean
  /// radiance of the last measured ring continues to this half-angle (deg), then stops.
  /// 0 = none (the map is zero beyond the NA, and the file says so).
  double extrapolate_to_deg = 0;
};

/// Cone geometry fitted (Ceres) from all cone images together: the apex (the pinhole) at
/// (x, y, z), the axis direction as slopes (tx, ty), and the edge half-angle: at each dz the
/// cone's centroid is apex_xy + (dz - z) t and its edge radius (dz - z) tan(half_angle).
struct ConeFit {
  double apex_x_um = 0, apex_y_um = 0, apex_z_um = 0;
  double tilt_x = 0, tilt_y = 0;
  double half_angle_deg = 0;
  double rms_center_residual_um = 0, rms_radius_residual_um = 0;
  std::vector<double> radius_um, center_x_um, center_y_um;  ///< measured per cone image
  bool cut_by_na = false;  ///< the edge is the objective's acceptance, not the cone's own
};

struct LightFieldSummary {
  CalibrationData data;  ///< light-field part and optics, with provenance
  double pinhole_x_um = 0, pinhole_y_um = 0, pinhole_diameter_um = 0;
  ConeFit cone;
  std::vector<std::string> warnings;
  std::string BriefReport() const;
};

/// Runs the light-field calibration. Throws Error on bad input (missing, blank or mismatched
/// images); problems that leave a usable result are warnings.
LightFieldSummary CalibrateLightField(const LightFieldInput& input, const LightFieldOptions& o);

/// Angular radiance map (per du dv, arbitrary common units) from one cone image in photons,
/// with the apex at (ax, ay, az) in object-plane micrometres and the image focused dz beyond
/// the object plane. Values are signed (noise after dark subtraction is kept so that sums stay
/// unbiased). Cells whose direction misses the image or exceeds `na` are 0; `*covered`
/// (optional) flags cells that were measured. Pixel centres follow docs/conventions.md.
Image ConeToAngularMap(const Image& photons, double pixel_um, double dz_um, double ax, double ay,
                       double az, int n, double extent, double na, std::vector<char>* covered);

/// Spatial map (relative irradiance at the object plane) from a flat-field image in photons:
/// bin x bin pixel means over the view, normalised to the mean of its central quarter. Returns
/// the map and its rectangle (um); *lo and *hi give its range.
Image SpatialMapFromFlat(const Image& photons, double pixel_um, int bin, double size_um[2],
                         double* lo, double* hi);

/// Object-plane coordinates (um) of a pixel centre, with pixel_um the object-plane pixel size
/// (upright image, docs/conventions.md).
inline double PixX(int col, int nx, double pixel_um) { return (col + 0.5 - nx / 2.0) * pixel_um; }
inline double PixY(int row, int ny, double pixel_um) { return (ny / 2.0 - row - 0.5) * pixel_um; }

/// Intensity-weighted centroid (object-plane um) of the pixels above `fraction` of the maximum.
void Centroid(const Image& img, double pixel_um, double fraction, double* x, double* y,
              double* rms_radius);

}  // namespace raymatch::calibrate
