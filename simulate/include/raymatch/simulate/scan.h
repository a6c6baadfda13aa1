#pragma once
// Focus scans: trace one image per defocus value and write them as files.
//
// For each plane: <name>_z<defocus>um.tif (32-bit float counts, ImageJ/Fiji/Python readable),
// a PNG preview (0 .. 2x the median count), and a JSON sidecar saying how it was made. The index
// <name>_scan.json / <name>_scan.csv lists the planes. All files are written atomically.
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "raymatch/simulate/tracer.h"

namespace raymatch::simulate {

struct ScanOptions {
  std::string output_dir;  ///< created if missing
  RunControl control;
  std::optional<uint64_t> rays;  ///< overrides the scene's ray count / photon target
  bool write_png = true;
};

struct ScanPlaneOutput {
  double defocus_um = 0;
  std::string image, png, sidecar;  ///< paths written
  std::string code_values;          ///< <stem>_dn.tif with [camera.readout], else empty
  double mean_counts = 0;
  double seconds = 0;
};

/// The counter-based streams of the camera's read noise start here (plus the plane index),
/// apart from the rays' streams (the plane index itself).
inline constexpr uint32_t kReadoutStream = 0x80000000u;

struct ScanSummary {
  uint64_t rays_per_image = 0;
  double hits_per_pixel_per_ray = 0;  ///< from the photon-target pilot, 0 if not used
  std::vector<ScanPlaneOutput> planes;
  std::string index_json, index_csv;
  double seconds = 0;
  std::vector<std::string> effects;
};

/// With the scene's [camera.readout]: a plane's code values (read noise from the counter-based
/// streams (seed, kReadoutStream + plane index, pixel)) and the sidecar entry `code_values`
/// describing them (camera values, saturated and zero pixels); false without a read-out.
bool CodeValues(const Scene& scene, const Image& counts, uint32_t plane_index, Image* code_values,
                nlohmann::json* entry);

/// Runs the scene's focus scan and writes all outputs. Throws Error on failure (a focus position
/// listed twice fails before anything is written); files already
/// finished stay (each is complete), nothing half-written remains.
ScanSummary RunScan(const Scene& scene, const ScanOptions& options);

/// One plane of `CompareOptics`: the exact wave image (expected photons), a ray image at the
/// same photon count and their difference in units of the shot noise.
struct OpticsComparisonPlane {
  double defocus_um = 0;
  /// mean over pixels of ((rays - wave) / sqrt(wave))^2: 1 where the ray model is right within
  /// the shot noise; the excess over 1 grows in proportion to the photons per pixel.
  double chi2_per_pixel = 0;
  double max_abs_z = 0;  ///< the largest |rays - wave| / sqrt(wave)
  std::string wave_image, ray_image, z_image, z_png;
  /// With [trace] optics = "physical": the physical-optics image (expected photons, no noise)
  /// against the wave image, z = (physical - wave) / sqrt(wave): mean z^2 is its excess over
  /// the shot noise (0 where it is exact), and the files of both.
  bool physical = false;
  double chi2_physical = 0, max_abs_z_physical = 0;
  std::string physical_image, z_physical_image;
};

/// For a sphere scene (MieUnsupportedReason empty) at its photon target: per plane the wave
/// image (<stem>_mie.tif, expected photons), the traced ray image (<stem>_rays.tif) and
/// z = (rays - wave) / sqrt(wave) (<stem>_z.tif, .png on -5..5), and <name>_optics.csv with one
/// line per plane. Where the ray model can be trusted at this photon count: chi2_per_pixel
/// near 1. A scene with optics = "physical" adds its physical-optics image (<stem>_physical.tif)
/// and z = (physical - wave) / sqrt(wave) (<stem>_z_physical.tif, .png).
std::vector<OpticsComparisonPlane> CompareOptics(const Scene& scene, const ScanOptions& options);

/// Throws Error when a focus position is listed twice (two planes would share a file name);
/// RunScan checks this before anything is written, the Python module before tracing.
void CheckPlanePositions(const Scene& scene);

class MieImager;       // wave_image.h
class PhysicalImager;  // physical_image.h

/// One plane of the exact wave model ([trace] optics = "mie"): the expected image, Poisson
/// photon counts from the streams (seed, plane index, pixel) in `counts`, and its sidecar
/// metadata in `*meta`.
PlaneResult MiePlane(const MieImager& mie, double defocus_um, uint32_t plane_index,
                     const RunControl& control, nlohmann::json* meta);

/// One plane of the physical-optics model ([trace] optics = "physical"), as MiePlane.
PlaneResult PhysicalPlane(const PhysicalImager& phys, double defocus_um, uint32_t plane_index,
                          const RunControl& control, nlohmann::json* meta);

/// The sidecar metadata for one traced plane (also embedded in the TIFF ImageDescription).
nlohmann::json PlaneMetadata(const Simulator& sim, const PlaneResult& r, uint32_t plane_index);

/// "<name>_z+012.50um" style stem for a defocus value: two decimals when they read back as the
/// same double, else more (up to 17), so distinct values always give distinct stems.
std::string PlaneStem(const std::string& name, double defocus_um);

}  // namespace raymatch::simulate
