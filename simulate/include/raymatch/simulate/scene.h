#pragma once
// The scene: illumination, transparent objects, microscope optics and camera, read from TOML.
//
// Frames and units (docs/conventions.md): one right-handed world frame in micrometres. Light
// travels along +z. The optical axis is the z axis. z = 0 is the scene's reference plane (the
// object plane where sources define their field). Angles in degrees in files, radians inside.
// Refractive indices are absolute (relative to vacuum).
#include <toml++/toml.h>

#include <array>
#include <cmath>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "raymatch/core/camera_readout.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image.h"
#include "raymatch/core/vec.h"
#include "raymatch/simulate/index_field.h"

namespace raymatch::simulate {

enum class SourceType { kCollimated, kCone, kPoint, kLightField, kRayList };
enum class FieldShape { kDisc, kRect };

/// A density tabulated at increasing x, linear between the samples (a pulse's power over time, a
/// spectrum's power over wavelength): inverse-CDF sampling and its mean.
struct PiecewiseLinear {
  std::vector<double> x, p;
  std::vector<double> cumulative;  ///< integral of p up to each x (last = total)
  double mean = 0;                 ///< integral of x p / integral of p
  double Sample(double u) const;   ///< x for a uniform u in [0, 1)
};

/// Reads lines "x,p[,q]" (a header line allowed; p >= 0, x increasing; an optional third column
/// multiplies p, e.g. a camera's quantum efficiency) into a PiecewiseLinear. Throws Error naming
/// the file and line; `what` names the columns in messages.
PiecewiseLinear ReadPiecewiseLinearCsv(const std::string& path, const std::string& what);

/// Gaussian with the given centre and FWHM cut at +-3 FWHM: inverse CDF for u in [0, 1).
double TruncatedGaussianSample(double center, double fwhm, double u);

enum class SpectrumType { kNone, kGaussian, kLines, kFile };
const char* SpectrumTypeName(SpectrumType t);  ///< "none", "gaussian", "lines", "file"

/// [source] spectrum: the illumination's wavelengths. Each ray that can meet a dispersive object
/// draws its wavelength from its own stream; objects with a dispersion law (water, Cauchy,
/// Sellmeier) then have that wavelength's index for it. Ideal lenses are achromatic.
struct SpectrumSpec {
  SpectrumType type = SpectrumType::kNone;
  double center_um = 0, fwhm_um = 0;            ///< gaussian (drawn within +-3 FWHM)
  std::vector<double> wavelengths_um, weights;  ///< lines (weights normalised to sum 1)
  std::string file;                             ///< file: wavelength_um, power[, efficiency]
  PiecewiseLinear table;                        ///< file
  double Sample(double u) const;                ///< wavelength (um) for u in [0, 1)
  double mean_um() const;                       ///< power-weighted mean wavelength
};

/// Illumination. Collimated, cone and light-field sources define rays by where they cross the
/// reference plane z = 0 and their direction, then start them on a source plane before every
/// object (back-traced along straight lines, paper Fig. 1b).
/// A calibrated light field's soft edge beyond the NA at `theta_deg` from the edge's axis:
/// (1 - tanh((theta - edge_half_angle_deg) / edge_width_deg)) / 2 (SourceSpec::edge_*).
inline double LightFieldSoftEdge(double theta_deg, double edge_half_angle_deg,
                                 double edge_width_deg) {
  return 0.5 * (1 - std::tanh((theta_deg - edge_half_angle_deg) / edge_width_deg));
}
/// Where a continued light field's edge model takes over from the measured map: this many map
/// pixels inside the NA cut (the cone images' angular blur near the cut, about 2 deg on the
/// sample).
inline constexpr double kEdgeRingPixels = 3;

struct SourceSpec {
  SourceType type = SourceType::kCone;
  FieldShape field_shape = FieldShape::kDisc;
  double field_radius_um = 0;             ///< disc field radius; 0 = automatic (covers the view)
  std::array<double, 2> field_size_um{};  ///< rect field width, height
  Vec3 field_center_um{};                 ///< centre of the field (z ignored)
  double half_angle_deg = 0;              ///< cone: max angle to +z (uniform radiance inside)
  double tilt_deg = 0, azimuth_deg = 0;   ///< collimated: direction polar angle and azimuth
  Vec3 position_um{};                     ///< point: emission point
  // Light field: a tabulated angular radiance map over direction cosines (u, v) in
  // [-angular_extent, angular_extent]^2 (columns: u increasing; rows: v decreasing from the top),
  // and an optional spatial map over the field rectangle.
  Image angular_map;
  double angular_extent = 0;
  Image spatial_map;
  /// The spatial map's edge values continue beyond its rectangle out to the automatic field
  /// extent (set for maps from a calibration file, which cover about the camera's view).
  bool extend_spatial_map = false;
  /// Ray list: weighted rays where they cross the object plane z = 0, each (x_um, y_um, u, v,
  /// weight); rays are drawn with probability proportional to weight (and back-traced to the
  /// source plane like the others). From a .npy file of shape (N, 5).
  std::vector<std::array<double, 5>> rays;
  std::string ray_file;
  std::string angular_map_file, spatial_map_file;
  /// A light field from a calibration file whose map is cut at the objective's NA: the sine of
  /// that cut (0 = not cut), and the illumination beyond it when edge_half_angle_deg > 0: the
  /// map's ring 3 map pixels inside the cut continued outwards, across the cut, under the soft
  /// edge E(theta) = (1 - tanh((theta - edge_half_angle_deg) / edge_width_deg)) / 2, relative
  /// to E at that ring (the cone images blur the last 2 deg before the cut; scene table
  /// [light_field_edge], calibration [light_field] edge_*).
  double map_na_limit = 0;
  double edge_half_angle_deg = 0, edge_width_deg = 0;
  /// The edge's axis tilted from the optical axis, [x, y] in degrees: theta above is measured
  /// from the axis with direction cosines (sin x, sin y) (light_field_edge.tilt_deg,
  /// calibration edge_tilt_deg). The map inside the ring is the measurement either way.
  std::array<double, 2> edge_tilt_deg{0, 0};
  /// Which part of a continued light field the source emits: all, only inside the reference
  /// ring (the measurement) or only from it outwards (the edge model). Fits trace the two parts as
  /// separate ray populations, so the edge's keys leave the inside rays' paths unchanged
  /// (Simulator::source_weight()).
  enum class EdgePart { kAll, kInside, kBeyond };
  EdgePart edge_part = EdgePart::kAll;
  SpectrumSpec spectrum;  ///< none: monochromatic at Scene::wavelength_um
};

enum class DispersionLaw { kNone, kWater, kCauchy, kSellmeier };

/// How an object's index depends on the wavelength (none: a constant `index`, monochromatic).
struct Dispersion {
  DispersionLaw law = DispersionLaw::kNone;
  double temperature_K = 0, density_kg_m3 = 0;  ///< water (IAPWS R9-97)
  std::vector<double> coefficients;             ///< Cauchy: n = A + B / l^2 + C / l^4 (l in um)
  std::vector<double> sellmeier_b, sellmeier_c_um2;  ///< n^2 = 1 + sum B l^2 / (l^2 - C)
  double IndexAt(double wavelength_um) const;
};

enum class ShapeType { kSphere, kEllipsoid, kBox, kMesh };

struct TriangleMesh;  // shapes.h

struct ObjectSpec {
  std::string name;
  ShapeType shape = ShapeType::kSphere;
  Vec3 center_um{};
  double radius_um = 0;      ///< sphere
  Vec3 semi_axes_um{};       ///< ellipsoid semi-axes, box half-sizes
  Vec3 rotation_deg{};       ///< ellipsoid, box, mesh: Euler x-y-z (docs)
  std::string mesh_file;     ///< mesh: OBJ/PLY/STL path (resolved)
  double mesh_scale_um = 1;  ///< mesh: micrometres per mesh unit
  /// Generated mesh in object-local micrometres (surface of revolution, iso-surface); when set
  /// it is used instead of mesh_file.
  std::shared_ptr<const TriangleMesh> mesh;
  std::string shape_description;  ///< how a generated mesh was made
  double index = 1.0;             ///< absolute refractive index
  /// Imaginary part k of the complex index n + i k (absorption; optics = "mie" only: the ray
  /// model does not absorb, and a scene with k > 0 asks for the wave model).
  double absorption_index = 0;
  std::string material;      ///< "constant" or "water (IAPWS R9-97, T=..., rho=...)"
  double density_kg_m3 = 0;  ///< water: the density used (0 for a constant index)
  /// water: "given" (density_kg_m3 in the file) or "defaulted" (Tanaka et al. 2001 at T);
  /// empty for a constant index.
  std::string density_source;
  /// The index over the spectrum ([source] spectrum); `index` is its value at wavelength_um.
  Dispersion dispersion;
  /// Gradient-index field inside the object (null: homogeneous, never integrated).
  std::shared_ptr<const IndexField> index_field;
  /// Velocity during the exposure, micrometres per microsecond (= m/s); center_um is the
  /// object's position at the pulse's centre (ExposureSpec). Meshes and fields move with it.
  Vec3 velocity_um_per_us{};
  /// How far the object can move from center_um during the exposure: |v| x the pulse's largest
  /// offset (ExposureSpec::max_offset_us); its bounds grow by this much.
  double SweepUm(double max_offset_us) const { return Length(velocity_um_per_us) * max_offset_us; }
  FileLocation where;  ///< for messages
};

enum class PulseShape { kNone, kTopHat, kGaussian, kFile };
const char* PulseName(PulseShape s);  ///< "none", "tophat", "gaussian", "file"

/// [exposure]: the illumination pulse's time profile. Each ray that can meet a moving object
/// draws its emission time from its own stream (Offset); objects are traced where they are at
/// that time. Times are offsets from the pulse's centre: the top-hat's midpoint, the Gaussian's
/// peak, a tabulated profile's power-weighted mean time.
struct ExposureSpec {
  PulseShape shape = PulseShape::kNone;
  double duration_us = 0;   ///< top-hat
  double fwhm_us = 0;       ///< Gaussian (truncated at +-3 FWHM: 7 sigma)
  std::string file;         ///< tabulated: CSV of time_us, relative power (piecewise linear)
  PiecewiseLinear profile;  ///< tabulated, times relative to its power-weighted mean
  /// The largest |t - centre| a ray can draw.
  double max_offset_us() const;
  /// The emission time's offset from the pulse's centre for a uniform u in [0, 1).
  double Offset(double u) const;
};

/// A tabulated pulse from a CSV file (time_us, relative power; piecewise linear between lines),
/// its times made relative to the power-weighted mean. Throws Error naming the file and line.
ExposureSpec TabulatedExposure(const std::string& path);

enum class ObjectiveModel { kSingle, kTwoLens };

struct CorrectorSpec {
  bool enabled = false;
  double distance_mm = 0;             ///< plane distance from the focal plane (0 = default)
  std::vector<double> ring_outer_mm;  ///< outer radius of the disc and each ring, ascending
  std::vector<double> transmissions;  ///< one per zone, in [0, 1]
};

struct OpticsSpec {
  ObjectiveModel model = ObjectiveModel::kSingle;
  double objective_focal_mm = 10;  ///< effective focal length f
  /// Numerical aperture NA = n sin(theta_max), n the medium the objective looks into
  /// (Scene::medium_index: dipping/immersion), so it accepts sin(theta) <= NA / n in that medium
  /// (docs/conventions.md). Must be below n.
  double na = 0.42;
  double working_distance_mm = 20;  ///< two-lens: front focal plane to first lens
  double back_focal_mm = 0;         ///< two-lens: last lens to back focal plane (stop)
  double tube_focal_mm = 200;
  double tube_distance_mm = 150;  ///< objective stop (back focal plane) to tube lens
  CorrectorSpec corrector;
};

struct CameraSpec {
  int nx = 0, ny = 0;                 ///< pixels (columns, rows)
  double pixel_pitch_um = 0;          ///< sensor pixel pitch
  std::array<double, 2> offset_um{};  ///< sensor centre offset from the axis, sensor frame
  double sensor_shift_mm = 0;         ///< sensor displacement along z from the tube focus
  bool flip = true;                   ///< true: store the image upright (undo the inversion)
  /// Gaussian point-spread function (sigma, at the object plane) applied to each detected ray:
  /// a convolution of the photon distribution that keeps exact Poisson statistics. 0 = none.
  double psf_sigma_um = 0;
  /// [camera.readout]: also write the frame as the camera's code values (read noise, gain, dark
  /// level, full well, converter bits), like a raw frame. Empty: photon counts only.
  std::optional<CameraReadout> readout;
};

enum class PartialReflection { kOff, kUnpolarized, kPolarized };

/// Which model makes the images: Monte Carlo rays (the default), or the exact wave image of a
/// homogeneous sphere (Mie scattering with partially coherent imaging, wave_image.h).
enum class ImageOptics { kRays, kMie, kPhysical };
const char* ImageOpticsName(ImageOptics o);  ///< "rays", "mie", "physical"

/// [trace.mie]: the wave image's sampling (defaults converge to below 0.1 % of the background for
/// spheres above about 10 um radius; smaller ones need a finer grid: docs/wave-optics.md).
struct MieSettings {
  int nodes_per_panel = 6;    ///< Gauss-Legendre nodes per panel of sin(theta) (illumination)
  double panel_width = 0.03;  ///< widest panel in sin(theta)
  int harmonics = 8;          ///< azimuthal harmonics of an asymmetric (light-field) source
  double oversample = 1.5;    ///< FFT grid spacing lambda_medium / (4 NA / n) / oversample
  double margin_um = 0;       ///< window margin beyond the sphere's light (0: 8 um + 8 lambda/NA)
  /// The FFT window's side (0: automatic, from the sphere's radius and defocus). Fits fix it, so
  /// the sampling does not jump as the radius and z change between evaluations.
  double window_um = 0;
  int pixel_subsamples = 0;  ///< per pixel side (0: spacing at most lambda_medium / (8 NA / n))
  int spectrum_nodes = 8;    ///< wavelengths of a Gaussian or tabulated spectrum (equal power)
  /// Wavelengths per illumination direction class: the directions are split into this many
  /// interleaved classes, each with its own `spectrum_nodes` wavelengths shifted along the
  /// spectrum, so the image samples spectrum_nodes x spectrum_interleave wavelengths at the
  /// cost of spectrum_nodes (at one wavelength the classes add up to the full image).
  int spectrum_interleave = 1;
  int motion_nodes = 8;  ///< times over the pulse of a moving sphere (equal power)
};

/// [trace.physical]: the sampling of the physical-optics image (docs/physical-optics.md).
struct PhysicalSettings {
  int polar_nodes = 3;      ///< Gauss-Legendre nodes in sin(theta) across a cone (per side of NA)
  int azimuths = 8;         ///< illumination directions per polar node of a cone
  double oversample = 1.5;  ///< image grid spacing lambda_medium / (4 NA / n) / oversample
  double margin_um = 0;     ///< window margin beyond the objects' light (0: 8 um + 8 lambda/NA)
  /// The FFT window's side (0: automatic, from the objects' extent and the defocus). Fits fix
  /// it, so the sampling does not jump as the objects change between evaluations.
  double window_um = 0;
  int pixel_subsamples = 0;   ///< per pixel side (0: spacing at most lambda_medium / (8 NA / n))
  double ray_spacing_um = 0;  ///< field rays' coarse lattice (0: the medium's wavelength)
  int refine_levels = 6;      ///< halvings of a lattice cell at most
  double max_cell_steps = 1;  ///< a cell is halved while its exit-plane image spans more steps
  int max_events = 4;         ///< surface events of the longest Fresnel branch (at most 8)
  int spectrum_nodes = 8;     ///< wavelengths of a Gaussian or tabulated spectrum (equal power)
  int motion_nodes = 8;       ///< times over the pulse of moving objects (equal power)
};

struct TraceSpec {
  uint64_t rays = 0;             ///< rays per image; 0 = derive from photons_per_pixel
  double photons_per_pixel = 0;  ///< target mean hits per pixel in the flat field
  PartialReflection partial_reflection = PartialReflection::kUnpolarized;
  int max_interactions = 100;  ///< interface events per ray before it is abandoned
  int threads = 0;             ///< 0 = all cores
  uint64_t seed = 1;
  GrinSettings grin;                        ///< gradient-index integration tolerances
  ImageOptics optics = ImageOptics::kRays;  ///< [trace] optics = "rays" | "mie"
  MieSettings mie;                          ///< [trace.mie]
  PhysicalSettings physical;                ///< [trace.physical]
};

struct Scene {
  std::string name = "image";
  std::string file;  ///< the scene file this came from
  double wavelength_um = 0.462;
  double medium_index = 1.0;
  SourceSpec source;
  std::vector<ObjectSpec> objects;
  OpticsSpec optics;
  CameraSpec camera;
  TraceSpec trace;
  ExposureSpec exposure;  ///< [exposure]; only used when an object moves
  /// Whether an object moves during the exposure (a velocity_um_per_us and a pulse).
  bool has_motion() const;
  /// A spectrum and at least one object whose index depends on the wavelength.
  bool is_spectral() const;
  std::vector<double> defocus_um{0.0};  ///< focal-plane positions (see docs: sign convention)
  std::vector<std::string> warnings;    ///< non-fatal notes from loading (printed by apps)
  /// Every file the scene read besides itself (calibration and its maps, maps, tables, fields,
  /// outlines), and the meshes it names, resolved, once each: what a result made from the
  /// scene depends on.
  std::vector<std::string> input_files;
};

/// Reads and validates a scene file. Throws raymatch::Error "file:line:col: error: ..." for
/// syntax errors, unknown keys, wrong types, missing values and impossible numbers.
Scene LoadScene(const std::string& path);

/// The same from an already parsed table (e.g. a scene with values changed by a fit); `path`
/// names it in messages and resolves relative file names.
Scene LoadScene(const toml::table& table, const std::string& path);

/// Checks cross-field consistency (objects before the objective, field large enough, ...);
/// LoadScene calls it. Throws Error naming the offending value.
void ValidateScene(const Scene& scene);

/// sin of the largest angle to the axis the objective accepts in the scene's medium: NA / n.
double AcceptanceSin(const Scene& scene);

/// Magnification of the objective + tube lens (negative: inverted image).
double Magnification(const OpticsSpec& optics);

}  // namespace raymatch::simulate
