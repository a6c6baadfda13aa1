// The fit's final steps and uncertainties: derivative sets at the optimum over independent ray
// streams, Fisher-scoring steps with their average, then the covariance (curvature of the
// Poisson likelihood with the derivatives' noise), the Cramer-Rao bound, repeated fits with
// independent simulation seeds and error-function slices (docs/fit.md, "Uncertainties").
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "profile.h"
#include "runner.h"

namespace raymatch::fit::internal {

namespace {

Matrix Correlation(const Matrix& cov) {
  Matrix c = cov;
  for (size_t i = 0; i < cov.size(); ++i)
    for (size_t j = 0; j < cov.size(); ++j) {
      const double d = std::sqrt(cov[i][i] * cov[j][j]);
      c[i][j] = d > 0 ? cov[i][j] / d : 0;
    }
  return c;
}

}  // namespace

OptimumDerivatives FinalSteps(Runner& run, const FitSpec& spec, std::vector<double>* best_io,
                              const FitResult& res) {
  FitModel& model = run.model();
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  std::vector<double>& best = *best_io;
  // Derivatives at the optimum from several independent sets of ray streams, and final
  // Gauss-Newton steps with their average. With fixed ray streams a central difference counts
  // the rays that cross pixel edges, and at photon-matched rays that counting noise is as large
  // as the derivative itself for z and the index (measured: the single-stream Jacobian's column
  // for the index has a cosine of 0.62 with the exact one). The root of J^T r = 0 with such a J
  // scatters up to 2x the Cramer-Rao bound; averaging `jacobian_seeds` sets divides the noise's
  // variance by their number (docs/fit.md, "Finite rays"). The sets are the uncertainties' too.
  // When the steps move the optimum by more than half a step (the stencil's half-width) of any
  // parameter, or end with a decrease still predicted, the derivatives are taken again there
  // (at most three rounds): along the curved z-radius-index valley a single linearisation
  // stops short (issue 26 item 2: z 0.2 um short, 7 CRB, from starts 1.8 um off).
  OptimumDerivatives od;
  Differences& half_a = od.half_a;
  Differences& half_b = od.half_b;
  Simulated& final_sim = od.final_sim;
  Eigen::MatrixXd& score_derivative_noise = od.score_derivative_noise;
  const std::vector<double> read_variance = ReadVariance(spec);
  for (int round = 0; round < 3 && res.status != FitStatus::kFlat && spec.uncertainties &&
                      (round == 0 || run.Budget());
       ++round) {
    const size_t S = size_t(std::max(2, spec.rays.jacobian_seeds));
    std::vector<Differences> sets;
    for (size_t s = 0; s < S; ++s)
      sets.push_back(Differentiate(run, spec, best, final_level,
                                   spec.seed + kDerivativeSetSeedStride * s, Stage::kFisher, true,
                                   s == 0));
    half_a = AverageSets(sets, 0, 2), half_b = AverageSets(sets, 1, 2);
    // Fisher scoring (the Poisson score and expected information, linear in the counts) with
    // derivative images from the other streams only: the main streams' differences count the
    // same rays as their template, and that correlation would bias the score by O(1/k).
    const Differences others = AverageSets(sets, 1, 1);
    od.score_dmu = others.dmu;  // (also for the profile-likelihood paths)
    if (!FinalStepsRun(spec) || !run.Budget())
      break;  // (the sets are always taken: the uncertainties need them, as before the steps)
    const std::vector<std::vector<Image>>& dmu = others.dmu;
    const int bin = model.BinAt(final_level);
    // The root of the score J~^T W (e - mu) = 0 with a noisy J~ = J + dJ moves by
    // F^-1 dJ^T W (e - mu): zero on average, but with variance F^-1 N F^-1 (1 + 1/k), N the
    // noise Gram matrix of the mean of the S - 1 sets, estimated by their scatter: the Gram
    // matrix of the derivative images' deviations in the score's metric W = 1/(mu + r^2). (Not
    // the deviance residuals' Jacobians: at a few photons per pixel their noise also carries the
    // residuals' curvature in e, which overstated N 2-3x on a 20-photon image.) Measured: a
    // single set's index column has a cosine of 0.62 with the exact derivative, so with three
    // sets this adds about half the information's size along the valley (docs/fit.md).
    {
      const double m = double(S - 1);
      Eigen::MatrixXd gram = Eigen::MatrixXd::Zero(Eigen::Index(P), Eigen::Index(P));
      for (size_t s = 1; s < S; ++s) {
        std::vector<std::vector<Image>> dev = sets[s].dmu;
        for (size_t k = 0; k < dev.size(); ++k)
          for (size_t i = 0; i < P; ++i)
            for (size_t q = 0; q < dev[k][i].size(); ++q)
              dev[k][i].pixels[q] -= others.dmu[k][i].pixels[q];
        gram += ToEigen(FisherInformation(sets[0].mu.photons, dev, dev, read_variance));
      }
      score_derivative_noise = gram / ((m - 1) * m);
    }
    std::vector<double> x = best, sc, info;
    model.Score(sets[0].mu, dmu, bin, &sc, &info);  // the main ray streams, as in the search
    // The information for the steps from the cross product of the two halves (unbiased, as for
    // the uncertainties): sum dmu dmu^T / T with one noisy dmu is inflated by the derivatives'
    // noise, most along the weakly determined valley, where it shrank every step by half
    // (measured: z crept 0.025, 0.010, 0.005 um towards a truth 0.1 um away).
    const Eigen::MatrixXd F = ScoringInformation(half_a, half_b, bin, spec, info);
    const auto solver = F.ldlt();
    auto Predicted = [&](const std::vector<double>& v) {
      const Eigen::VectorXd g = Eigen::Map<const Eigen::VectorXd>(v.data(), P);
      return g.dot(solver.solve(g));
    };
    double predicted = Predicted(sc);
    for (int it = 0; it < 4 && run.Budget() && predicted >= kPolishTolerance; ++it) {
      const Eigen::VectorXd step = solver.solve(Eigen::Map<const Eigen::VectorXd>(sc.data(), P));
      if (!step.allFinite()) break;
      std::vector<double> y = x;
      for (size_t i = 0; i < P; ++i) y[i] += step(i);
      y = Clip(y, spec);
      double e = 0;
      const Simulated mu_y = run.Images(y, final_level, spec.seed, Stage::kFinal, &e);
      std::vector<double> sy, unused;
      model.Score(mu_y, dmu, bin, &sy, &unused);
      const double predicted_y = Predicted(sy);
      if (!(predicted_y < predicted)) break;
      x = y, sc = sy, predicted = predicted_y, final_sim = mu_y;
    }
    bool far = false;
    for (size_t i = 0; i < P; ++i)
      far = far || std::abs(x[i] - best[i]) > 0.5 * spec.parameters[i].step;
    const bool moved = x != best;
    best = x;
    if ((!far && predicted < kPolishTolerance) || !moved) break;
  }
  return od;
}

Simulated EstimateUncertainties(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                                const OptimumDerivatives& od, FitResult* res_out) {
  FitResult& res = *res_out;
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  const Eigen::MatrixXd& score_derivative_noise = od.score_derivative_noise;
  const Differences& half_a = od.half_a;
  const Differences& half_b = od.half_b;
  const Simulated& final_sim = od.final_sim;
  Simulated best_sim;
  // The information from two independent halves of the derivative sets. The noise of a Monte
  // Carlo difference adds a positive bias to any sum of squared derivatives (J^T J, Fisher),
  // which would make the information look larger than it is; the cross product of two
  // independent estimates is free of it (its noise averages out instead of adding up).
  const Differences& d = half_a;
  const Differences& d2 = half_b;
  best_sim = final_sim.photons.empty() ? d.mu : final_sim;
  res.best_images = best_sim.photons;
  const Eigen::MatrixXd JtJ =
      0.5 * (d.jacobian.transpose() * d2.jacobian + d2.jacobian.transpose() * d.jacobian);
  const Matrix cov = InverseSpd(FromEigen(JtJ));
  const double k = spec.rays.ray_factor * spec.rays.fractions.back();
  // The estimate's covariance: C (1 + 1/k) from the experiment's and the template's noise,
  // plus C N C (1 + 1/k) from the noise N of the derivatives that the final steps' score used.
  auto Total = [&](const Matrix& c) {
    if (score_derivative_noise.size() == 0) return c;
    const Eigen::MatrixXd cm = ToEigen(c);
    return FromEigen(cm + cm * score_derivative_noise * cm);
  };
  auto SetSigmas = [&](const Matrix& c) {
    const Matrix t = Total(c);
    for (size_t i = 0; i < P; ++i) {
      res.parameters[i].sigma = std::sqrt(t[i][i] * (1 + 1 / k));
      res.parameters[i].sigma_derivatives =
          std::sqrt(std::max(0.0, t[i][i] - c[i][i]) * (1 + 1 / k));
    }
    res.correlation = Correlation(t);
  };
  if (!cov.empty()) {
    for (size_t i = 0; i < P; ++i) res.parameters[i].sigma_curvature = std::sqrt(cov[i][i]);
    SetSigmas(cov);
  }
  const Matrix crb =
      spec.cramer_rao || cov.empty()
          ? InverseSpd(FisherInformation(d.mu.photons, d.dmu, d2.dmu, ReadVariance(spec)))
          : Matrix();
  if (!crb.empty()) {
    for (size_t i = 0; i < P; ++i) {
      res.parameters[i].sigma_cramer_rao = std::sqrt(crb[i][i]);
      res.parameters[i].sigma_expected = std::sqrt(crb[i][i] * (1 + 1 / k));
    }
    res.crb_correlation = Correlation(crb);
  }
  if (cov.empty() && !crb.empty()) {
    // The deviance's curvature from two noisy halves can be indefinite along a weakly
    // determined direction (many nuisances, e.g. a sphere calibration's edge, width and tilt)
    // while the expected (Fisher) information is not: the sigmas are the Cramer-Rao bound's
    // with the template's and the derivatives' noise, as the curvature's would be for a
    // correct model.
    SetSigmas(crb);
    res.message +=
        "; the deviance's curvature is not positive definite (noise along a weakly "
        "determined direction): sigmas from the expected (Fisher) information";
  } else if (cov.empty()) {
    res.message +=
        "; the curvature does not determine every parameter (information matrix not "
        "positive definite): their uncertainties are not reported";
  }
  // Repeated fits with independent ray streams, from the optimum, at the final fraction.
  if (spec.repeat_seeds >= 2) {
    std::vector<std::vector<double>> reps;
    for (int k = 1; k <= spec.repeat_seeds && run.Budget(); ++k) {
      const uint64_t seed = spec.seed + kRepeatSeedStride * k;
      if (spec.method == Method::kLevenbergMarquardt || spec.method == Method::kGrid) {
        FitResult scratch;
        reps.push_back(LevenbergMarquardt(run, spec, &scratch, best, seed, {final_level}, false));
      } else {
        // Pattern: a compass search at the final fraction with this seed, from the optimum.
        std::vector<double> x = best;
        std::vector<bool> moved(P, false);
        double delta = 0.25;
        Compass(
            run, spec, final_level, [&] { return seed; }, Stage::kRepeat, &x, &delta, 1.0 / 64,
            &moved);
        reps.push_back(x);
      }
    }
    if (reps.size() >= 2)
      for (size_t i = 0; i < P; ++i) {
        double m = 0, v = 0;
        for (const auto& r : reps) m += r[i];
        m /= double(reps.size());
        for (const auto& r : reps) v += (r[i] - m) * (r[i] - m);
        res.parameters[i].sigma_repeat = std::sqrt(v / double(reps.size() - 1));
      }
  }
  // Error-function slices through the optimum: +-3 sigma (curvature), at least +-step/2.
  if (spec.slice_points >= 3) {
    for (size_t i = 0; i < P; ++i) {
      ParameterResult& pr = res.parameters[i];
      const double half = std::max(3 * pr.sigma_curvature, 0.5 * spec.parameters[i].step);
      for (int k = 0; k < spec.slice_points && run.Budget(); ++k) {
        std::vector<double> th = best;
        th[i] = best[i] - half + 2 * half * k / (spec.slice_points - 1);
        if (th[i] < pr.lower || th[i] > pr.upper) continue;
        pr.slice_x.push_back(th[i]);
        pr.slice_error.push_back(run.Eval(th, final_level, spec.seed, Stage::kSlice));
      }
    }
  }
  // Profile-likelihood intervals where the curvature interval may not be trustworthy.
  ProfileIntervals(run, spec, best, od, &res);
  return best_sim;
}

}  // namespace raymatch::fit::internal
