#pragma once
// Extracting 3D properties from images: simulated images are optimised against experimental
// ones (paper section II.E, Fig. 9). A fit file names a scene, the experimental images with
// their defocus, the free parameters by their scene key, an error function, a method and a ray
// schedule (docs/fit.md).
//
// Noise model: an experimental pixel holds a Poisson count of mean mu(theta); the simulation
// traces `ray_factor` times more rays than the experiment recorded photons and is scaled down,
// so its own shot noise adds mu/ray_factor to the variance. With common random numbers every
// evaluation reuses the same ray streams, so the error function is not re-noised at every step.
#include <toml++/toml.h>

#include <array>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "raymatch/core/error.h"
#include "raymatch/core/image.h"

namespace raymatch::fit {

enum class ErrorFunction { kPoisson, kMse, kSsim, kMsSsim, kCwSsim };
const char* ErrorFunctionName(ErrorFunction e);  ///< "poisson", "mse", "1-ssim", ...

enum class Method { kGrid, kPattern, kLevenbergMarquardt };
const char* MethodName(Method m);  ///< "grid", "pattern", "lm"

/// How a fit ended. kFlat: a parameter leaves every pixel unchanged (the fit cannot move it);
/// kMaxEvaluations: the evaluation budget ran out; kFailed: the solver gave no usable solution.
enum class FitStatus { kNone, kConverged, kFailed, kMaxEvaluations, kFlat };
const char* StatusName(FitStatus s);  ///< "", "converged", "failed", "max_evaluations", "flat"

/// The step of a fit an evaluation belongs to: the search (grid points, pattern polls, LM
/// levels, the Gauss-Newton polish), the derivative sets and final steps at the optimum, the
/// repeated fits, the error-function slices, the images at a grid or pattern optimum, the
/// points of the profile-likelihood paths.
enum class Stage {
  kGrid,
  kPoll,
  kLm,
  kPolish,
  kFisher,
  kFinal,
  kRepeat,
  kSlice,
  kBest,
  kProfile,
  kStart,
  kScan,
  kHop
};
const char* StageName(Stage s);  ///< "grid", "poll", "lm", "polish", "fisher", "final", ...

/// One experimental image (photon counts after dark subtraction and gain).
struct FitImage {
  std::string file;
  double defocus_um = 0;
  std::string dark_file;     ///< subtracted in code values when given
  double gain_e_per_dn = 1;  ///< photons per code value after dark subtraction
  /// The camera's read noise (electrons rms, of the dark-subtracted image): the Poisson
  /// likelihood uses the shifted-Poisson approximation, e + r^2 ~ Poisson(mu + r^2), which
  /// matches the Poisson-Gaussian mean and variance (docs/fit.md, "Camera noise"). 0 = none.
  double read_noise_e = 0;
  /// Raw code values at or above this are saturated (0 = no check; `calibrate sphere` gives
  /// 2^bit_depth - 1). Saturated pixels, and with a dark frame pixels clipped at 0, are left
  /// out of the likelihood (their count is in fit.json).
  double saturation_dn = 0;
  Image usable;  ///< 1 where a pixel enters the likelihood, 0 where left out; empty: all
  size_t excluded_pixels = 0;
  Image photons;  ///< prepared image (filled by LoadFitSpec)
  FileLocation where;
};

/// A free parameter: a numeric value of the scene (or an image's defocus) by its key.
struct Parameter {
  std::string key;  ///< e.g. "object.drop.center_um[2]", "image[0].defocus_um"
  double lower = 0, upper = 0, start = 0;
  double step = 0;   ///< typical change: pattern mesh, grid spacing, FD step base
  int points = 0;    ///< grid: samples from lower to upper (0: from step)
  std::string unit;  ///< from the key's suffix (_um, _deg, ...) for reports
  /// A Gaussian prior (an independent measurement of the value, e.g. the calibration's): the
  /// fit minimises the deviance plus ((theta - prior_mean) / prior_sigma)^2, and the sigmas,
  /// bounds and profiles hold it. prior_sigma 0: none. prior_from says where it came from.
  double prior_mean = 0, prior_sigma = 0;
  std::string prior_from;
  FileLocation where;
};

/// The ranges a fit file's [rays] ray_factor, jacobian_seeds and [uncertainty] repeat_seeds
/// take (repeat_seeds: 0 or from 2).
inline constexpr double kMinRayFactor = 1.0 / 1024, kMaxRayFactor = 1024;
inline constexpr int kMinJacobianSeeds = 2, kMaxJacobianSeeds = 64, kMaxRepeatSeeds = 1000;

struct RaySchedule {
  double ray_factor = 1;                               ///< simulated rays per experimental photon
  std::vector<double> fractions{1.0 / 16, 0.25, 1.0};  ///< coarse-to-fine; last = final
  bool common_random_numbers = true;
  /// Photons per pixel of the experiment's flat background (0: the scene's trace value, or
  /// when the scene gives none, the median of the first image's border frame).
  double photons_per_pixel = 0;
  bool reuse_background = true;  ///< trace rays that miss every object only once
  /// Scale each simulated image to the experiment's total photons (the exposure's maximum-
  /// likelihood value, profiled out); false: the photon count is taken as known.
  bool fit_exposure = true;
  /// Treat the simulated counts as the Poisson sample they are: the template of each pixel is
  /// the count plus one ray (false: the plain count, which biases the fit by O(1/ray_factor);
  /// for comparisons only; docs/design/fit-estimator.md, "Finite rays").
  bool finite_ray_correction = true;
  /// The final polish also keeps steps that halve the predicted Gauss-Newton decrease (the
  /// score with a smooth chord Jacobian) instead of only those that lower the rough deviance
  /// of fixed ray streams (false: descents only, which stop short in a local dip).
  bool smooth_polish = true;
  /// Gauss-Newton polish at the final fraction after the coarse levels' search. false: when the
  /// final steps follow (jacobian_seeds > 2, Poisson error), they start from the
  /// coarse optimum instead (docs/design/fit-estimator.md, "Finite rays"); otherwise the
  /// polish runs anyway.
  bool polish = false;
  /// Independent ray-stream sets whose one-sided differences (forward and backward in turn, so
  /// that pairs make central differences) are averaged at the optimum, for the final steps and
  /// the uncertainties (2: the two sets the uncertainties
  /// need, no final steps). docs/design/fit-estimator.md, "Finite rays".
  int jacobian_seeds = 4;
  /// Pixel binning per fraction (empty: the smallest b with b^2 x ray_factor x fraction >= 1).
  std::vector<int> binning;
};

/// When the fit computes profile-likelihood intervals (docs/fit.md).
enum class ProfileMode { kAuto, kAlways, kNever };

struct FitSpec {
  std::string file;  ///< the fit file
  std::string scene_file;
  std::string calibration_file;  ///< set in the scene when not empty
  toml::table scene;             ///< the parsed scene (values changed per evaluation)
  std::vector<FitImage> images;
  std::vector<Parameter> parameters;
  ErrorFunction error = ErrorFunction::kPoisson;
  Method method = Method::kLevenbergMarquardt;
  RaySchedule rays;
  uint64_t seed = 1;
  int max_evaluations = 2000;
  int repeat_seeds = 3;  ///< repeated final fits with independent seeds
  bool cramer_rao = true;
  int slice_points = 7;  ///< error-function slices per parameter (0: none)
  /// Profile-likelihood intervals: kAuto where the curvature interval may not be trustworthy
  /// (a correlation above `profile_correlation`, a curvature that is not positive definite, a
  /// sigma above the parameter's step), kAlways for every parameter, kNever.
  ProfileMode profile = ProfileMode::kAuto;
  double profile_correlation = 0.9;
  bool uncertainties = true;  ///< false: search only (benchmarks)
  int threads = 0;
  /// The image model: "rays", "mie" (exact for spheres) or "physical" (rays that carry their
  /// field, any scene).
  std::string optics = "rays";
  /// The images come from a model without simulation noise (optics = "mie" or "physical"): one
  /// image per evaluation, no ray fractions, no repeats with other ray streams, and every
  /// (1 + 1 / k) of the finite-ray formulas is 1.
  bool exact_images() const { return optics != "rays"; }
  /// Search stages before the method's own search (the fit file's [search] table, docs/fit.md
  /// "Starts far from the truth"). `start_fit`: the same fit with the ray model (search only),
  /// whose optimum becomes the start. `scan`: parameters (indices) scanned in turn at this fit's
  /// model, each over its `points` from lower to upper with the others held; the best point
  /// becomes its start.
  std::shared_ptr<const FitSpec> start_fit;
  std::vector<size_t> scan;
  /// After the fit: the fit again from its optimum moved by -hop_step and +hop_step along
  /// parameter `hop` (-1: none), the lowest error kept, hops going on in the direction that
  /// lowered it (neighbouring valleys of a resonant sphere's likelihood).
  int hop = -1;
  double hop_step = 0;
  /// Simulated rays per experimental photon at the final level (infinite for exact images).
  double RaysPerPhoton() const;
};

/// Reads and checks a fit file: scene, images (read and prepared), parameter keys resolved in
/// the scene (a key that does not exist or is not numeric is an error naming the fit file's
/// line and the keys that exist). Throws Error "file:line:col: error: ...".
FitSpec LoadFitSpec(const std::string& path);

/// The same with the scene and/or the calibration given separately (empty: the fit file's):
/// `scene_override` replaces the fit file's `scene`; `calibration_override` (or the fit file's
/// `calibration` key) sets the scene's calibration file (light field, corrector, optics), e.g.
/// the one `raymatch run` just made.
FitSpec LoadFitSpec(const std::string& path, const std::string& scene_override,
                    const std::string& calibration_override = "");

struct Evaluation {
  std::vector<double> theta;
  double error = 0;
  double ray_fraction = 1;
  int bin = 1;        ///< pixel binning the error was computed on
  uint64_t rays = 0;  ///< rays traced in this evaluation (all images)
  uint64_t seed = 0;
  double seconds = 0;
  Stage stage = Stage::kLm;  ///< which step of the fit asked for it (StageName() in fit.json)
};

struct ParameterResult {
  std::string key, unit;
  double start = 0, best = 0, lower = 0, upper = 0;
  double prior_mean = 0, prior_sigma = 0;  ///< the Gaussian prior the fit used (sigma 0: none)
  std::string prior_from;                  ///< "calibration" or "fit file"
  double sigma_curvature =
      0;  ///< from the Poisson likelihood's curvature (Gauss-Newton) at the optimum
  /// The reported uncertainty. With the final steps (the default): the covariance of their
  /// estimating equation's root, A^-1 (B_e + B_t) A^-T (docs/design/fit-estimator.md, "Finite
  /// rays"), which holds the experiment's and the templates' shot noise and the derivatives'
  /// Monte Carlo noise. Without them: sigma_curvature x sqrt(1 + 1/k), k = ray_factor x final
  /// fraction.
  double sigma = 0;
  /// The part of sigma from the Monte Carlo noise of the derivative images that the final steps'
  /// score used (their scatter between independent ray-stream sets): a noisy derivative turns
  /// the residuals' noise into a scatter of the root of the score equation.
  double sigma_derivatives = 0;
  /// The part of sigma from the simulation's own noise (the template's shot noise and the
  /// derivatives'): what the fits of one experiment scatter by over independent ray streams
  /// (`seed`); the rest of sigma is the experiment's shot noise.
  double sigma_simulation = 0;
  /// The final steps' derivative image of this parameter: "as traced", "smoothed" ([1/4, 1/2,
  /// 1/4] in x and y) or "a as traced + b smoothed", the mixture weighted for the smallest
  /// variance of the root; "" without final steps.
  std::string score_derivative;
  /// sigma before the model-mismatch inflation (equal to sigma when the fit is consistent).
  double sigma_statistical = 0;
  double sigma_repeat = 0;      ///< scatter of repeated fits with independent simulation seeds
  double sigma_cramer_rao = 0;  ///< Cramer-Rao bound of the image(s), noise-free expectation
  /// Expected precision including the simulation's own shot noise:
  /// CRB x sqrt(1 + 1/(ray_factor x final fraction)).
  double sigma_expected = 0;
  bool at_bound = false;
  /// The error along this axis through the optimum: the mean over two independent ray-stream
  /// sets, and its ray noise (one standard deviation of a point's mean about the slice's shape,
  /// from the two sets' differences; 0 with fewer than 3 points).
  std::vector<double> slice_x, slice_error;
  double slice_noise = 0;
  /// Profile-likelihood interval (68 %), computed where the curvature interval may not be
  /// trustworthy; `profile_reason` says why (empty: not computed). The profile deviance is
  /// followed along the linearised profile path over +-2 sigma (the reported sigma, simulation
  /// noise included) and scaled to that sigma, so for a quadratic likelihood the interval is
  /// best +- sigma; the ends are where it is 1 above its minimum. An open end (no such rise
  /// within the range followed, or a bound) is reported at that range's end and flagged.
  std::string profile_reason;
  double profile_lower = 0, profile_upper = 0;
  double profile_lower_sigmas = 0, profile_upper_sigmas = 0;  ///< (end - best) / sigma
  bool profile_lower_open = false, profile_upper_open = false;
  /// The profile curve: offsets in units of sigma and the scaled deviance above the profile's
  /// minimum there.
  std::vector<double> profile_t, profile_delta;  ///< error along this axis through the optimum
};

/// Does the model describe the image? Computed at the optimum on the final level's pixels.
/// The template mean of a pixel whose simulated count is `photons / w` rays of weight w photons:
/// the count plus one ray. The fit solves the score equation sum_q G_q (1 - e_q / T_q) = 0
/// (G = dT/dtheta; the gradient of the deviance), whose terms must vanish on average at the
/// truth. A simulated count m is Poisson with mean k mu (k = 1/w rays per photon), and the
/// plain template T = m/k has E[1/T] = (1 + 1/(k mu) + ...)/mu: every pixel pulls towards a
/// brighter template by 1/k photons, which biases each parameter that changes the light in dark
/// regions (the index and radius of a drop: several sigma at k = 1). With T = (m + 1)/k,
/// E[1/(m + 1)] = (1 - exp(-k mu))/(k mu) exactly for a Poisson m (the classic negative moment;
/// Chao and Strawderman, J. Am. Stat. Assoc. 67, 429 (1972)), so E[e/T] = 1 up to exp(-k mu).
/// This is the light form of the Barlow-Beeston treatment of finite Monte Carlo templates
/// (Comput. Phys. Commun. 77, 219 (1993); Conway, arXiv:1103.0354) for a score-equation fit.
inline double TemplateMean(double photons, double photons_per_ray,
                           bool finite_ray_correction = true) {
  return photons + (finite_ray_correction ? 1.0 : 0.0) * photons_per_ray;
}

struct GoodnessOfFit {
  /// Poisson deviance at the point tested: the template's best point, one weighted
  /// least-squares step from the estimate along the fit's derivative images (`step`), or the
  /// estimate itself where there is no step.
  double deviance = 0;
  double estimate_deviance = 0;  ///< the deviance at the estimate itself
  std::vector<double> step;      ///< that step per parameter (empty: none taken)
  double expected = 0;           ///< its expectation for a correct model (experiment's and
                                 ///< simulation's Poisson noise, fitted parameters removed)
  double sd = 0;                 ///< its standard deviation
  double z = 0;                  ///< (deviance - expected) / sd
  double reduced = 1;            ///< deviance / expected
  size_t pixels = 0;
  /// Residual structure: residuals (experiment less the template's plain count) summed over
  /// blocks of block_px x block_px pixels, each block normalised to unit variance; their
  /// chi-square against the block count, block_z its Wilson-Hilferty normal deviate.
  int block_px = 8;
  size_t blocks = 0;
  double block_chi2 = 0, block_z = 0, block_reduced = 1;
  /// Correlation of neighbouring Pearson residuals (right and lower neighbours): 0 +-
  /// 1/sqrt(pairs).
  double neighbour_correlation = 0, neighbour_z = 0;
  bool mismatch = false;  ///< any of the three z above 3 (one-sided, p < 0.0014 each;
                          ///< the neighbour test also needs a correlation above 0.05)
  /// Factor applied to every sigma: sqrt of the larger of the reduced deviance and the reduced
  /// block chi-square when `mismatch`, else 1.
  double sigma_inflation = 1;
  std::string verdict;  ///< "consistent with the noise" or "model mismatch: ..."
  /// Independent ray-stream sets whose mean image at the estimate is the template tested (the
  /// derivative sets, `jacobian_seeds`; 1: the main streams' image alone).
  size_t template_sets = 1;
};

struct FitResult {
  bool converged = false;
  FitStatus status = FitStatus::kNone;  ///< StatusName() in fit.json, the terminal and the report
  std::string message;
  std::vector<ParameterResult> parameters;
  std::vector<std::vector<double>> correlation;      ///< from the curvature covariance
  std::vector<std::vector<double>> crb_correlation;  ///< from the inverse Fisher information
  double best_error = 0;
  /// The final steps' estimating equation at the estimate, Q = U^T (B_e + B_t)^-1 U: 0 at its
  /// root, below 0.05 where the steps converged; Q > 1 puts the estimate more than one
  /// statistical sigma from the root along some direction. Negative: no final steps ran.
  double final_steps_q = -1;
  GoodnessOfFit goodness;  ///< Poisson error only (empty otherwise)
  std::vector<Evaluation> evaluations;
  std::vector<Image> best_images;    ///< expected photons per image at the optimum
  std::vector<Image> residuals;      ///< (sim - exp)/sqrt(sim (1 + 1/ray_factor))
  uint64_t photon_matched_rays = 0;  ///< rays per image at ray fraction 1 before ray_factor
  double region_radius_um = 0;       ///< region the objects can occupy (rays outside reused)
  double object_pixel_um = 0;        ///< the camera's pixel at the object plane (0: unknown)
  std::array<double, 3> region_center_um{};
  /// The region after the search, narrowed to two steps of each key about its optimum (0: not
  /// narrowed); its centre.
  double focused_region_radius_um = 0;
  std::array<double, 3> focused_region_center_um{};
  double near_ray_fraction = 0;  ///< share of rays re-traced per evaluation (in the search)
  /// Grid landscape (method grid): axes values and errors in row-major order (last axis fastest).
  std::vector<std::vector<double>> grid_axes;
  std::vector<double> grid_errors;
  std::vector<std::pair<std::string, double>> seconds;  ///< time split: setup, background, ...
  double total_seconds = 0;
};

struct FitOptions {
  int threads = 0;        ///< 0: the fit file's value, then all cores
  bool progress = false;  ///< progress lines on stderr
};

/// Runs the fit. Throws Error on bad input or when no evaluation succeeds.
FitResult RunFit(const FitSpec& spec, const FitOptions& options = {});

/// Writes fit.json, evaluations.csv, best and residual images (TIFF + PNG), slice/landscape
/// plots and report.html into `dir` (created). Returns the report's path.
std::string WriteFitOutputs(const FitSpec& spec, const FitResult& result, const std::string& dir);

/// One row of a grid study: where one error function's grid minimum lands at one ray fraction.
struct GridStudyRow {
  std::string error;
  double fraction = 1;
  int bin = 1;
  size_t evaluations = 0;
  double seconds = 0;
  std::vector<double> best;
};

/// The paper's Fig. 9 study: the fit file's grid evaluated at each ray fraction with each error
/// function (search only). For `raymatch bench fit-grid`.
std::vector<GridStudyRow> RunGridStudy(const FitSpec& spec, const std::vector<double>& fractions,
                                       const std::vector<ErrorFunction>& errors,
                                       const FitOptions& options = {});

// ----------------------------------------------------------------------------------------------
// Building blocks (public for tests and benchmarks).

/// The numeric scene value at `key` (see docs/fit.md for the key syntax); throws Error listing
/// the keys that exist when it is missing or not a number.
double SceneValue(const toml::table& scene, const std::string& key, const std::string& scene_file);

/// An image key of a fit or a sensitivity study: image[i].defocus_um, image[i].background_photons,
/// image[i].background_slope_x or _y with i < `images`; returns i and the field name, nullopt
/// for any other key (ImageKeysHelp says what they are). A malformed key throws Error.
std::optional<std::pair<size_t, std::string>> ParseImageKey(const std::string& key, size_t images);
std::string ImageKeysHelp(size_t images);

/// The unit a key's name ends in ("um", "mm", "deg", "K", "kg_m3"; "" for none).
std::string UnitOf(const std::string& key);

/// Sets the numeric scene value at `key` (which must exist).
void SetSceneValue(toml::table& scene, const std::string& key, double value,
                   const std::string& scene_file);

/// Poisson deviance 2 sum[mu - e + e ln(e/mu)] of counts `e` against means `mu` (mu floored at
/// 1e-6 so a zero-mean pixel with counts stays finite).
double PoissonDeviance(const Image& e, const Image& mu);

/// Fisher information sum_p (dmu_i)(dmu_j)/mu over pixels from mean images and their
/// derivatives (one image per parameter, per experimental image). Pixels with mu <= 0 skipped.
std::vector<std::vector<double>> FisherInformation(const std::vector<Image>& mu,
                                                   const std::vector<std::vector<Image>>& dmu);

/// The same from two independent Monte Carlo estimates of the derivatives:
/// sum (dmu_a_i dmu_b_j + dmu_b_i dmu_a_j) / (2 (mu + r_k^2)). Unlike the square of one noisy
/// estimate, whose noise adds a positive bias (information that is not there), it is unbiased.
/// `read_variance` (empty: none): per image k the read noise variance r_k^2 in photons^2 that
/// each pixel's variance carries besides mu (the shifted-Poisson likelihood, docs/fit.md).
std::vector<std::vector<double>> FisherInformation(const std::vector<Image>& mu,
                                                   const std::vector<std::vector<Image>>& dmu_a,
                                                   const std::vector<std::vector<Image>>& dmu_b,
                                                   const std::vector<double>& read_variance = {});

/// Inverse of a symmetric positive definite matrix (Eigen LDLT); empty when singular.
std::vector<std::vector<double>> InverseSpd(const std::vector<std::vector<double>>& m);

}  // namespace raymatch::fit
