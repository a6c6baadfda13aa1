#pragma once
// The physical-optics image of any scene ([trace] optics = "physical"): for each illumination
// plane wave, the angular spectrum the objects leave behind them from rays that carry their
// field (ray_field.h), imaged through the microscope as the wave model images a sphere's
// (wave_image.h), the intensities summed over the mutually incoherent directions and the two
// polarisations.
//
// Model (docs/physical-optics.md):
//  * A cone source is sampled at `polar_nodes` Gauss-Legendre nodes in sin(theta) (on each
//    side of the NA where the cone is wider) times `azimuths` equally spaced azimuths, each a plane
//    wave of unit flux density through the z-plane per unit of the source's density (the ray
//    model's convention); a collimated source is one plane wave. Each is unpolarised: the images of
//    two orthogonal polarisations are averaged.
//  * Its scattered angular spectrum A(k_t) (RayAngularSpectrum, on the Fourier grid of the
//    image window, the objects' centre as origin) passes the objective's NA; the aplanatic
//    objective and tube lens carry each plane wave to the camera with amplitude sqrt(cos theta)
//    and its meridional component turned radial (Richards and Wolf, Proc. R. Soc. A 253, 358
//    (1959)); defocus is the propagation phase exp(i (k_z - k_z,in) (z_focus - z_origin)).
//  * The corrector apodises the pupil by angle: every plane wave, scattered or direct, passes
//    with amplitude sqrt(T) of the zone its direction falls in (the zones as the Mie model sees
//    them, from the focal plane's axis point); a cone's nodes are split at the zone edges.
//  * The image is the flat field plus the intensity change |E_direct + E_s|^2 - |E_direct|^2,
//    blurred by the camera's PSF (a Gaussian at the object plane) where one is set, integrated
//    over each pixel, scaled so the flat field gives `photons_per_pixel` on average (without
//    objects, exactly).
//  * A spectrum is incoherent over wavelengths (lines as given, a Gaussian or tabulated
//    spectrum at `spectrum_nodes` equal-power quantiles), each with the objects' indices at its
//    wavelength; motion averages `motion_nodes` equal-power times of the pulse, the objects
//    where they are then. Each such part is the image above, with its share of the power.
//  * A light field's directions are rings out to its angular map's reach, each direction
//    weighted by the map over its azimuth sector; its spatial map is the image's envelope.
// What it does not take yet (refused with the reason): a point source or a ray list.
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "raymatch/core/image.h"
#include "raymatch/simulate/ray_field.h"
#include "raymatch/simulate/scene.h"

namespace raymatch::simulate {

/// The reason a scene has no physical-optics image here ("" when it has one).
std::string PhysicalUnsupportedReason(const Scene& scene);

/// The FFT window's side (um) that PhysicalImager chooses for `scene` focused at `defocus_um`
/// when [trace.physical] window_um is 0: the objects' light on the focal plane and a margin.
/// A fit takes the largest over its parameter box and fixes it.
double AutomaticPhysicalWindowUm(const Scene& scene, double defocus_um);

/// How the physical-optics image was sampled.
struct PhysicalSampling {
  int directions = 0;        ///< illumination plane waves
  int grid = 0;              ///< FFT grid per side
  double grid_um = 0;        ///< its spacing at the object plane
  double window_um = 0;      ///< its size
  int pixel_subsamples = 0;  ///< per pixel side
  uint64_t field_rays = 0;   ///< field rays traced for the last image
  int wavelengths = 1;       ///< of a spectrum (monochromatic: 1)
  int times = 1;             ///< of the pulse, for moving objects (still: 1)
  nlohmann::json ToJson() const;
};

/// The field rays' layouts (FieldLayout) of an imager's illumination directions and of its
/// parts (a spectrum's wavelengths, a pulse's times), kept across imagers of one scene whose
/// objects change (a fit's evaluations): see PhysicalImager::KeepLayouts.
struct FieldLayouts {
  std::vector<FieldLayout> directions;
  std::vector<std::shared_ptr<FieldLayouts>> parts;
};

class PhysicalImager {
 public:
  /// Throws Error (naming the scene file) when PhysicalUnsupportedReason is not empty.
  explicit PhysicalImager(const Scene& scene);
  ~PhysicalImager();
  PhysicalImager(const PhysicalImager&) = delete;
  PhysicalImager& operator=(const PhysicalImager&) = delete;

  /// The expected image (photons per pixel, no noise) with the objective focused at
  /// `defocus_um`; `threads` 0: all cores. The same for any thread count. `progress`: a
  /// progress bar on stderr over the illumination directions, labelled `label`.
  Image Expected(double defocus_um, int threads = 0, bool progress = false,
                 const std::string& label = "") const;
  /// Lays the field rays out as `layouts` says and records there what it does not yet say
  /// (FieldLayout): imagers of one scene that share it sample their objects alike, so their
  /// images change continuously with the objects. Layouts made for other directions (another
  /// count) are laid out afresh. Expected then writes to `layouts`: imagers that share it must
  /// not run at the same time.
  void KeepLayouts(std::shared_ptr<FieldLayouts> layouts);
  /// The sampling of the last Expected call (or the constructor's, before one).
  PhysicalSampling sampling() const;
  /// The stages this model runs, e.g. {"optics:physical", "source:cone", "partial_reflection"}.
  std::vector<std::string> Effects() const;
  const Scene& scene() const;

  struct Impl;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace raymatch::simulate
