#pragma once
// How a fit gets its expected images: the image model of the scene's optics. The fit engine
// (FitModel: parameters, exposure, backgrounds, likelihood) asks an ImageModel for the images
// of a scene; the ray tracer with its common random numbers and its caches of rays that miss
// the objects, the exact wave image of a sphere and the physical-optics image of any scene are
// the three models. Not installed.
#include <cstdint>
#include <map>
#include <memory>
#include <span>
#include <tuple>
#include <vector>

#include "raymatch/core/image.h"
#include "raymatch/core/vec.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/wave_image.h"

namespace raymatch::fit::internal {

/// What one evaluation asks for: the rays of its schedule level, the photons one ray stands
/// for, and the ray streams. Exact models ignore all of it.
struct Draw {
  uint64_t rays = 0;
  double photons_per_ray = 1;
  uint64_t seed = 0;
  /// The evaluation's parameters with those that only move the scene's one object across the
  /// axis (Binding::MovesAcross) set to 0: two evaluations with equal keys have scenes that
  /// differ at most by that move. Empty: no such promise.
  std::vector<double> across_key;
  /// The evaluation's parameters with those that leave the rays of the light field's part
  /// inside the NA (or of the whole source) on the same paths set to 0: the edge's keys where
  /// the part beyond the NA is its own population, the PSF where it is drawn per ray on a finer
  /// camera, the images' backgrounds. Two evaluations with equal keys, seeds and rays trace
  /// the same image of that part. Empty: no such promise.
  std::vector<double> inside_key;
  /// The same for the part beyond the NA (the edge's keys kept).
  std::vector<double> beyond_key;
};

/// One evaluation's images before the exposure and backgrounds: per experimental image, counts
/// (rays) times `photons_per_count` are photons.
struct ModelImages {
  std::vector<Image> counts;
  double photons_per_count = 1;
};

class ImageModel {
 public:
  virtual ~ImageModel() = default;
  /// No simulation noise: one image per evaluation, no ray fractions, no repeats with other
  /// ray streams (FitSpec::exact_images).
  virtual bool exact() const = 0;
  /// The expected images of `scene` (its defocus_um, one per experimental image). Adds the
  /// rays traced to `*rays_traced`.
  virtual ModelImages Images(const simulate::Scene& scene, const Draw& draw,
                             uint64_t* rays_traced) = 0;
  /// Share of the rays that were traced near the objects in the last evaluation (0: none).
  virtual double near_fraction() const { return 0; }
  /// Seconds spent tracing the rays that miss every object (cached per image and ray count).
  virtual double background_seconds() const { return 0; }
  /// The sphere every object stays inside from now on (the near/far split); an evaluation whose
  /// objects leave it traces every ray.
  virtual void SetRegion(const Vec3& /*center*/, double /*radius*/) {}
  /// The next evaluation lays out afresh a sampling the model keeps from evaluation to
  /// evaluation; false where it keeps none (the default), and its images stay as they were.
  virtual bool Relayout() { return false; }
};

/// An image model without simulation noise, in photons at a flat field of `photons_per_pixel`,
/// with one FFT window (`window_um`) for every evaluation.
class NoiselessImageModel : public ImageModel {
 public:
  bool exact() const override { return true; }

 protected:
  NoiselessImageModel(double photons_per_pixel, double window_um, int threads)
      : photons_per_pixel_(photons_per_pixel), window_um_(window_um), threads_(threads) {}
  /// `scene` at this model's photon target (no ray count).
  simulate::Scene AtPhotonTarget(simulate::Scene scene) const {
    scene.trace.photons_per_pixel = photons_per_pixel_;
    scene.trace.rays = 0;
    return scene;
  }
  double photons_per_pixel_, window_um_;
  int threads_;
};

/// The exact wave image of a homogeneous sphere (simulate::MieImager).
class MieImageModel : public NoiselessImageModel {
 public:
  MieImageModel(double photons_per_pixel, double window_um, int threads)
      : NoiselessImageModel(photons_per_pixel, window_um, threads) {}
  ~MieImageModel() override;
  /// An evaluation whose Draw::across_key equals the last one's moves the last imager's sphere
  /// (simulate::MieImager::MoveAcross) instead of building a new one: its fields are kept.
  ModelImages Images(const simulate::Scene& scene, const Draw& draw,
                     uint64_t* rays_traced) override;

 private:
  std::unique_ptr<simulate::MieImager> last_;
  std::vector<double> last_key_;
};

/// The physical-optics image of any scene (simulate::PhysicalImager, rays that carry their
/// field). The window is fixed and the field rays are laid out as the first evaluation laid
/// them out (simulate::FieldLayouts), moved and scaled with the objects' bounds, so the image
/// changes continuously with every parameter (no cell count or refinement test flips).
class PhysicalImageModel : public NoiselessImageModel {
 public:
  PhysicalImageModel(double photons_per_pixel, double window_um, int threads)
      : NoiselessImageModel(photons_per_pixel, window_um, threads),
        layouts_(std::make_shared<simulate::FieldLayouts>()) {}
  ModelImages Images(const simulate::Scene& scene, const Draw& draw,
                     uint64_t* rays_traced) override;
  bool Relayout() override {
    layouts_ = std::make_shared<simulate::FieldLayouts>();
    return true;
  }

 private:
  std::shared_ptr<simulate::FieldLayouts> layouts_;
};

/// The scene as the ray model traces it: the light field's part `part` and, with `psf_os` > 1,
/// a camera psf_os times finer with psf_margin fine pixels beyond each side and no PSF (which
/// RayImageModel applies ray by ray).
simulate::Scene TracedScene(simulate::Scene s, simulate::SourceSpec::EdgePart part, int psf_os,
                            int psf_margin);

/// A fine count image of TracedScene (`os` times finer than the camera, `margin` fine pixels
/// beyond each side) summed to the camera's pixels with the PSF drawn ray by ray: the k-th ray
/// of a fine pixel lands at a point uniform within it plus a Gaussian offset of `sigma_fine`
/// fine pixels, drawn from its own stream (seed, plane, the pixel and k). The template stays a
/// Poisson sample whatever the PSF (a smoothing convolution would shrink its noise as sigma
/// grows, and the deviance would favour wide PSFs), and the draws are common random numbers
/// across evaluations, so the image changes smoothly with sigma. With `skip`, the rays below
/// skip's count of each pixel are left out: they took the pixel's first draws. threads: 0 =
/// every core; the image is the same for any number.
Image DrawPsf(const Image& fine, int os, int margin, double sigma_fine, uint64_t seed,
              uint32_t plane, const Image* skip, int threads);

/// The Monte Carlo ray tracer with common random numbers: every evaluation draws the same rays
/// (streams from Draw::seed), and rays that cannot meet an object are traced once per image,
/// seed and defocus and reused (the near/far split).
class RayImageModel : public ImageModel {
 public:
  struct Setup {
    size_t images = 0;
    int threads = 0;
    /// The sphere every object stays inside over the parameter box (the near/far split).
    Vec3 region_center;
    double region_radius = 0;
    bool split = false;       ///< reuse the rays that miss the region
    bool edge_split = false;  ///< the light field inside and beyond the NA as two populations
    double inside_share = 1;  ///< the part inside the NA's share of the rays (edge_split)
    int psf_os = 1, psf_margin = 0;  ///< PSF drawn per ray on a finer camera (psf_os > 1)
    double object_pixel_um = 0;
  };
  explicit RayImageModel(const Setup& setup) : setup_(setup) {}
  bool exact() const override { return false; }
  ModelImages Images(const simulate::Scene& scene, const Draw& draw,
                     uint64_t* rays_traced) override;
  double near_fraction() const override { return near_fraction_; }
  double background_seconds() const override { return background_seconds_; }
  /// Drops the near lists and backgrounds of the old region (the kept parts' images stay).
  void SetRegion(const Vec3& center, double radius) override;

 private:
  /// DrawPsf with this setup's fine camera and the PSF sigma in um at the object plane.
  Image ApplyPsf(const Image& fine, double sigma_um, uint64_t seed, uint32_t plane,
                 const Image* skip = nullptr) const;
  /// ApplyPsf of image i's counts: the background's rays, the first draws of their pixels,
  /// taken from a cache per (background, sigma, seed, plane); the rest drawn here. The same
  /// image as ApplyPsf of the whole (whole counts added in any order are exact).
  Image PsfOf(const Image& fine, const std::shared_ptr<const Image>& background, double sigma_um,
              uint64_t seed, uint32_t plane);
  // Rays that can meet an object, per (image, seed): the indices below `rays` (ascending).
  // Coarse-to-fine levels use the first n rays of the same streams, so a finer level extends
  // the list and the background instead of starting again.
  struct NearRays {
    uint64_t rays = 0;
    std::vector<uint64_t> list;
  };
  // The image of the other rays below `rays`, per (image, seed, defocus); replaced, not
  // changed, when more rays extend it.
  struct Background {
    uint64_t rays = 0;
    std::shared_ptr<const Image> image;
  };
  // One part's traced counts per image (before the PSF drawn per ray), for Draw::inside_key or
  // beyond_key, its seed and ray count; with the part's source weight and near share, and per
  // image the background its counts include (null: none).
  struct Traced {
    std::vector<double> key;
    uint64_t seed = 0, rays = 0;
    std::vector<Image> counts;
    std::vector<std::shared_ptr<const Image>> background;
    double weight = 0, near_fraction = 0;
  };
  // A background's rays with the PSF drawn (ApplyPsf), for one sigma, seed and plane.
  struct PsfBackground {
    std::shared_ptr<const Image> background;
    double sigma_um = 0;
    uint64_t seed = 0;
    uint32_t plane = 0;
    Image image;
  };
  /// The kept part with this key, seed and rays, or null (an empty key is never kept).
  static const Traced* Recall(const std::vector<Traced>& kept, const Traced& want);
  /// Keeps `t` (the last few per part) and returns it.
  static const Traced* Remember(std::vector<Traced>* kept, Traced t);
  Traced TraceInside(const simulate::Scene& full, const Traced& want, uint64_t* rays_traced);
  Traced TraceBeyond(const simulate::Scene& full, const Traced& want, double inside_weight,
                     uint64_t* rays_traced) const;
  /// The background of image i at n rays; extends `near` as needed. Null when it cannot be
  /// extended (fewer rays than already traced for this defocus): then trace everything.
  std::shared_ptr<const Image> BackgroundAt(const simulate::Simulator& sim, size_t i, uint64_t seed,
                                            double dz, uint64_t n, const simulate::RunControl& rc,
                                            uint64_t* rays_traced);
  Setup setup_;
  std::map<std::tuple<size_t, uint64_t>, NearRays> near_;
  std::map<std::tuple<size_t, uint64_t, double>, Background> background_;
  std::vector<Traced> inside_, beyond_;        // most recent last
  std::vector<PsfBackground> psf_background_;  // most recent last
  double near_fraction_ = 0;
  double background_seconds_ = 0;
};

}  // namespace raymatch::fit::internal
