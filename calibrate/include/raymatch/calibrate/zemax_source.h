#pragma once
// Zemax OpticStudio binary source files (.DAT/.SDF; the layout is in the OpticStudio
// manual, "Source File"): export a weighted
// ray list sampled from a calibrated light field, and import one back into an angular map.
#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "raymatch/core/array_io.h"
#include "raymatch/core/calibration_file.h"

namespace raymatch::calibrate {

/// The 208-byte little-endian header, field by field in file order.
struct ZemaxSourceHeader {
  int32_t identifier = 1010;  ///< always 1010
  uint32_t num_rays = 0;
  std::string description;      ///< at most 99 characters (NUL-padded char[100])
  float source_flux = 1;        ///< total flux of the source (flux_type units)
  float ray_set_flux = 1;       ///< flux of the rays in this file
  float wavelength_um = 0.462;  ///< used when ray_format = 0
  float inclination_begin = 0, inclination_end = 90;  ///< deg (informational)
  float azimuth_begin = 0, azimuth_end = 360;         ///< deg (informational)
  int32_t dimension_units = 4;                        ///< 0 m, 1 in, 2 cm, 3 ft, 4 mm
  std::array<float, 3> location{}, rotation{}, scale{{1, 1, 1}};
  std::array<float, 4> unused{};
  int32_t ray_format = 0;  ///< 0 flux only (7 floats/ray), 2 spectral (8 floats/ray)
  int32_t flux_type = 0;   ///< 0 watts, 1 lumens
  std::array<int32_t, 2> reserved{};
};

/// One ray: position in dimension_units, direction cosines (l, m, n), flux; wavelength_um is
/// stored only with ray_format = 2.
struct ZemaxRay {
  float x = 0, y = 0, z = 0, l = 0, m = 0, n = 1, flux = 0, wavelength_um = 0;
};

struct ZemaxSourceFile {
  ZemaxSourceHeader header;
  std::vector<ZemaxRay> rays;
};

/// Micrometres per dimension unit (0 m, 1 in, 2 cm, 3 ft, 4 mm); throws Error for other codes.
double ZemaxUnitUm(int32_t dimension_units);

/// Writes the file atomically; header.num_rays is set from rays.size(). Throws Error on bad
/// header values (identifier, ray_format, description length).
void WriteZemaxSourceFile(const std::string& path, const ZemaxSourceFile& file);

/// Reads and checks a file: identifier 1010, ray format 0 or 2, units, and a size of exactly
/// 208 + num_rays x (28 or 32) bytes. Errors name the file and the byte offset.
ZemaxSourceFile ReadZemaxSourceFile(const std::string& path);

struct ZemaxExportOptions {
  uint64_t num_rays = 1000000;
  uint64_t seed = 1;
  double field_radius_um = 0;   ///< uniform disc at z = 0; 0 = the calibration's field radius
  double flux = 1;              ///< total source flux (W); each ray carries flux / num_rays
  int32_t dimension_units = 4;  ///< mm
};

/// Samples rays from the calibration's light field: positions uniform in the field disc at
/// z = 0, directions (u, v) from the angular map (piecewise-constant inverse CDF, uniform within
/// a cell, directions with u^2 + v^2 >= 1 redrawn), n = sqrt(1 - u^2 - v^2). Equal-flux rays:
/// their density per dx dy du dv is the radiance (etendue in direction cosines). Philox streams per
/// ray index: the result depends on the seed only. Throws Error without a light field.
ZemaxSourceFile SampleZemaxSource(const CalibrationData& cal, const ZemaxExportOptions& o);

struct ZemaxImportOptions {
  int map_size = 64;  ///< angular map cells per side
  double extent = 0;  ///< half-width in direction cosines; 0 = from the rays (max |l|, |m|)
};

struct ZemaxImportSummary {
  CalibrationData data;  ///< angular_map, angular_extent, field_radius_um (optics left 0)
  uint64_t rays_used = 0, rays_skipped = 0;  ///< skipped: n <= 0 or outside the map
  std::vector<std::string> warnings;
};

/// Histogram of the rays' (l, m) weighted by flux, divided by the cell area du dv: radiance
/// per du dv (flux units per unit du dv). The field radius is sqrt(2) x the RMS radius of the
/// ray positions (exact for a uniform disc); the light field is assumed separable (positions
/// and directions independent), as the simulator's light-field source is.
ZemaxImportSummary AngularMapFromZemax(const ZemaxSourceFile& file, const ZemaxImportOptions& o);

/// AngularMapFromZemax, with the result's light field replacing `base`'s (its optics and
/// corrector are kept; na_limit 0, provenance updated with the source file's checksum).
ZemaxImportSummary ImportZemaxLightField(const ZemaxSourceFile& file, const ZemaxImportOptions& o,
                                         const CalibrationData& base,
                                         const std::string& source_path = "");

/// The rays as the simulator's ray list (scene source type "ray_list"): an (N, 5) array of
/// x_um, y_um, l, m, flux per ray with n > 0 (others skipped; *skipped counts them). Positions
/// are taken at the object plane in the light frame (ray z, location, rotation, scale ignored,
/// as in AngularMapFromZemax); nothing is binned, so position-direction correlations are kept.
NdArray ZemaxRayList(const ZemaxSourceFile& file, uint64_t* skipped = nullptr);

}  // namespace raymatch::calibrate
