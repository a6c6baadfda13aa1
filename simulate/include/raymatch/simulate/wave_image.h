#pragma once
// The exact wave-optics image of a homogeneous sphere in a brightfield microscope ([trace]
// optics = "mie"): Mie scattering of every illumination plane wave, partially coherent Koehler
// imaging through an aplanatic objective, intensities summed over the mutually incoherent
// illumination directions.
//
// Model (docs/wave-optics.md derives each step):
//  * Every direction (u, v) of the source is a plane wave of unit flux density through the
//    z-plane per unit of the source's density w(u, v) du dv (the ray model's convention: a ray
//    density per dx dy du dv), unpolarised: the two polarisations are averaged.
//  * The sphere's scattered field (Bohren and Huffman's S1, S2 in the scattering plane) becomes
//    an angular spectrum: a far field f exp(ikr) / r has the angular-spectrum density
//    A = f / (-2 pi i k cos theta) (stationary phase; Mandel and Wolf, Optical Coherence and
//    Quantum Optics, sec. 3.3), sampled on the window's Fourier grid.
//  * The objective passes sin(theta) <= NA / n_medium; the corrector's zone transmissions
//    apodise the pupil by angle (amplitude sqrt(T), the zone a direction meets on axis); the
//    aplanatic lens maps each object-space plane wave to the camera with amplitude
//    sqrt(cos theta) and turns its meridional component into the radial one (Richards and Wolf,
//    Proc. R. Soc. A 253, 358 (1959)), so a flat field keeps the flux of the ray model;
//    defocus is the propagation phase exp(i (k_z - k_z,in) (z_focus - z_sphere)).
//  * A rotationally symmetric microscope makes the image of a tilted wave the rotated image of
//    the wave tilted by the same angle in the x-z plane: the intensity change is computed for
//    a set of polar angles only (Gauss-Legendre panels in sin theta, split where the NA, the
//    corrector's zones and the source's edges make it jump), expanded in azimuthal harmonics
//    about the sphere, and weighted by the source's azimuthal Fourier moments at each angle. A
//    rotationally symmetric source needs the zeroth harmonic only.
//  * The image is the flat field plus that change, integrated over each pixel, convolved with
//    the camera PSF if set, scaled so the flat field gives `photons_per_pixel` on average, and
//    multiplied by the light field's spatial map (a slowly varying envelope) where it has one.
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "raymatch/core/image.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::simulate {

/// The reason a scene has no exact wave image ("" when it has one): optics = "mie" needs one
/// homogeneous sphere, or two concentric ones (a coated sphere: a shell and the core inside it,
/// e.g. a bubble in a drop), and a cone, light-field or on-axis collimated source.
std::string MieUnsupportedReason(const Scene& scene);

/// How finely the wave image was sampled (from the scene's [trace.mie] table; how far the
/// defaults converge: docs/wave-optics.md).
struct MieSampling {
  int directions = 0;              ///< polar-angle nodes of the illumination (quadrature)
  int harmonics = 0;               ///< azimuthal harmonics of the source kept (0: symmetric)
  int grid = 0;                    ///< FFT grid per side
  double grid_um = 0;              ///< its spacing at the object plane
  double window_um = 0;            ///< its size
  int pixel_subsamples = 0;        ///< per pixel side
  int terms = 0;                   ///< Mie series terms (at the first wavelength)
  int wavelengths = 1;             ///< wavelength nodes of a spectrum
  double size_parameter = 0;       ///< 2 pi n_medium a / lambda
  double core_size_parameter = 0;  ///< a coated sphere's core's (0: homogeneous)
  double background = 0;           ///< flat-field flux before scaling (source units)
  nlohmann::json ToJson() const;
};

/// The FFT window side MieImager chooses by itself for `scene`'s sphere focused at `defocus_um`
/// (MieSettings::window_um = 0): the sphere's light plus the margin, on both sides.
double AutomaticMieWindowUm(const Scene& scene, double defocus_um);

class MieImager {
 public:
  /// Throws Error (naming the scene file) when MieUnsupportedReason is not empty.
  explicit MieImager(const Scene& scene);
  /// One class of an interleaved spectrum (MieSettings::spectrum_interleave): a monochromatic
  /// `scene`'s image from the illumination nodes whose index is `offset` modulo `stride`, in
  /// the photon scale of all of them (the classes' images add up to the full one).
  MieImager(const Scene& scene, int stride, int offset);
  ~MieImager();
  MieImager(const MieImager&) = delete;
  MieImager& operator=(const MieImager&) = delete;

  /// The expected image (photons per pixel, no noise) with the objective focused at
  /// `defocus_um`; `threads` 0: all cores. The same for any thread count. It keeps the fields
  /// of each axial offset for later calls, so one imager must not be used from two threads at
  /// once.
  Image Expected(double defocus_um, int threads = 0) const;

  /// Moves the sphere to (x_um, y_um) across the axis, keeping its z: the image of the scene
  /// with that centre, without recomputing the fields (they are kept per axial offset from the
  /// focal plane; a lateral move only shifts where they are rendered).
  void MoveAcross(double x_um, double y_um);

  /// The sampling used by the last Expected call (or the constructor's, before one).
  MieSampling sampling() const;
  /// The stages this model runs, e.g. {"optics:mie", "source:cone", "corrector", "psf"}.
  std::vector<std::string> Effects() const;
  const Scene& scene() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

/// A Poisson sample of `expected` (photons per pixel) from counter-based streams keyed by
/// (seed, plane, pixel): the same image for any thread count.
Image PoissonSample(const Image& expected, uint64_t seed, uint32_t plane);

}  // namespace raymatch::simulate
