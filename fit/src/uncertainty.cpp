// The fit's final steps and uncertainties: derivative sets at the optimum over independent ray
// streams, Fisher-scoring steps with their average, then the covariance (curvature of the
// Poisson likelihood with the derivatives' noise), the Cramer-Rao bound, repeated fits with
// independent simulation seeds and error-function slices (docs/fit.md, "Uncertainties").
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <limits>

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

// [1/4, 1/2, 1/4] in x and y (at the image's edges renormalised over the pixels inside).
Image Smooth121(const Image& a) {
  Image t(a.width, a.height), o(a.width, a.height);
  for (int y = 0; y < a.height; ++y)
    for (int x = 0; x < a.width; ++x) {
      double s = 0.5 * a.at(x, y), w = 0.5;
      if (x > 0) s += 0.25 * a.at(x - 1, y), w += 0.25;
      if (x + 1 < a.width) s += 0.25 * a.at(x + 1, y), w += 0.25;
      t.at(x, y) = float(s / w);
    }
  for (int y = 0; y < a.height; ++y)
    for (int x = 0; x < a.width; ++x) {
      double s = 0.5 * t.at(x, y), w = 0.5;
      if (y > 0) s += 0.25 * t.at(x, y - 1), w += 0.25;
      if (y + 1 < a.height) s += 0.25 * t.at(x, y + 1), w += 0.25;
      o.at(x, y) = float(s / w);
    }
  return o;
}

std::vector<std::vector<Image>> SmoothedDerivatives(std::vector<std::vector<Image>> dmu) {
  for (auto& per_image : dmu)
    for (Image& im : per_image) im = Smooth121(im);
  return dmu;
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
    // The final steps solve an estimating equation, J~^T W (e - m(theta)) = 0 (FitModel::Score
    // with a reference): J~ the derivative images of the sets other than the main streams
    // (independent of the template m and of e), each smoothed with [1/4, 1/2, 1/4] in x and y,
    // W = 1/(mu + r^2) from those sets' mean images, m the main streams' plain count at theta.
    // For any fixed J~ and W it vanishes on average at the truth in every pixel, so neither the
    // smoothing nor the stencil biases its root; the smoothing removes most of the derivatives'
    // counting noise (a ray crossing a pixel edge adds a +-1 dipole to a central difference,
    // which the kernel shrinks 20-fold while the derivative, smooth over a pixel, passes), which
    // otherwise scatters the root by up to 2x the Cramer-Rao bound along the z-radius-index
    // valley. (The score sum dmu (e / (count + one ray) - 1), the search's, is biased by
    // -exp(-k mu) per pixel: with smoothed derivatives reaching into dark pixels it moved case
    // A's index by +10 bounds; docs/fit.md, "Finite rays".)
    const Differences others = AverageSets(sets, 1, 1);
    od.score_reference = others.mean;
    const int bin = model.BinAt(final_level);
    // Candidate columns: each parameter's derivative image as traced (0..P-1) and smoothed
    // (P..2P-1). Their response to the main streams' derivatives (A = J~^T W J, J independent
    // of J~), their Gram matrix (B = J~^T W J~, with J~'s own noise: the score's variance per
    // unit of (1 + 1/k)) and the part of B from that noise (the scatter of the S - 1 sets about
    // their mean, divided by S - 1 for the mean's).
    std::vector<std::vector<Image>> cand = others.dmu;
    {
      const auto smoothed = SmoothedDerivatives(others.dmu);
      for (size_t k = 0; k < cand.size(); ++k)
        cand[k].insert(cand[k].end(), smoothed[k].begin(), smoothed[k].end());
    }
    std::vector<std::vector<Image>> main_dmu = sets[0].dmu;
    const Eigen::MatrixXd a_all =
        ToEigen(model.CrossInformation(cand, main_dmu, od.score_reference, bin));
    const Eigen::MatrixXd b_all =
        ToEigen(model.CrossInformation(cand, cand, od.score_reference, bin));
    Eigen::MatrixXd n_all = Eigen::MatrixXd::Zero(b_all.rows(), b_all.cols());
    if (S > 2) {
      const double m = double(S - 1);
      for (size_t s = 1; s < S; ++s) {
        std::vector<std::vector<Image>> dev = sets[s].dmu;
        const auto smoothed = SmoothedDerivatives(sets[s].dmu);
        for (size_t k = 0; k < dev.size(); ++k) {
          dev[k].insert(dev[k].end(), smoothed[k].begin(), smoothed[k].end());
          for (size_t i = 0; i < 2 * P; ++i)
            for (size_t q = 0; q < dev[k][i].size(); ++q)
              dev[k][i].pixels[q] -= cand[k][i].pixels[q];
        }
        n_all += ToEigen(model.CrossInformation(dev, dev, od.score_reference, bin));
      }
      n_all /= (m - 1) * m;
    }
    // Per parameter the column (as traced or smoothed) that gives the smaller variance of the
    // root, A^-1 B A^-T, summed over the parameters in units of their Cramer-Rao bounds (the
    // halves' cross product): every combination up to 12 parameters (a coordinate descent
    // could stop in a local minimum: measured on bench/fit_accuracy.py case B), beyond that
    // coordinate descent from all smoothed. The choice uses the derivative sets only, not the
    // experiment, so each choice's equation stays unbiased.
    const Matrix crb = InverseSpd(
        FisherInformation(half_a.mu.photons, half_a.dmu, half_b.dmu, read_variance));
    auto Cost = [&](const std::vector<size_t>& c) {
      const auto n = static_cast<Eigen::Index>(P);
      Eigen::MatrixXd A(n, n), B(n, n);
      for (size_t i = 0; i < P; ++i) {
        A.row(Eigen::Index(i)) = a_all.row(Eigen::Index(c[i]));
        for (size_t j = 0; j < P; ++j) B(Eigen::Index(i), Eigen::Index(j)) = b_all(Eigen::Index(c[i]), Eigen::Index(c[j]));
      }
      const auto lu = A.fullPivLu();
      if (!lu.isInvertible()) return std::numeric_limits<double>::infinity();
      const Eigen::MatrixXd ai = lu.inverse(), cov = ai * B * ai.transpose();
      double sum = 0;
      for (size_t i = 0; i < P; ++i) sum += cov(Eigen::Index(i), Eigen::Index(i)) / crb[i][i];
      return std::isfinite(sum) ? sum : std::numeric_limits<double>::infinity();
    };
    std::vector<size_t> choice(P);
    for (size_t i = 0; i < P; ++i) choice[i] = P + i;
    if (!crb.empty()) {
      double cost = Cost(choice);
      if (P <= 12) {  // every combination (4096 at most, each a P x P inversion)
        for (uint32_t mask = 0; mask < (1u << P); ++mask) {
          std::vector<size_t> t(P);
          for (size_t i = 0; i < P; ++i) t[i] = (mask >> i) & 1u ? i : P + i;
          const double c = Cost(t);
          if (c < cost) choice = t, cost = c;
        }
      } else {  // coordinate descent from all smoothed
        for (int pass = 0; pass < 2; ++pass)
          for (size_t i = 0; i < P; ++i) {
            std::vector<size_t> t = choice;
            t[i] = t[i] < P ? t[i] + P : t[i] - P;
            const double c = Cost(t);
            if (c < cost) choice = t, cost = c;
          }
      }
    }
    od.score_dmu.assign(cand.size(), {});
    od.score_smoothed.assign(P, false);
    od.score_response.resize(Eigen::Index(P), Eigen::Index(P));
    od.score_variance.resize(Eigen::Index(P), Eigen::Index(P));
    score_derivative_noise.resize(Eigen::Index(P), Eigen::Index(P));
    for (size_t i = 0; i < P; ++i) {
      od.score_smoothed[i] = choice[i] >= P;
      for (size_t k = 0; k < cand.size(); ++k) od.score_dmu[k].push_back(cand[k][choice[i]]);
      od.score_response.row(Eigen::Index(i)) = a_all.row(Eigen::Index(choice[i]));
      for (size_t j = 0; j < P; ++j) {
        od.score_variance(Eigen::Index(i), Eigen::Index(j)) = b_all(Eigen::Index(choice[i]), Eigen::Index(choice[j]));
        score_derivative_noise(Eigen::Index(i), Eigen::Index(j)) = n_all(Eigen::Index(choice[i]), Eigen::Index(choice[j]));
      }
    }
    if (!FinalStepsRun(spec) || !run.Budget())
      break;  // (the sets are always taken: the uncertainties need them, as before the steps)
    const std::vector<std::vector<Image>>& dmu = od.score_dmu;
    std::vector<double> x = best;
    std::vector<double> sc = model.Score(sets[0].mu, dmu, od.score_reference, bin);
    // Steps s = A^-1 g. The decrease they predict, in units of the root's covariance
    // A^-1 B A^-T, is s^T A^T B^-1 A s = g^T B^-1 g: below kPolishTolerance the remaining step
    // is a fifth of a sigma.
    const auto step_solver = od.score_response.partialPivLu();
    const auto size_solver = od.score_variance.ldlt();
    auto Predicted = [&](const std::vector<double>& v) {
      const Eigen::VectorXd g = Eigen::Map<const Eigen::VectorXd>(v.data(), Eigen::Index(P));
      return g.dot(size_solver.solve(g));
    };
    double predicted = Predicted(sc);
    for (int it = 0; it < 4 && run.Budget() && predicted >= kPolishTolerance; ++it) {
      const Eigen::VectorXd step =
          step_solver.solve(Eigen::Map<const Eigen::VectorXd>(sc.data(), Eigen::Index(P)));
      if (!step.allFinite()) break;
      std::vector<double> y = x;
      for (size_t i = 0; i < P; ++i) y[i] += step(Eigen::Index(i));
      y = Clip(y, spec);
      double e = 0;
      const Simulated mu_y = run.Images(y, final_level, spec.seed, Stage::kFinal, &e);
      const std::vector<double> sy = model.Score(mu_y, dmu, od.score_reference, bin);
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
  // The estimate's covariance. With the final steps, the root of their estimating equation:
  // A^-1 B A^-T (1 + 1/k) (the experiment's and the template's noise through the smoothed
  // derivatives, whose own noise B includes; sigma_derivatives is that part,
  // A^-1 N A^-T (1 + 1/k)). Otherwise C (1 + 1/k), C the deviance's curvature.
  Eigen::MatrixXd a_inv;
  if (od.score_response.size() > 0 && od.score_variance.size() > 0) {
    const auto lu = od.score_response.fullPivLu();
    if (lu.isInvertible()) a_inv = lu.inverse();
  }
  auto Sandwich = [&](const Eigen::MatrixXd& m) {
    return FromEigen(a_inv * m * a_inv.transpose());
  };
  auto SetSigmas = [&](const Matrix& c) {
    const Matrix t = a_inv.size() > 0 ? Sandwich(od.score_variance) : c;
    const Matrix n = a_inv.size() > 0 && score_derivative_noise.size() > 0
                         ? Sandwich(score_derivative_noise)
                         : Matrix(P, std::vector<double>(P, 0.0));
    for (size_t i = 0; i < P; ++i) {
      res.parameters[i].sigma = std::sqrt(std::max(0.0, t[i][i]) * (1 + 1 / k));
      res.parameters[i].sigma_derivatives = std::sqrt(std::max(0.0, n[i][i]) * (1 + 1 / k));
      // The simulation's share: the template's noise (the rest of t, over k) and the
      // derivatives' (all of n's part).
      const double rest = std::max(0.0, t[i][i] - n[i][i]);
      res.parameters[i].sigma_simulation = std::sqrt(rest / k + std::max(0.0, n[i][i]) * (1 + 1 / k));
    }
    res.correlation = Correlation(t);
  };
  for (size_t i = 0; i < P && i < od.score_smoothed.size() && a_inv.size() > 0; ++i)
    res.parameters[i].score_derivative = od.score_smoothed[i] ? "smoothed" : "as traced";
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
