#pragma once
// The fit's internals shared by the search (fit.cpp) and the uncertainties (uncertainty.cpp):
// the evaluation runner, finite differences over ray-stream sets and the searches the repeated
// fits reuse. Not installed.
#include <unistd.h>

#include <Eigen/Dense>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <deque>
#include <functional>
#include <string>
#include <vector>

#include "model.h"
#include "raymatch/fit/fit.h"

namespace raymatch::fit::internal {

using Clock = std::chrono::steady_clock;
/// Seed offsets of the ray streams beside the main ones (spec.seed): derivative set s at the
/// optimum uses seed + s kDerivativeSetSeedStride, repeated fit k seed + k kRepeatSeedStride,
/// and evaluation n without common random numbers seed + n kFreshSeedStride. Distinct strides
/// keep the streams of the three apart for any practical count.
inline constexpr uint64_t kDerivativeSetSeedStride = 7777777;
inline constexpr uint64_t kRepeatSeedStride = 1000003;
inline constexpr uint64_t kFreshSeedStride = 7919;
/// After the search the near/far split's region shrinks to the objects over this many steps of
/// each key about the optimum (FitModel::FocusRegion): four times a derivative's half step,
/// wider than the final steps, profiles and slices go (an evaluation outside traces every ray).
inline constexpr double kFocusSteps = 2;

/// Per image, the read noise variance in photons^2 (FisherInformation's read_variance).
inline std::vector<double> ReadVariance(const FitSpec& spec) {
  std::vector<double> v;
  for (const FitImage& im : spec.images) v.push_back(im.read_noise_e * im.read_noise_e);
  return v;
}

inline double Since(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

using Matrix = std::vector<std::vector<double>>;

/// The public API's row-major nested vectors <-> Eigen (element copies, nothing else).
inline Eigen::MatrixXd ToEigen(const Matrix& m) {
  const auto rows = static_cast<Eigen::Index>(m.size());
  const auto cols = static_cast<Eigen::Index>(m.empty() ? 0 : m[0].size());
  Eigen::MatrixXd a(rows, cols);
  for (Eigen::Index i = 0; i < rows; ++i)
    for (Eigen::Index j = 0; j < cols; ++j) a(i, j) = m[size_t(i)][size_t(j)];
  return a;
}
inline Matrix FromEigen(const Eigen::MatrixXd& a) {
  Matrix m(size_t(a.rows()), std::vector<double>(size_t(a.cols())));
  for (Eigen::Index i = 0; i < a.rows(); ++i)
    for (Eigen::Index j = 0; j < a.cols(); ++j) m[size_t(i)][size_t(j)] = a(i, j);
  return m;
}

/// The Gaussian priors' share of the error, sum ((theta - mean) / sigma)^2 over the parameters
/// that have one (Parameter::prior_sigma): the fit minimises the deviance plus this.
inline double PriorPenalty(const FitSpec& spec, const std::vector<double>& th) {
  double s = 0;
  for (size_t i = 0; i < th.size(); ++i) {
    const Parameter& p = spec.parameters[i];
    if (p.prior_sigma > 0) s += std::pow((th[i] - p.prior_mean) / p.prior_sigma, 2);
  }
  return s;
}

/// The priors' precisions 1 / sigma^2 (0 where none): the information they add.
inline Eigen::VectorXd PriorPrecision(const FitSpec& spec) {
  Eigen::VectorXd l = Eigen::VectorXd::Zero(Eigen::Index(spec.parameters.size()));
  for (size_t i = 0; i < spec.parameters.size(); ++i)
    if (spec.parameters[i].prior_sigma > 0)
      l(Eigen::Index(i)) = 1 / std::pow(spec.parameters[i].prior_sigma, 2);
  return l;
}

/// Evaluations with bookkeeping: the record of every evaluation, the best so far, progress.
class Runner {
 public:
  /// Keeps a reference to `spec` (which must outlive the Runner) and a copy of `opt`.
  Runner(const FitSpec& spec, FitOptions opt, FitResult* res)
      : spec_(spec),
        opt_(opt),
        res_(res),
        t0_(Clock::now()),
        model_(spec, opt.threads > 0 ? opt.threads : spec.threads,
               [&](const std::string& m) { Say(m); }) {}

  Runner(FitSpec&&, FitOptions, FitResult*) = delete;  // would keep a reference to a temporary

  FitModel& model() { return model_; }

  /// The image model lays its kept sampling out afresh (FitModel::Relayout); the images kept
  /// from the old one are dropped.
  void Relayout() {
    if (!model_.Relayout()) return;
    cache_.clear();
    best_error_ = -1;
  }

  void Say(const std::string& m) {
    if (!opt_.progress) return;
    std::fprintf(stderr, "%sraymatch fit: %s\n", isatty(2) ? "\r\033[K" : "", m.c_str());
  }

  /// Expected images at `th` with the ray fraction and binning of schedule level `level`.
  Simulated Images(const std::vector<double>& th, size_t level, uint64_t seed, Stage stage,
                   double* error) {
    // With fixed ray streams an image is a function of (theta, level, seed): the searches come
    // back to points they have traced (Ceres evaluates the Jacobian where it accepted a step;
    // the uncertainties start from where the polish ended), so recent images are kept. An
    // exact image model's images do not depend on the seed: the uncertainties' derivative set
    // is then the polish's last stencil.
    for (size_t i = 0; i < th.size(); ++i)  // never a NaN into the tracer: an error, not a crash
      if (!std::isfinite(th[i]))
        throw Error("fit: internal error: " + spec_.parameters[i].key +
                    " is not a finite number at a point the fit asked for (please report)");
    for (const Cached& c : cache_)
      if (c.level == level && (c.seed == seed || spec_.exact_images()) && c.theta == th) {
        if (error) *error = c.error;
        return c.images;
      }
    const auto t0 = Clock::now();
    const double fraction = spec_.rays.fractions[level];
    Evaluation ev;
    ev.theta = th;
    ev.ray_fraction = fraction;
    ev.seed = seed;
    ev.stage = stage;
    Simulated mu = model_.Expected(th, fraction, seed, &ev.rays);
    ev.bin = model_.BinAt(level);
    ev.error = model_.Error(mu, ev.bin) + PriorPenalty(spec_, th);
    ev.seconds = Since(t0);
    if (error) *error = ev.error;
    res_->evaluations.push_back(ev);
    if (cache_.size() >= 2 * th.size() + 6) cache_.pop_front();  // a polish iteration's images
    cache_.push_back({th, level, seed, ev.error, mu});
    if (stage != Stage::kFisher && stage != Stage::kRepeat && stage != Stage::kSlice &&
        stage != Stage::kProfile &&
        (best_error_ < 0 || fraction > best_fraction_ ||
         (fraction == best_fraction_ && ev.error < best_error_))) {
      best_error_ = ev.error, best_fraction_ = fraction;
    }
    // Progress: a rewritten line on a terminal (at most twice a second), else a line every 10 s.
    const double now = Since(t0_);
    if (opt_.progress && now - last_progress_ >= (tty_ ? 0.5 : 10.0)) {
      last_progress_ = now;
      // An exact image model has no rays: its fractions only name the levels.
      const std::string model =
          spec_.exact_images() ? "exact image" : "ray fraction " + Fmt(fraction, 3);
      std::fprintf(stderr,
                   "%sraymatch fit: %-8s eval %4zu of at most %d  error %-12s best %-12s "
                   "%-19s  %.0f s%s",
                   tty_ ? "\r\033[K" : "", StageName(stage), res_->evaluations.size(),
                   spec_.max_evaluations, Fmt(ev.error).c_str(), Fmt(best_error_).c_str(),
                   model.c_str(), now, tty_ ? "" : "\n");
      std::fflush(stderr);
    }
    return mu;
  }

  double Eval(const std::vector<double>& th, size_t level, uint64_t seed, Stage stage) {
    double e = 0;
    Images(th, level, seed, stage, &e);
    return e;
  }

  bool Budget() const { return int(res_->evaluations.size()) < spec_.max_evaluations; }
  size_t Count() const { return res_->evaluations.size(); }

  /// The seed of the streams used at every evaluation of the main fit (common random numbers),
  /// or a fresh one per evaluation when they are switched off.
  uint64_t Seed() {
    return spec_.rays.common_random_numbers ? spec_.seed : spec_.seed + kFreshSeedStride * ++fresh_;
  }

 private:
  const FitSpec& spec_;
  const FitOptions opt_;
  FitResult* res_;
  Clock::time_point t0_;
  FitModel model_;
  double best_error_ = -1, best_fraction_ = 0;
  bool tty_ = isatty(2) != 0;
  double last_progress_ = -1e9;
  uint64_t fresh_ = 0;
  struct Cached {
    std::vector<double> theta;
    size_t level;
    uint64_t seed;
    double error;
    Simulated images;
  };
  std::deque<Cached> cache_;
};

inline std::vector<double> Clip(std::vector<double> th, const FitSpec& spec) {
  for (size_t i = 0; i < th.size(); ++i)
    th[i] = std::clamp(th[i], spec.parameters[i].lower, spec.parameters[i].upper);
  return th;
}

/// Differences of the expected images and of the deviance residuals with common random numbers
/// (the same ray streams on both sides). kCentral: theta +- step/2 (Levenberg-Marquardt, the
/// polish; twice that half-width gave case A's radius an RMS error of 2.9 Cramer-Rao bounds
/// instead of 1.8 when the fit's root used these derivatives directly, docs/performance.md),
/// one-sided at a bound. kForward / kBackward: theta and theta +- step/2 (backward / forward at
/// a bound): P + 1 images instead of 2P + 1, at twice the counting noise (half the span; a whole
/// step's span made case A's x sigma 1.34x short of its scatter); the final steps' derivative
/// sets alternate them so that each half's mean is the central difference over +-step/2
/// (uncertainty.cpp, FinalSteps). `with_center` false (central only): the image at theta is
/// not traced, and `mu` and `residuals` stay empty (the derivative sets at the optimum when no
/// final steps use their images: one image fewer per set).
enum class Stencil { kCentral, kForward, kBackward };

struct Differences {
  Simulated mu;                         // at theta
  std::vector<std::vector<Image>> dmu;  // [image][parameter] d mu / d theta_i
  Eigen::MatrixXd jacobian;             // residuals x parameters
  Eigen::VectorXd residuals;
  std::vector<bool> flat;  // parameter leaves every pixel unchanged
  std::vector<int> side;   // per parameter: +1 forward, -1 backward (one-sided), 0 central
};

Differences Differentiate(Runner& run, const FitSpec& spec, const std::vector<double>& th,
                          size_t level, uint64_t seed, Stage stage, Stencil stencil,
                          bool with_center = true);

/// The mean of sets[first], sets[first + stride], ...: Jacobian and derivative images averaged
/// (mu, residuals and flags of the first). Derivatives from independent ray streams average
/// their counting noise down; disjoint halves give the unbiased cross products.
Differences AverageSets(const std::vector<Differences>& sets, size_t first, size_t stride);

/// The polish and the final steps end when the Gauss-Newton decrease of the deviance they
/// predict is below this: the remaining step is a fraction (0.22) of one sigma. A deviance change
/// of 1 is one standard deviation along the least determined direction: a polish that stopped
/// there would end up to 1 sigma short of the optimum, on the side it came from.
inline constexpr double kPolishTolerance = 0.05;

/// Whether the fit ends with the final steps at the optimum (a cross-fitted estimating equation)
/// (the Poisson error with Levenberg-Marquardt and more than the two derivative sets the
/// uncertainties need).
inline bool FinalStepsRun(const FitSpec& spec) {
  return spec.uncertainties && spec.method == Method::kLevenbergMarquardt &&
         spec.error == ErrorFunction::kPoisson && spec.rays.jacobian_seeds > 2;
}

/// One compass search at schedule level `level` from *x (fit.cpp).
bool Compass(Runner& run, const FitSpec& spec, size_t level, const std::function<uint64_t()>& seed,
             Stage stage, std::vector<double>* x, double* delta, double delta_min,
             std::vector<bool>* moved);

/// Levenberg-Marquardt over the levels, then the polish (fit.cpp); `record` false: a repeat.
std::vector<double> LevenbergMarquardt(Runner& run, const FitSpec& spec, FitResult* res,
                                       const std::vector<double>& start, uint64_t seed,
                                       const std::vector<size_t>& levels, bool record);

/// The derivative sets at the optimum and what the final steps leave for the uncertainties.
struct OptimumDerivatives {
  Differences half_a,
      half_b;           // averages of the even and the odd sets (the first is the main streams)
  Simulated final_sim;  // the main streams' images at the final steps' root (empty: none)
  double root_q = -1;   // the equation's Q at the estimate (FitResult::final_steps_q)
  // The mean of the derivative sets' images at the estimate, photons per ray divided by their
  // number (empty: exact images, or no sets): the goodness of fit's template.
  Simulated mean_sim;
  size_t mean_sets = 0;
  // The equation's derivative images (J~_a + J~_b, the columns chosen): the
  // profile-likelihood paths' score (FitModel::PoissonScore).
  std::vector<std::vector<Image>> score_dmu;
  // The final steps' estimating equation (uncertainty.cpp, FinalSteps; when they do not run,
  // only the response, the halves' cross information, for the profile paths): its response A, the
  // variance of U at the truth from the experiment's noise, B_e (derivatives' noise included), and
  // from the templates', B_t, and the part of B_e from the derivatives' Monte Carlo noise, N. The
  // root's covariance is A^-1 (B_e + B_t) A^-T.
  Eigen::MatrixXd score_response, score_variance_experiment, score_variance_template,
      score_derivative_noise;
  // Per parameter the smoothed image's weight w in the score's derivative image,
  // (1 - w) as traced + w smoothed, chosen to minimise sum_i Var(root_i) / score_scale_i over
  // the candidate equations (columns as traced 0..P-1, smoothed P..2P-1): their response
  // (2P x P) and the variance of their values at the truth, B_e + B_t (2P x 2P).
  std::vector<double> score_smoothing;
  Eigen::MatrixXd candidate_response, candidate_variance;
  Eigen::VectorXd score_scale;  // the Cramer-Rao variances the weights' cost divides by
  // The Gaussian priors' precisions on the score's scale (2 Lambda with the final steps, whose U
  // sums two halves; Lambda without): their score is score_prior (m - theta).
  Eigen::VectorXd score_prior;
};

/// The final steps' choice of derivative images (uncertainty.cpp): per parameter i the weight
/// w_i in [0, 1] of its smoothed image in the combination row_i = (1 - w_i) e_i + w_i e_{P+i}
/// of 2P candidate equations (as traced, then smoothed) with the given response (2P x P) and
/// variance (2P x 2P), minimising sum_i Var(root_i) / scale_i: the best corner (w in {0, 1}),
/// then a coordinate descent in eighths. SmoothingCombination is that P x 2P matrix.
/// SmoothingCost is that sum for the weights w (infinity where the combination is singular).
double SmoothingCost(const Eigen::MatrixXd& response, const Eigen::MatrixXd& variance,
                     const Eigen::VectorXd& scale, const std::vector<double>& w);
std::vector<double> SmoothingWeights(const Eigen::MatrixXd& response,
                                     const Eigen::MatrixXd& variance, const Eigen::VectorXd& scale);
Eigen::MatrixXd SmoothingCombination(const std::vector<double>& w);
/// The stencil of derivative set s at the optimum: with the final steps one-sided, forward,
/// backward, backward, forward, ... so that the halves' means (sets 0, 2, ... and 1, 3, ...) are
/// central for a multiple of four sets and the cross products of the pilot's two sets (forward
/// with backward) lose the one-sided truncation error to first order; without them central.
Stencil SetStencil(size_t s, bool steps);
/// What of the derivative sets' scatter is their counting noise (uncertainty.cpp): per
/// parameter i the projection M_i = I - X (X^T X)^+ X^T (S x S) onto what the halves' means
/// (X's indicator columns of sets 0, 2, ... and 1, 3, ...) and the side of each set's one-sided
/// difference (X's column sides[s][i], +1 forward, -1 backward, 0 central) leave. A forward and a
/// backward difference differ by their truncation errors (about h times the second derivative),
/// which is no noise. The deviations dev_s = sum_t M_i(s, t) y_t of the sets' values y_t of
/// parameter i and dev'_s of parameter j have E[sum_s dev_s dev'_s] = tr(M_i M_j) Cov(y, y')
/// for sets with equal noise, whatever the halves' means and the sides' offsets.
std::vector<Eigen::MatrixXd> ScatterProjections(const std::vector<std::vector<int>>& sides);

/// Derivative sets at the optimum and the final steps, which move *best
/// (uncertainty.cpp).
OptimumDerivatives FinalSteps(Runner& run, const FitSpec& spec, std::vector<double>* best,
                              const FitResult& res);

/// The goodness of fit of the fit's result (uncertainty.cpp): the Poisson tests at the point
/// where the template and the experiment agree best, one weighted least-squares step along the
/// derivative images from the estimate `best` (FitModel::Goodness). Exact images step their
/// image linearly; the ray model's mean template of the derivative sets (od.mean_sim) is traced
/// again at the step's point (at most 3 reported sigmas from the estimate in any parameter),
/// and the point the experiment agrees with better is tested. `best_sim` is the template where
/// there is no mean template.
GoodnessOfFit TestedGoodness(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                             const Simulated& best_sim, const OptimumDerivatives& od,
                             const FitResult& res);

/// Sigmas, correlations, Cramer-Rao bounds, repeated fits and slices at the optimum into
/// res->parameters; returns the expected images there (uncertainty.cpp).
Simulated EstimateUncertainties(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                                const OptimumDerivatives& od, FitResult* res);

}  // namespace raymatch::fit::internal
