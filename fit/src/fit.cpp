// The fit: grid scan, generalised pattern search and Levenberg-Marquardt (Ceres) over
// simulated images with common random numbers; the final steps and the uncertainties are in
// uncertainty.cpp.
#include <ceres/ceres.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <iostream>
#include <sstream>

#include "profile.h"
#include "runner.h"

namespace raymatch::fit {

namespace internal {

// ------------------------------------------------------------------------------------ grid

/// The k-th of a parameter's `points` from lower to upper (its start when it has one point).
double GridPoint(const Parameter& p, int k) {
  return p.points == 1 ? p.start : p.lower + (p.upper - p.lower) * k / (p.points - 1);
}

std::vector<double> Grid(Runner& run, const FitSpec& spec, FitResult* res) {
  const size_t P = spec.parameters.size();
  res->grid_axes.assign(P, {});
  size_t total = 1;
  for (size_t i = 0; i < P; ++i) {
    const Parameter& p = spec.parameters[i];
    for (int k = 0; k < p.points; ++k) res->grid_axes[i].push_back(GridPoint(p, k));
    total *= p.points;
  }
  const size_t level = spec.rays.fractions.size() - 1;
  std::vector<double> best;
  double best_e = 0;
  for (size_t n = 0; n < total; ++n) {
    std::vector<double> th(P);
    size_t r = n;
    for (size_t i = P; i-- > 0;) {  // last axis fastest
      th[i] = res->grid_axes[i][r % res->grid_axes[i].size()];
      r /= res->grid_axes[i].size();
    }
    const double e = run.Eval(th, level, run.Seed(), Stage::kGrid);
    res->grid_errors.push_back(e);
    if (best.empty() || e < best_e) best = th, best_e = e;
  }
  const auto [mn, mx] = std::minmax_element(res->grid_errors.begin(), res->grid_errors.end());
  if (*mn == *mx) {
    res->status = FitStatus::kFlat;
    res->message =
        "the error function has the same value at every grid point: the parameters do not change "
        "the image";
  } else {
    res->status = FitStatus::kConverged;
    res->converged = true;
    res->message = "grid minimum of " + std::to_string(total) + " points";
  }
  return best;
}

// ------------------------------------------------------------------- generalised pattern search

/// One compass search at schedule level `level` from *x: poll +-delta step_i along each axis,
/// move to the first point that lowers the error, else halve delta, until delta < delta_min.
/// Marks in *moved the parameters whose polls changed the error. False when the evaluation
/// budget ran out.
bool Compass(Runner& run, const FitSpec& spec, size_t level, const std::function<uint64_t()>& seed,
             Stage stage, std::vector<double>* x, double* delta, double delta_min,
             std::vector<bool>* moved) {
  double fx = run.Eval(*x, level, seed(), stage);
  while (*delta >= delta_min) {
    bool improved = false;
    for (size_t i = 0; i < x->size() && !improved; ++i)
      for (int sgn : {+1, -1}) {
        std::vector<double> y = *x;
        y[i] += sgn * *delta * spec.parameters[i].step;
        y = Clip(y, spec);
        if (y[i] == (*x)[i]) continue;
        if (!run.Budget()) return false;
        const double fy = run.Eval(y, level, seed(), stage);
        if (fy != fx) (*moved)[i] = true;
        if (fy < fx) {
          *x = y, fx = fy, improved = true;
          break;
        }
      }
    if (!improved) *delta *= 0.5;
  }
  return true;
}

/// Compass search (Kolda, Lewis, Torczon, SIAM Review 45, 385 (2003), section 3): poll
/// +-delta step_i e_i, move to the first point that decreases the error, otherwise halve the
/// mesh; points beyond a bound are projected onto it. Coarse-to-fine: each ray fraction polls
/// down to a mesh 4x finer than the previous one, the last down to step/64.
std::vector<double> Pattern(Runner& run, const FitSpec& spec, FitResult* res) {
  const size_t P = spec.parameters.size();
  const size_t L = spec.rays.fractions.size();
  std::vector<double> x;
  for (const Parameter& p : spec.parameters) x.push_back(p.start);
  double delta = 1;
  std::vector<bool> moved(P, false);
  bool budget = true;
  for (size_t l = 0; l < L && budget; ++l) {
    const double delta_min = std::pow(4.0, double(L - 1 - l)) / 64;
    delta = std::max(delta, 2 * delta_min);
    budget = Compass(
        run, spec, l, [&] { return run.Seed(); }, Stage::kPoll, &x, &delta, delta_min, &moved);
  }
  if (std::none_of(moved.begin(), moved.end(), [](bool b) { return b; })) {
    res->status = FitStatus::kFlat;
    res->message =
        "the error function did not change for any polled step: the parameters do not change the "
        "image";
  } else if (!budget) {
    res->status = FitStatus::kMaxEvaluations;
    res->message = "stopped after max_evaluations = " + std::to_string(spec.max_evaluations);
  } else {
    res->status = FitStatus::kConverged;
    res->converged = true;
    res->message = "pattern mesh below step/64";
  }
  return x;
}

// --------------------------------------------------------------- Levenberg-Marquardt (Ceres)

Differences Differentiate(Runner& run, const FitSpec& spec, const std::vector<double>& th,
                          size_t level, uint64_t seed, Stage stage, Stencil stencil,
                          bool with_center) {
  FitModel& m = run.model();
  const int bin = m.BinAt(level);
  const size_t P = th.size(), R = m.num_residuals(bin);
  Differences d;
  double e = 0;
  const bool central = stencil == Stencil::kCentral;
  if (with_center || !central) {
    d.mu = run.Images(th, level, seed, stage, &e);
    d.residuals.resize(R);
    m.DevianceResiduals(d.mu, bin, d.residuals.data());
  }
  d.jacobian.resize(R, P);
  d.dmu.assign(spec.images.size(), std::vector<Image>(P));
  d.flat.assign(P, false);
  d.side.assign(P, 0);
  Eigen::VectorXd rp(R), rm(R);
  for (size_t i = 0; i < P; ++i) {
    const Parameter& p = spec.parameters[i];
    // With ray noise the step must span several counting-noise widths; an exact image model
    // has none, and a tenth of it keeps the difference inside the linear range of the wave
    // image's interference fringes (an index step of 0.0015 turns the phase through a 25 um
    // sphere by half a radian).
    const double h = 0.5 * p.step * (spec.exact_images() ? 0.1 : 1.0);
    std::vector<double> a = th, b = th;
    Simulated mu_a, mu_b;
    if (central) {
      a[i] = std::min(th[i] + h, p.upper);
      b[i] = std::max(th[i] - h, p.lower);
      mu_a = run.Images(a, level, seed, stage, &e);
      mu_b = run.Images(b, level, seed, stage, &e);
      m.DevianceResiduals(mu_a, bin, rp.data());
      m.DevianceResiduals(mu_b, bin, rm.data());
    } else {  // h to one side (the other at a bound): one image per parameter
      // The other side where this one has less than h of room and that one more.
      const double up = p.upper - th[i], down = th[i] - p.lower;
      bool fwd = stencil == Stencil::kForward;
      const double room = fwd ? up : down, other = fwd ? down : up;
      if (room < h && other > room) fwd = !fwd;
      d.side[i] = fwd ? 1 : -1;
      if (fwd)
        a[i] = std::min(th[i] + h, p.upper);
      else
        b[i] = std::max(th[i] - h, p.lower);
      (fwd ? mu_a : mu_b) = run.Images(fwd ? a : b, level, seed, stage, &e);
      (fwd ? mu_b : mu_a) = d.mu;
      m.DevianceResiduals(mu_a, bin, rp.data());
      m.DevianceResiduals(mu_b, bin, rm.data());
    }
    const double span = a[i] - b[i];
    d.jacobian.col(i) = (rp - rm) / span;
    bool same = true;
    for (size_t k = 0; k < mu_a.photons.size(); ++k) {
      const Image& ia = mu_a.photons[k];
      const Image& ib = mu_b.photons[k];
      d.dmu[k][i] = Image(ia.width, ia.height);
      for (size_t q = 0; q < ia.size(); ++q) {
        d.dmu[k][i].pixels[q] = static_cast<float>((double(ia.pixels[q]) - ib.pixels[q]) / span);
        same = same && ia.pixels[q] == ib.pixels[q];
      }
    }
    d.flat[i] = same;
  }
  return d;
}

Differences AverageSets(const std::vector<Differences>& sets, size_t first, size_t stride) {
  Differences a = sets.at(first);
  size_t n = 1;
  for (size_t s = first + stride; s < sets.size(); s += stride, ++n) {
    a.jacobian += sets[s].jacobian;
    for (size_t k = 0; k < a.dmu.size(); ++k)
      for (size_t i = 0; i < a.dmu[k].size(); ++i)
        for (size_t q = 0; q < a.dmu[k][i].size(); ++q)
          a.dmu[k][i].pixels[q] += sets[s].dmu[k][i].pixels[q];
  }
  if (n > 1) {
    a.jacobian /= double(n);
    for (auto& per_image : a.dmu)
      for (Image& im : per_image)
        for (float& v : im.pixels) v = float(v / double(n));
  }
  return a;
}

class ImageCost : public ceres::CostFunction {
 public:
  ImageCost(Runner& run, const FitSpec& spec, size_t level, uint64_t seed, std::vector<bool>* flat)
      : run_(run), spec_(spec), level_(level), seed_(seed), flat_(flat) {
    set_num_residuals(static_cast<int>(run.model().num_residuals(run.model().BinAt(level))));
    mutable_parameter_block_sizes()->push_back(static_cast<int>(spec.parameters.size()));
  }
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    const size_t P = spec_.parameters.size();
    const std::vector<double> th = Clip(std::vector<double>(params[0], params[0] + P), spec_);
    if (!run_.Budget()) return false;
    if (jacobians && jacobians[0]) {
      const Differences d =
          Differentiate(run_, spec_, th, level_, seed_, Stage::kLm, Stencil::kCentral);
      std::copy(d.residuals.data(), d.residuals.data() + d.residuals.size(), residuals);
      // Ceres wants row-major residuals x parameters.
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>> J(
          jacobians[0], d.jacobian.rows(), d.jacobian.cols());
      J = d.jacobian;
      *flat_ = d.flat;
    } else {
      double e = 0;
      const Simulated mu = run_.Images(th, level_, seed_, Stage::kLm, &e);
      run_.model().DevianceResiduals(mu, run_.model().BinAt(level_), residuals);
    }
    return true;
  }

 private:
  Runner& run_;
  const FitSpec& spec_;
  size_t level_;
  uint64_t seed_;
  std::vector<bool>* flat_;
};

/// The Gaussian priors as residuals (theta_i - mean_i) / sigma_i, whose squares add
/// PriorPenalty to the deviance (Ceres' cost is half the sum of squares, as for the images').
class PriorCost : public ceres::CostFunction {
 public:
  explicit PriorCost(const FitSpec& spec) : spec_(spec) {
    for (size_t i = 0; i < spec.parameters.size(); ++i)
      if (spec.parameters[i].prior_sigma > 0) index_.push_back(i);
    set_num_residuals(static_cast<int>(index_.size()));
    mutable_parameter_block_sizes()->push_back(static_cast<int>(spec.parameters.size()));
  }
  bool Evaluate(double const* const* params, double* residuals, double** jacobians) const override {
    const size_t P = spec_.parameters.size();
    const std::vector<double> th = Clip(std::vector<double>(params[0], params[0] + P), spec_);
    for (size_t r = 0; r < index_.size(); ++r) {
      const Parameter& p = spec_.parameters[index_[r]];
      residuals[r] = (th[index_[r]] - p.prior_mean) / p.prior_sigma;
      if (jacobians && jacobians[0])
        for (size_t j = 0; j < P; ++j)
          jacobians[0][r * P + j] = j == index_[r] ? 1 / p.prior_sigma : 0;
    }
    return true;
  }

 private:
  const FitSpec& spec_;
  std::vector<size_t> index_;
};

/// The priors' rows appended to deviance residuals r (and their Jacobian J when given).
void AppendPriorRows(const FitSpec& spec, const std::vector<double>& x, Eigen::VectorXd* r,
                     Eigen::MatrixXd* J) {
  const size_t P = spec.parameters.size();
  for (size_t i = 0; i < P; ++i) {
    const Parameter& p = spec.parameters[i];
    if (!(p.prior_sigma > 0)) continue;
    const Eigen::Index n = r->size();
    r->conservativeResize(n + 1);
    (*r)(n) = (x[i] - p.prior_mean) / p.prior_sigma;
    if (J) {
      J->conservativeResize(n + 1, Eigen::Index(P));
      J->row(n).setZero();
      (*J)(n, Eigen::Index(i)) = 1 / p.prior_sigma;
    }
  }
}

/// Stops a level once the search stalls at the resolution the ray streams allow: a successful
/// step that lowered the deviance by less than 1 or moved every parameter by less than 1/32 of
/// its `step`, or five unsuccessful iterations in a row (the error with fixed ray streams is
/// piecewise constant at small scales).
class StallCallback : public ceres::IterationCallback {
 public:
  StallCallback(const double* x, const FitSpec& spec, std::function<bool()> over_budget)
      : x_(x),
        spec_(spec),
        last_(x, x + spec.parameters.size()),
        over_budget_(std::move(over_budget)) {}
  ceres::CallbackReturnType operator()(const ceres::IterationSummary& s) override {
    if (over_budget_()) return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    if (s.iteration == 0) return ceres::SOLVER_CONTINUE;
    if (!s.step_is_successful)
      return ++failures_ >= 5 ? ceres::SOLVER_TERMINATE_SUCCESSFULLY : ceres::SOLVER_CONTINUE;
    failures_ = 0;
    // Ceres' cost is half the deviance: a step worth less than 1 in deviance (0.5 in
    // log-likelihood) is well inside one standard deviation of every parameter. An exact image
    // model has no ray streams to resolve: it runs to Ceres' own tolerances (a deviance step
    // of 1e-3 is 0.03 standard deviations).
    if (spec_.exact_images())
      return s.cost_change < 5e-4 ? ceres::SOLVER_TERMINATE_SUCCESSFULLY : ceres::SOLVER_CONTINUE;
    if (s.cost_change < 0.5) return ceres::SOLVER_TERMINATE_SUCCESSFULLY;
    double moved = 0;
    for (size_t i = 0; i < last_.size(); ++i) {
      moved = std::max(moved, std::abs(x_[i] - last_[i]) / spec_.parameters[i].step);
      last_[i] = x_[i];
    }
    return moved < 1.0 / 32 ? ceres::SOLVER_TERMINATE_SUCCESSFULLY : ceres::SOLVER_CONTINUE;
  }

 private:
  const double* x_;
  const FitSpec& spec_;
  std::vector<double> last_;
  std::function<bool()> over_budget_;
  int failures_ = 0;
};

/// Gauss-Newton polish at schedule level L from `start`. Levenberg-Marquardt's damping crawls
/// along a weakly determined valley (z, radius and index of a defocused sphere), and its
/// shrinking trust region ends on the staircase that fixed ray streams make at small steps.
/// Undamped steps from central differences at half the parameter steps cross the valley; a step
/// is kept when it lowers the deviance (by more than kPolishTolerance / 2), halving it up to 3
/// times. The polish moves by far less than the difference steps, so the Jacobian is kept (a
/// chord method: one image per iteration instead of 2P + 2) while the point stays inside the
/// neighbourhood of the stencil it came from (within 2h = step of each parameter, h = step/2).
/// It ends when the predicted decrease of the deviance is below kPolishTolerance, i.e. the
/// remaining step is a fraction of the statistical uncertainty, confirmed with a Jacobian at
/// that point (which the uncertainties then reuse).
std::vector<double> Polish(Runner& run, const FitSpec& spec, const std::vector<double>& start,
                           size_t L, uint64_t seed, Stage stage) {
  const size_t P = spec.parameters.size();
  const int bin = run.model().BinAt(L);
  // kPolishTolerance: with fixed ray streams the deviance differences between nearby points
  // are deterministic, so steps much smaller than one sigma still count.
  std::vector<double> x = Clip(start, spec);
  Eigen::MatrixXd J;
  Eigen::VectorXd r;
  std::vector<double> x_jacobian;
  for (int it = 0; it < 12 && run.Budget(); ++it) {
    bool fresh = J.size() == 0;
    for (size_t i = 0; i < P && !fresh; ++i)
      fresh = std::abs(x[i] - x_jacobian[i]) > spec.parameters[i].step;
    if (fresh) {
      const Differences d = Differentiate(run, spec, x, L, seed, stage, Stencil::kCentral);
      J = d.jacobian, r = d.residuals, x_jacobian = x;
      AppendPriorRows(spec, x, &r, &J);
    }
    const double dev = r.squaredNorm();
    Eigen::MatrixXd A = J.transpose() * J;
    A.diagonal() *= 1 + 1e-9;
    const Eigen::VectorXd step = A.ldlt().solve(-J.transpose() * r);
    if (!step.allFinite()) break;
    const double predicted = step.dot(A * step);  // Gauss-Newton's decrease of the deviance
    if (predicted < kPolishTolerance) {
      if (fresh) break;
      J.resize(0, 0);  // confirm with the Jacobian at this point before stopping
      continue;
    }
    bool accepted = false;
    for (double scale = 1; scale >= 0.125 && !accepted && run.Budget(); scale *= 0.5) {
      std::vector<double> y = x;
      for (size_t i = 0; i < P; ++i) y[i] += scale * step(i);
      y = Clip(y, spec);
      double e = 0;
      const Simulated mu = run.Images(y, L, seed, stage, &e);
      Eigen::VectorXd ry(Eigen::Index(run.model().num_residuals(bin)));
      run.model().DevianceResiduals(mu, bin, ry.data());
      AppendPriorRows(spec, y, &ry, nullptr);
      // Kept when it lowers the deviance, or when it lowers the Gauss-Newton decrease still
      // predicted (the estimating equation J^T r = 0 with this smooth chord Jacobian). With
      // fixed ray streams the deviance is rough at scales below one sigma (rays cross pixel
      // edges one by one: jumps of a few units within +-1 sigma of the index,
      // docs/design/fit-estimator.md, "Finite rays"), and a search that keeps only its
      // descents ends in whichever local dip of that roughness it meets first, up to several
      // sigma from the smooth optimum; the predicted decrease is linear in the counts and not
      // rough at that scale.
      const Eigen::VectorXd gy = J.transpose() * ry;
      const double predicted_y = gy.dot(A.ldlt().solve(gy));
      if (ry.squaredNorm() < dev - 0.5 * kPolishTolerance ||
          (spec.rays.smooth_polish && predicted_y < 0.5 * predicted))
        x = y, r = ry, accepted = true;
    }
    if (!accepted) {
      if (fresh) break;
      J.resize(0, 0);  // a stale Jacobian may have pointed the wrong way: renew it once
    }
  }
  return x;
}

/// Levenberg-Marquardt on signed Poisson deviance residuals (sum of squares = deviance, so the
/// least-squares optimum is the maximum-likelihood one), coarse-to-fine over the ray fractions.
std::vector<double> LevenbergMarquardt(Runner& run, const FitSpec& spec, FitResult* res,
                                       const std::vector<double>& start, uint64_t seed,
                                       const std::vector<size_t>& levels, bool record) {
  const size_t P = spec.parameters.size();
  std::vector<double> x = start;
  std::vector<bool> flat(P, false);
  bool ok = true;
  ceres::TerminationType term = ceres::CONVERGENCE;
  // With several levels, Levenberg-Marquardt runs on the coarse ones and the final level is
  // the Gauss-Newton polish alone: the coarse optimum is already in the final level's quadratic
  // basin, where LM's damped steps and its Jacobian at every accepted point cost full-ray
  // images that one or two undamped steps do not need (measured in docs/performance.md).
  const std::vector<size_t> lm_levels(levels.begin(), levels.end() - (levels.size() > 1 ? 1 : 0));
  for (size_t f : lm_levels) {
    ceres::Problem::Options po;
    po.cost_function_ownership = ceres::TAKE_OWNERSHIP;
    ceres::Problem problem(po);
    problem.AddResidualBlock(new ImageCost(run, spec, f, seed, &flat), nullptr, x.data());
    if (PriorPrecision(spec).sum() > 0)
      problem.AddResidualBlock(new PriorCost(spec), nullptr, x.data());
    // Bounds are kept by clipping inside the cost (not Ceres' bound constraints, whose projected
    // line search evaluates the Jacobian, i.e. P more images, at every trial point).
    ceres::Solver::Options so;
    so.linear_solver_type = ceres::DENSE_QR;
    so.max_num_iterations = 60;
    so.function_tolerance = 1e-7;
    so.parameter_tolerance = 1e-7;
    so.num_threads = 1;  // the tracer uses the cores
    so.logging_type = ceres::SILENT;
    so.minimizer_progress_to_stdout = false;
    so.update_state_every_iteration = true;
    // Evaluation caps per level: coarse levels are cheap and carry the search through the curved
    // valleys of z, radius and index (40 Jacobians' worth); the final level refines (12).
    const size_t level_start = run.Count();
    const bool last = f + 1 == spec.rays.fractions.size();
    const size_t level_cap = (last && !spec.exact_images() ? 12 : 40) * (P + 2);
    StallCallback stall(x.data(), spec, [&] { return run.Count() - level_start >= level_cap; });
    so.callbacks.push_back(&stall);
    ceres::Solver::Summary sum;
    ceres::Solve(so, &problem, &sum);
    term = sum.termination_type;
    if (record)
      run.Say(
          "level " + std::to_string(f + 1) + " (" +
          (spec.exact_images() ? "exact image" : "ray fraction " + Fmt(spec.rays.fractions[f], 3)) +
          ", bin " + std::to_string(run.model().BinAt(f)) +
          "): " + std::to_string(sum.iterations.size()) + " iterations, deviance " +
          Fmt(2 * sum.initial_cost) + " -> " + Fmt(2 * sum.final_cost) + ", " +
          std::to_string(run.Count() - level_start) + " evaluations");
    ok = ok && sum.IsSolutionUsable();
    if (record && std::all_of(flat.begin(), flat.end(), [](bool b) { return b; })) break;
  }
  // Then the Gauss-Newton polish at the final level (Polish). Skipped in the main search when
  // the final steps follow (`[rays] polish`): they start from the coarse
  // optimum and cross the valley with averaged derivatives.
  const bool polish = !record || spec.rays.polish || !FinalStepsRun(spec);
  if (polish && !levels.empty() &&
      std::none_of(flat.begin(), flat.end(), [](bool b) { return b; })) {
    // A sampling the model kept from the start (physical optics) is laid out again near the
    // optimum, so the polish, the uncertainties and the goodness of fit see the model's own
    // sampling there.
    run.Relayout();
    x = Polish(run, spec, x, levels.back(), seed, record ? Stage::kPolish : Stage::kRepeat);
  }
  if (!record) return Clip(x, spec);
  std::string flat_keys;
  for (size_t i = 0; i < P; ++i)
    if (flat[i]) flat_keys += (flat_keys.empty() ? "" : ", ") + spec.parameters[i].key;
  if (!flat_keys.empty()) {
    res->status = FitStatus::kFlat;
    res->message = "the image does not change with " + flat_keys +
                   " (flat error function): the fit cannot move it";
  } else if (!run.Budget()) {
    res->status = FitStatus::kMaxEvaluations;
    res->message = "stopped after max_evaluations = " + std::to_string(spec.max_evaluations);
  } else {
    res->converged = ok;
    res->status = ok ? FitStatus::kConverged : FitStatus::kFailed;
    res->message = std::string("Levenberg-Marquardt: ") +
                   (term == ceres::CONVERGENCE || term == ceres::USER_SUCCESS
                        ? (spec.exact_images() ? "converged"
                                               : "converged (steps below what the ray streams "
                                                 "resolve)")
                        : "stopped without convergence");
  }
  return Clip(x, spec);
}

}  // namespace internal

using namespace internal;

Matrix InverseSpd(const Matrix& m) {
  const size_t n = m.size();
  Eigen::LDLT<Eigen::MatrixXd> ldlt(ToEigen(m));
  if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return {};
  for (int i = 0; i < ldlt.vectorD().size(); ++i)
    if (!(ldlt.vectorD()(i) > 1e-300)) return {};
  return FromEigen(ldlt.solve(Eigen::MatrixXd::Identity(n, n)));
}

Matrix FisherInformation(const std::vector<Image>& mu, const std::vector<std::vector<Image>>& dmu) {
  return FisherInformation(mu, dmu, dmu);
}

Matrix FisherInformation(const std::vector<Image>& mu, const std::vector<std::vector<Image>>& dmu_a,
                         const std::vector<std::vector<Image>>& dmu_b,
                         const std::vector<double>& read_variance) {
  const size_t P = dmu_a.empty() ? 0 : dmu_a[0].size();
  Matrix F(P, std::vector<double>(P, 0.0));
  for (size_t k = 0; k < mu.size(); ++k)
    for (size_t q = 0; q < mu[k].size(); ++q) {
      if (!(mu[k].pixels[q] > 0)) continue;
      const double m = mu[k].pixels[q] + (k < read_variance.size() ? read_variance[k] : 0.0);
      for (size_t i = 0; i < P; ++i)
        for (size_t j = 0; j < P; ++j)
          F[i][j] += 0.5 *
                     (double(dmu_a[k][i].pixels[q]) * dmu_b[k][j].pixels[q] +
                      double(dmu_b[k][i].pixels[q]) * dmu_a[k][j].pixels[q]) /
                     m;
    }
  return F;
}

namespace {

/// The fit from the parameters' starts (RunFit without the [search] stages).
FitResult RunFitFromStart(const FitSpec& spec, const FitOptions& options) {
  const auto t_start = Clock::now();
  FitResult res;
  Runner run(spec, options, &res);
  FitModel& model = run.model();
  res.photon_matched_rays = model.photon_matched_rays();
  res.region_center_um = {model.region_center().x, model.region_center().y,
                          model.region_center().z};
  res.region_radius_um = model.region_radius();
  res.object_pixel_um = model.object_pixel_um();
  const double setup_s = Since(t_start);
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  std::vector<size_t> all_levels;
  for (size_t l = 0; l <= final_level; ++l) all_levels.push_back(l);

  // 1. Search.
  const auto t_search = Clock::now();
  std::vector<double> start;
  for (const Parameter& p : spec.parameters) start.push_back(p.start);
  std::vector<double> best;
  switch (spec.method) {
    case Method::kGrid:
      best = Grid(run, spec, &res);
      break;
    case Method::kPattern:
      best = Pattern(run, spec, &res);
      break;
    case Method::kLevenbergMarquardt:
      best = LevenbergMarquardt(run, spec, &res, start, spec.seed, all_levels, true);
      break;
  }
  const double bg_search = model.background_seconds();
  const double search_s = Since(t_search);
  res.near_ray_fraction = model.near_fraction();

  const auto t_unc = Clock::now();
  // From here on the evaluations stay near the optimum: the rays that pass near the objects
  // only over the search's box are traced once with the background (the same images).
  if (spec.uncertainties && model.FocusRegion(best, kFocusSteps)) {
    res.focused_region_radius_um = model.region_radius();
    res.focused_region_center_um = {model.region_center().x, model.region_center().y,
                                    model.region_center().z};
  }
  // 1b. Derivative sets at the optimum and the final steps' estimating equation (uncertainty.cpp).
  const OptimumDerivatives od = FinalSteps(run, spec, &best, res);
  res.final_steps_q = od.root_q;
  if (od.root_q > 1)
    res.message +=
        "; the final steps ended " + Fmt(std::sqrt(od.root_q), 2) +
        " statistical sigmas from their estimating equation's root (Q = " + Fmt(od.root_q, 3) +
        "); its sigma does not include that offset: more jacobian_seeds or rays";

  for (size_t i = 0; i < P; ++i) {
    const Parameter& p = spec.parameters[i];
    ParameterResult pr;
    pr.key = p.key, pr.unit = p.unit, pr.start = p.start, pr.best = best[i];
    pr.prior_mean = p.prior_mean, pr.prior_sigma = p.prior_sigma, pr.prior_from = p.prior_from;
    pr.lower = p.lower, pr.upper = p.upper;
    pr.at_bound = std::abs(best[i] - p.lower) < 1e-9 * (p.upper - p.lower) ||
                  std::abs(best[i] - p.upper) < 1e-9 * (p.upper - p.lower);
    res.parameters.push_back(pr);
  }

  // 2. Uncertainties at the optimum (skipped for a flat problem: there is no curvature).
  Simulated best_sim;
  if (res.status != FitStatus::kFlat && spec.uncertainties) {
    best_sim = EstimateUncertainties(run, spec, best, od, &res);
  } else {
    double e = 0;
    best_sim = run.Images(best, final_level, spec.seed, Stage::kBest, &e);
    res.best_images = best_sim.photons;
  }
  // The images shown, in the residuals and to the goodness of fit: the mean of the derivative
  // sets' images at the estimate where there is one (S times less template noise than the main
  // streams' image alone), else the main streams'.
  const bool mean = !od.mean_sim.photons.empty();
  if (mean) res.best_images = od.mean_sim.photons;
  const double template_variance = 1 / (spec.RaysPerPhoton() * (mean ? double(od.mean_sets) : 1));
  for (size_t k = 0; k < res.best_images.size(); ++k) {
    const Image& mu = res.best_images[k];
    const Image& ex = spec.images[k].photons;
    const double read2 = spec.images[k].read_noise_e * spec.images[k].read_noise_e;
    Image r(mu.width, mu.height);
    for (size_t q = 0; q < mu.size(); ++q) {
      const double var = std::max(1.0, double(mu.pixels[q])) * (1 + template_variance) + read2;
      r.pixels[q] = static_cast<float>((double(mu.pixels[q]) - ex.pixels[q]) / std::sqrt(var));
    }
    res.residuals.push_back(std::move(r));
  }
  res.best_error = model.Error(best_sim, model.BinAt(final_level));
  for (ParameterResult& p : res.parameters) p.sigma_statistical = p.sigma;
  if (spec.error == ErrorFunction::kPoisson && !best_sim.photons.empty()) {
    // Does the model describe the image? If not, the curvature's sigmas are too small: scale
    // them by the square root of the reduced deviance (or of the residuals' reduced block
    // chi-square, when the misfit is spatially coherent), as a least-squares fit scales by
    // sqrt(chi^2 / dof) (PDG, Review of Particle Physics, "Statistics", scale factor).
    res.goodness = TestedGoodness(run, spec, best, best_sim, od, res);
    if (res.goodness.mismatch) {
      for (ParameterResult& p : res.parameters) p.sigma *= res.goodness.sigma_inflation;
      res.message += "; " + res.goodness.verdict;
    }
  }
  if (spec.error != ErrorFunction::kPoisson && res.status != FitStatus::kFlat &&
      spec.uncertainties) {
    // MSE and the SSIM family are not likelihoods: the Poisson deviance's curvature at their
    // optimum is not the scatter of their estimate, so no sigma is reported. The Cramer-Rao
    // bound (what the images allow any estimator) and the scatter over repeated ray streams
    // (repeat_seeds) stay.
    for (ParameterResult& p : res.parameters) {
      p.sigma = p.sigma_statistical = p.sigma_curvature = p.sigma_derivatives = p.sigma_simulation =
          0;
      p.profile_reason.clear(), p.profile_t.clear(), p.profile_delta.clear();
    }
    res.correlation.clear();
    res.message += std::string("; error = ") + ErrorFunctionName(spec.error) +
                   " is not a likelihood: no sigma (the Cramer-Rao bound says what the images "
                   "allow; repeat_seeds measure the scatter over ray streams" +
                   (spec.method == Method::kGrid ? "; the grid's step is its resolution)" : ")");
  }
  ProfileValues(&res);  // the profile intervals' ends with the final sigmas
  const double unc_s = Since(t_unc);
  const double bg_total = model.background_seconds();
  res.seconds = {{"setup (region, source field, photon target)", setup_s},
                 {"background rays (traced once per image and ray count)", bg_total},
                 {"search evaluations", search_s - bg_search},
                 {"derivatives, final steps and uncertainties (repeats, slices, profiles)",
                  unc_s - (bg_total - bg_search)}};
  res.total_seconds = Since(t_start);
  if (options.progress && isatty(2)) std::fprintf(stderr, "\r\033[K");
  for (const ParameterResult& p : res.parameters)
    if (p.at_bound && res.status == FitStatus::kConverged)
      res.message += "; " + p.key + " ended at a bound: widen [lower, upper]";
  return res;
}

}  // namespace

FitResult RunFit(const FitSpec& spec, const FitOptions& options) {
  if (!spec.start_fit && spec.scan.empty() && spec.hop < 0) return RunFitFromStart(spec, options);
  const auto t_start = Clock::now();
  FitSpec main = spec;  // the same fit from the stages' start
  main.start_fit.reset();
  main.scan.clear();
  main.hop = -1;
  std::vector<Evaluation> before;
  std::vector<std::pair<std::string, double>> seconds;
  auto say = [&](const std::string& m) {
    if (options.progress)
      std::fprintf(stderr, "%sraymatch fit: %s\n", isatty(2) ? "\r\033[K" : "", m.c_str());
  };
  if (spec.start_fit) {
    // 1. The ray model's fit from the parameters' starts: its optimum is near the truth in
    // position and size, where the exact model's likelihood has its main valley.
    const auto t0 = Clock::now();
    say("start: fitting the ray model from the parameters' starts");
    const FitResult rays = RunFitFromStart(*spec.start_fit, options);
    for (Evaluation e : rays.evaluations) {
      e.stage = Stage::kStart;
      before.push_back(std::move(e));
    }
    for (size_t i = 0; i < main.parameters.size(); ++i)
      main.parameters[i].start = rays.parameters[i].best;
    seconds.push_back({"start: the ray model's fit", Since(t0)});
  }
  if (!spec.scan.empty()) {
    // 2. Each scanned parameter over its points at this fit's model, the others held.
    const auto t0 = Clock::now();
    FitResult scan;
    Runner run(main, options, &scan);
    const size_t level = main.rays.fractions.size() - 1;
    for (size_t i : spec.scan) {
      Parameter& p = main.parameters[i];
      say("scan: " + p.key + " over " + std::to_string(p.points) + " points");
      std::vector<double> th;
      for (const Parameter& q : main.parameters) th.push_back(q.start);
      double best_e = 0, best_v = p.start;
      for (int k = 0; k < p.points; ++k) {
        th[i] = GridPoint(p, k);
        const double e = run.Eval(th, level, run.Seed(), Stage::kScan);
        if (k == 0 || e < best_e) best_e = e, best_v = th[i];
      }
      p.start = best_v;
    }
    for (Evaluation& e : scan.evaluations) before.push_back(std::move(e));
    seconds.push_back({"scan", Since(t0)});
  }
  const auto t_fit = Clock::now();
  FitResult res = RunFitFromStart(main, options);
  if (spec.hop >= 0) {
    // 3. Hops: the fit again from its optimum moved by one step along the hop parameter, down
    // and up; a lower error wins and the hops go on that way. The fits that lose keep their
    // evaluations, as stage "hop".
    const size_t h = size_t(spec.hop);
    auto lose = [&](FitResult& r) {
      for (Evaluation& e : r.evaluations) {
        e.stage = Stage::kHop;
        before.push_back(std::move(e));
      }
    };
    for (int dir : {-1, 1}) {
      bool moved = false;
      for (;;) {
        FitSpec from = main;
        for (size_t i = 0; i < from.parameters.size(); ++i)
          from.parameters[i].start = res.parameters[i].best;
        Parameter& p = from.parameters[h];
        p.start += dir * spec.hop_step;
        if (p.start < p.lower || p.start > p.upper) break;
        std::ostringstream m;
        m << "hop: " << p.key << " from " << res.parameters[h].best << " to " << p.start;
        say(m.str());
        FitResult r = RunFitFromStart(from, options);
        if (!(r.best_error < res.best_error)) {
          lose(r);
          break;
        }
        lose(res);
        res = std::move(r);
        moved = true;
      }
      if (moved) break;  // the other way leads back to the valley just left
    }
    // The fit reported is the one that won; the others' time (the first fit's too, when a hop
    // won) is the hops'.
    seconds.push_back({"hops (the fits that lost)", Since(t_fit) - res.total_seconds});
  }
  res.evaluations.insert(res.evaluations.begin(), before.begin(), before.end());
  res.seconds.insert(res.seconds.begin(), seconds.begin(), seconds.end());
  for (size_t i = 0; i < res.parameters.size(); ++i)
    res.parameters[i].start = spec.parameters[i].start;
  res.total_seconds = Since(t_start);
  return res;
}

std::vector<GridStudyRow> RunGridStudy(const FitSpec& spec, const std::vector<double>& fractions,
                                       const std::vector<ErrorFunction>& errors,
                                       const FitOptions& options) {
  std::vector<GridStudyRow> rows;
  for (ErrorFunction e : errors)
    for (double f : fractions) {
      FitSpec s = spec;
      s.method = Method::kGrid;
      s.error = e;
      s.rays.fractions = {f};
      s.rays.binning.clear();
      s.uncertainties = false;
      s.repeat_seeds = 0;
      s.slice_points = 0;  // grid points per axis: set by LoadFitSpec
      const FitResult r = RunFit(s, options);
      GridStudyRow row;
      row.error = ErrorFunctionName(e);
      row.fraction = f;
      row.bin = r.evaluations.empty() ? 1 : r.evaluations.front().bin;
      row.evaluations = r.evaluations.size();
      row.seconds = r.total_seconds;
      for (const ParameterResult& p : r.parameters) row.best.push_back(p.best);
      rows.push_back(row);
    }
  return rows;
}

}  // namespace raymatch::fit
