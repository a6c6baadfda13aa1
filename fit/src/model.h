#pragma once
// Expected images for a parameter vector, traced with common random numbers, re-tracing only
// the rays that can meet an object.
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <tuple>

#include "binding.h"
#include "image_model.h"
#include "raymatch/core/vec.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/tracer.h"

namespace raymatch::fit {

/// Expected images of one evaluation: photons per pixel (the simulated counts times the
/// photons one ray stands for) and, per image, that weight. The weight is what the likelihood
/// needs to treat the simulated counts as the Poisson sample they are (see DevianceResiduals).
/// A number with `prec` significant digits, for messages.
std::string Fmt(double v, int prec = 6);

struct Simulated {
  std::vector<Image> photons;
  std::vector<double> photons_per_ray;
  bool finite_ray_correction = true;  ///< template = count + one ray (TemplateMean)
};

class FitModel {
 public:
  /// Prepares the model: the region the objects can occupy over the parameter box, a fixed
  /// source field (so every evaluation draws the same rays), the photon-matched ray count.
  /// Keeps a reference to `spec`, which must outlive the model.
  FitModel(const FitSpec& spec, int threads, std::function<void(const std::string&)> say);
  FitModel(FitSpec&&, int, std::function<void(const std::string&)>) = delete;

  /// Expected photon images (one per experimental image) at `theta` with `fraction` of the
  /// final rays and ray streams `seed`. Adds the rays traced to `*rays_traced`.
  Simulated Expected(const std::vector<double>& theta, double fraction, uint64_t seed,
                     uint64_t* rays_traced);

  /// The error function against the experiment (lower is better), on images binned `bin` x
  /// `bin` (sums of Poisson counts are Poisson; a remainder row/column is dropped).
  double Error(const Simulated& sim, int bin = 1) const;

  /// Signed deviance residuals of every (binned) pixel of every image: sum of squares = deviance.
  /// The template is the simulated count plus one ray (TemplateMean): the simulation is a
  /// Poisson sample itself, and with the plain count the score equation pulls every pixel
  /// towards a template 1/k photons brighter (k rays per photon), which biases every parameter
  /// that changes the light in dark regions (docs/design/fit-estimator.md, "Finite rays").
  void DevianceResiduals(const Simulated& sim, int bin, double* out) const;

  /// The final steps' estimating function (fit/src/uncertainty.cpp, FinalSteps): per
  /// parameter sum_q dmu_qi (e_q - m_q) / V_q, m the plain binned count of `sim` (no extra
  /// ray), V = max(reference, kReferenceFloor) + the read-noise shift, `reference` (per image,
  /// unbinned photons) traced with rays independent of `sim`'s. For any dmu and reference fixed
  /// independently of e and of `sim`'s rays it vanishes on average at the truth in every pixel,
  /// dark ones included (E[e - m] = 0), where e / (count + one ray) is biased by -exp(-k mu).
  std::vector<double> Score(const Simulated& sim, const std::vector<std::vector<Image>>& dmu,
                            const std::vector<Image>& reference, int bin) const;

  /// The Poisson log-likelihood's score with given derivative images, sum_q dmu_qi (e_q / T_q -
  /// 1), T the template (count plus one ray, TemplateOf): its weights follow the template, so
  /// differences of it along a path see the Poisson likelihood's asymmetry (the profile
  /// likelihood's paths; fit/src/profile.cpp).
  std::vector<double> PoissonScore(const Simulated& sim, const std::vector<std::vector<Image>>& dmu,
                                   int bin) const;

  /// sum over usable (binned) pixels of a_qi b_qj / V_q with Score's weights 1 / V
  /// (row i, column j; not symmetrised).
  std::vector<std::vector<double>> CrossInformation(const std::vector<std::vector<Image>>& a,
                                                    const std::vector<std::vector<Image>>& b,
                                                    const std::vector<Image>& reference,
                                                    int bin) const;

  /// The least variance a reference template gives a pixel in Score's weights (photons): one
  /// photon, so a pixel no reference ray reached does not get an unbounded weight.
  static constexpr double kReferenceFloor = 1.0;

  /// The deviance's mean and standard deviation for a correct model with templates `ts`
  /// (TemplateOf per image of `sim`, binned) and `parameters` fitted.
  std::pair<double, double> ExpectedDeviance(const std::vector<std::vector<double>>& ts,
                                             const Simulated& sim, int bin,
                                             size_t parameters) const;

  /// Goodness of fit at the optimum: deviance against its expectation, block chi-square of the
  /// Pearson residuals, neighbour correlation, the verdict and the sigma inflation.
  ///
  /// With derivative images `dmu_a` and `dmu_b` ([image][parameter], photons per unit, at the
  /// estimate; two independent halves of the derivative sets, or one set twice) the tests are
  /// taken at the template's own best point: one weighted least-squares step from the estimate
  /// along them (StepToTheTemplatesBest). An estimate with simulation noise lies off the point
  /// where the experiment and that template agree best, by its own ray-stream error (the final
  /// steps' root, whose sigma can be mostly the simulation's); the tests' null distribution
  /// (each fitted parameter removes one unit) holds at that point, not at the estimate. A
  /// misfit no parameter can absorb is left whole.
  GoodnessOfFit Goodness(const Simulated& sim, int bin, size_t parameters,
                         const std::vector<std::vector<Image>>& dmu_a = {},
                         const std::vector<std::vector<Image>>& dmu_b = {}) const;

  /// The Gauss-Newton step from the templates `ts` (binned, TemplateOf) that minimises the
  /// Pearson-weighted squared residuals along the derivative images: the normal matrix from
  /// the two halves' cross products, the right-hand side from their mean (returned binned in
  /// `*mean_dmu` when asked). Empty: no derivative images.
  std::vector<double> GaussNewtonStep(const Simulated& sim, int bin,
                                      const std::vector<std::vector<Image>>& dmu_a,
                                      const std::vector<std::vector<Image>>& dmu_b,
                                      const std::vector<std::vector<double>>& ts,
                                      std::vector<std::vector<Image>>* mean_dmu = nullptr) const;

  /// The templates (TemplateOf) of `sim`'s images, binned.
  std::vector<std::vector<double>> Templates(const Simulated& sim, int bin) const;

  /// GaussNewtonStep from the templates of `sim`.
  std::vector<double> TemplateStep(const Simulated& sim, int bin,
                                   const std::vector<std::vector<Image>>& dmu_a,
                                   const std::vector<std::vector<Image>>& dmu_b) const;

  /// The Poisson deviance of the experiment against the templates `ts` (binned, TemplateOf).
  double TemplatesDeviance(const std::vector<std::vector<double>>& ts, int bin) const;

  /// GaussNewtonStep moving the templates `ts` linearly along the mean derivative images, whole
  /// or halved while that lowers the deviance more (for exact images, whose derivatives carry
  /// no noise; a noisy derivative image adds its noise times the step); applies it to `ts` and
  /// returns it (per parameter: zeros where no step lowers the deviance; empty: no derivative
  /// images).
  std::vector<double> StepToTheTemplatesBest(const Simulated& sim, int bin,
                                             const std::vector<std::vector<Image>>& dmu_a,
                                             const std::vector<std::vector<Image>>& dmu_b,
                                             std::vector<std::vector<double>>* ts) const;
  size_t num_residuals(int bin = 1) const;

  /// Forgets the binned experiment: after the images of the FitSpec this model reads (by
  /// reference) were changed in place.
  void ExperimentChanged() {
    std::lock_guard<std::mutex> lk(binned_mutex_);
    binned_experiment_.clear();
    binned_usable_.clear();
  }

  /// The binning a ray fraction gets: the fit file's, or the smallest b with
  /// b^2 x ray_factor x fraction >= 1 (the simulation's counts per binned pixel at least the
  /// experiment's photons per pixel, so its shot noise does not dominate the error).
  int BinAt(size_t level) const;

  /// The additive background of image i at `theta` (its image[i].background_* keys: level in
  /// photons per pixel, slopes in photons per pixel per pixel about the centre, +y = down the
  /// rows); empty when the image has none.
  Image BackgroundOf(const std::vector<double>& theta, size_t i, int width, int height) const;

  /// Rays per image at `fraction` (ray_factor x photon-matched x fraction).
  uint64_t RaysAt(double fraction) const;
  /// Counts -> photons scale at `fraction`.
  double ScaleAt(double fraction) const;

  uint64_t photon_matched_rays() const { return photon_matched_rays_; }
  /// With the near/far split: the region the objects stay inside narrowed to the one they
  /// occupy over the box of `steps` times each moving key's step about theta (within its
  /// bounds), where that is smaller. Later evaluations re-trace only the rays that pass near
  /// it, with the same images (the rays between the two regions miss every object either way);
  /// an evaluation whose objects leave it traces every ray. Returns whether it narrowed.
  bool FocusRegion(const std::vector<double>& theta, double steps);
  /// Lets an image model whose sampling follows its first evaluation (physical optics' field
  /// rays) lay it out afresh at the next one (ImageModel::Relayout); false: it keeps none.
  bool Relayout() { return images_->Relayout(); }
  const Vec3& region_center() const { return region_center_; }
  double region_radius() const { return region_radius_; }
  double near_fraction() const { return images_->near_fraction(); }
  /// The camera's pixel at the object plane (micrometres, at the start values).
  double object_pixel_um() const { return object_pixel_um_; }
  double background_seconds() const { return images_->background_seconds(); }
  /// The scene with `theta` applied: the scene built once with the typed keys patched in
  /// (Binding), or read again when a key has no typed patch.
  simulate::Scene SceneAt(const std::vector<double>& theta) const;
  /// The same scene read from the scene file with every key set there (what SceneAt gives
  /// without typed patches; for its test).
  simulate::Scene SceneByReading(const std::vector<double>& theta) const;
  /// What each parameter's key sets, resolved once.
  const std::vector<internal::Binding>& bindings() const { return bindings_; }
  /// The image defocus values at `theta`.
  std::vector<double> DefocusAt(const std::vector<double>& theta) const;

 private:
  /// sum over image i's usable pixels p (binned) of dmu[i][a]_p f_i(p), f_i = residual(i) per
  /// binned pixel: the projection Score and PoissonScore share.
  std::vector<double> Project(const std::vector<std::vector<Image>>& dmu, int bin,
                              const std::function<std::vector<double>(size_t)>& residual) const;
  /// Scales image i's counts by the exposure (fitted or `scale`), adds its background keys and
  /// appends it to `out`.
  /// `s` with the images' defocus at `theta` and the fixed source field, checked.
  simulate::Scene Finished(simulate::Scene s, const std::vector<double>& theta) const;
  /// The corners of the box [lo, hi] in the keys that move objects (or, for many of them, its
  /// axis end points), the other keys at `at`.
  std::vector<std::vector<double>> Corners(const std::vector<double>& at,
                                           const std::vector<double>& lo,
                                           const std::vector<double>& hi) const;
  /// The sphere (centre, radius) with a safety margin that holds these objects' bounds (radius
  /// 0: none).
  static std::pair<Vec3, double> RegionOf(const std::vector<std::pair<Vec3, double>>& bounds);
  void AddExposureAndBackground(const std::vector<double>& theta, size_t i, Image counts,
                                double scale, Simulated* out) const;
  const FitSpec& spec_;
  std::vector<internal::Binding> bindings_;
  simulate::Scene built_;  // the scene file read once (typed keys are patched into copies)
  bool read_per_evaluation_ = false;  // a scene key without a typed patch
  int threads_;
  std::function<void(const std::string&)> say_;
  bool split_allowed_ = true;
  // Nuisance keys that keep the near/far split (docs/design/fit-estimator.md, "Nuisances that
  // keep the split"): with the light field's edge fitted, the parts inside and beyond the NA
  // are separate ray populations (the inside rays do not depend on the edge); with the PSF
  // fitted, the rays are traced onto a camera `psf_os_` times finer with `psf_margin_` fine
  // pixels beyond each side and each ray's PSF offset is drawn there (RayImageModel).
  bool edge_split_ = false;
  int psf_os_ = 1, psf_margin_ = 0;
  double object_pixel_um_ = 0;  // the camera's pixel at the object plane (at the start)
  std::unique_ptr<internal::ImageModel> images_;
  double field_radius_ = 0;  // fixed source field radius (0: the scene's own)
  Vec3 region_center_;
  double region_radius_ = 0;
  uint64_t photon_matched_rays_ = 0;
  double data_range_ = 1;  // L for the SSIM family (largest experimental pixel)
  mutable std::map<int, std::vector<Image>> binned_experiment_;
  mutable std::map<int, std::vector<Image>> binned_usable_;
  mutable std::mutex binned_mutex_;
  /// The experiment binned `bin` x `bin`, shifted by the read noise for the Poisson error.
  const std::vector<Image>& Experiment(int bin) const;
  /// Photons added to image i's binned pixels for the shifted-Poisson approximation of read
  /// noise (r^2 per read-out; 0 without read noise or for the non-Poisson errors).
  double ReadShift(size_t i, int bin) const;
  /// Image i's pixels that enter the likelihood, binned (empty images: all of them).
  const std::vector<Image>& Usable(int bin) const;
  std::vector<double> TemplateOf(const Image& binned, const Simulated& sim, size_t i,
                                 int bin) const;
};

}  // namespace raymatch::fit
