// The fit's final steps and uncertainties: derivative sets at the optimum over independent ray
// streams and the root of a cross-fitted estimating equation built from them, then the
// covariance (that root's sandwich, or the Poisson likelihood's curvature), the Cramer-Rao
// bound, repeated fits with independent simulation seeds and error-function slices
// (docs/design/fit-estimator.md, "Finite rays" and "Noise").
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdio>
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

/// Images per fitted image, and derivative images per fitted image and column.
using Images = std::vector<Image>;
using Columns = std::vector<std::vector<Image>>;  // [image][column]

/// The mean of list[first], list[first + stride], ...: pixel by pixel, per image.
Images MeanImages(const std::vector<Images>& list, size_t first, size_t stride) {
  Images m;
  size_t n = 0;
  for (size_t s = first; s < list.size(); s += stride, ++n) {
    const Images& c = list[s];
    if (m.empty())
      for (const Image& im : c) m.emplace_back(im.width, im.height);
    for (size_t k = 0; k < c.size(); ++k)
      for (size_t q = 0; q < c[k].size(); ++q) m[k].pixels[q] += c[k].pixels[q];
  }
  for (Image& im : m)
    for (float& v : im.pixels) v = float(v / double(std::max<size_t>(n, 1)));
  return m;
}

/// The mean of columns list[first], list[first + stride], ...
Columns MeanColumns(const std::vector<Columns>& list, size_t first, size_t stride) {
  std::vector<Images> flat;  // [set][image * columns + column]
  for (size_t s = 0; s < list.size(); ++s) {
    flat.emplace_back();
    for (const Images& per_image : list[s])
      flat.back().insert(flat.back().end(), per_image.begin(), per_image.end());
  }
  const Images mean = MeanImages(flat, first, stride);
  Columns c = list.at(first);
  size_t at = 0;
  for (Images& per_image : c)
    for (Image& im : per_image) im = mean[at++];
  return c;
}

/// The columns as traced followed by the same smoothed: [image][2P].
Columns Candidates(const Columns& dmu) {
  Columns c = dmu;
  for (size_t k = 0; k < c.size(); ++k)
    for (const Image& im : dmu[k]) c[k].push_back(Smooth121(im));
  return c;
}

Columns Plus(const Columns& a, const Columns& b) {
  Columns c = a;
  for (size_t k = 0; k < c.size(); ++k)
    for (size_t i = 0; i < c[k].size(); ++i)
      for (size_t q = 0; q < c[k][i].size(); ++q) c[k][i].pixels[q] += b[k][i].pixels[q];
  return c;
}

}  // namespace

Stencil SetStencil(size_t s, bool steps) {
  if (!steps) return Stencil::kCentral;
  return s % 4 == 0 || s % 4 == 3 ? Stencil::kForward : Stencil::kBackward;
}

std::vector<Eigen::MatrixXd> ScatterProjections(const std::vector<std::vector<int>>& sides) {
  const auto S = Eigen::Index(sides.size());
  const size_t P = sides.empty() ? 0 : sides[0].size();
  std::vector<Eigen::MatrixXd> m;
  for (size_t i = 0; i < P; ++i) {
    Eigen::MatrixXd x = Eigen::MatrixXd::Zero(S, 3);
    for (Eigen::Index s = 0; s < S; ++s) x(s, s % 2) = 1, x(s, 2) = sides[size_t(s)].at(i);
    // The projection onto X's column space (rank 2 where the sides are all alike or central).
    const Eigen::CompleteOrthogonalDecomposition<Eigen::MatrixXd> cod(x);
    m.push_back(Eigen::MatrixXd::Identity(S, S) - x * cod.pseudoInverse());
  }
  return m;
}

Eigen::MatrixXd SmoothingCombination(const std::vector<double>& w) {
  const auto P = Eigen::Index(w.size());
  Eigen::MatrixXd t = Eigen::MatrixXd::Zero(P, 2 * P);
  for (Eigen::Index i = 0; i < P; ++i) t(i, i) = 1 - w[size_t(i)], t(i, P + i) = w[size_t(i)];
  return t;
}

double SmoothingCost(const Eigen::MatrixXd& response, const Eigen::MatrixXd& variance,
                     const Eigen::VectorXd& scale, const std::vector<double>& w) {
  const Eigen::MatrixXd t = SmoothingCombination(w);
  const auto lu = (t * response).fullPivLu();
  if (!lu.isInvertible()) return std::numeric_limits<double>::infinity();
  const Eigen::MatrixXd ai = lu.inverse();
  const Eigen::MatrixXd cov = ai * (t * variance * t.transpose()) * ai.transpose();
  const double sum = (cov.diagonal().array() / scale.array()).sum();
  return std::isfinite(sum) ? sum : std::numeric_limits<double>::infinity();
}

std::vector<double> SmoothingWeights(const Eigen::MatrixXd& response,
                                     const Eigen::MatrixXd& variance,
                                     const Eigen::VectorXd& scale) {
  const size_t P = size_t(scale.size());
  auto Cost = [&](const std::vector<double>& w) {
    return SmoothingCost(response, variance, scale, w);
  };
  std::vector<double> weight(P, 1.0);
  double cost = Cost(weight);
  auto Try = [&](const std::vector<double>& t) {
    const double c = Cost(t);
    if (c < cost) weight = t, cost = c;
  };
  // The corners first (each parameter's image as traced or smoothed alone): every combination
  // up to 12 parameters, else a coordinate descent from all smoothed.
  if (P <= 12) {
    for (uint32_t mask = 0; mask < (1u << P); ++mask) {
      std::vector<double> t(P);
      for (size_t i = 0; i < P; ++i) t[i] = (mask >> i) & 1u ? 0.0 : 1.0;
      Try(t);
    }
  } else {
    for (int pass = 0; pass < 2; ++pass)
      for (size_t i = 0; i < P; ++i) {
        std::vector<double> t = weight;
        t[i] = 1 - t[i];
        Try(t);
      }
  }
  // Then a coordinate descent over each weight in eighths.
  for (int pass = 0; pass < 3; ++pass) {
    const std::vector<double> before = weight;
    for (size_t i = 0; i < P; ++i)
      for (int e = 0; e <= 8; ++e) {
        std::vector<double> t = weight;
        t[i] = e / 8.0;
        Try(t);
      }
    if (weight == before) break;
  }
  return weight;
}

namespace {

/// The derivatives' noise in U's variance B_e: per set, pooled over the halves from the sets'
/// scatter about their half's mean and their side's truncation offset (ScatterProjections); the
/// sum J~_a + J~_b holds it 1/na + 1/nb times. Zero without degrees of freedom (two sets).
Eigen::MatrixXd DerivativeNoise(const FitModel& model, const std::vector<Differences>& sets,
                                const std::vector<Columns>& cand_sets, const Images& vm, int bin,
                                size_t na, size_t nb) {
  const size_t S = sets.size(), P = sets.empty() ? 0 : sets[0].side.size();
  const Eigen::Index C = Eigen::Index(2 * P);
  Eigen::MatrixXd n_all = Eigen::MatrixXd::Zero(C, C);
  std::vector<std::vector<int>> sides;
  for (const Differences& d : sets) sides.push_back(d.side);
  const std::vector<Eigen::MatrixXd> proj = ScatterProjections(sides);
  // No degrees of freedom left (the pilot's two sets): N = 0 without summing the products.
  bool scatter = false;
  for (const Eigen::MatrixXd& m : proj) scatter = scatter || m.trace() > 0.5;
  for (size_t s = 0; s < S && scatter; ++s) {
    Columns dev = cand_sets[s];
    for (size_t i = 0; i < dev.size(); ++i)
      for (size_t c = 0; c < 2 * P; ++c) {
        const Eigen::MatrixXd& m = proj[c % P];
        for (size_t q = 0; q < dev[i][c].size(); ++q) {
          double v = 0;
          for (size_t t = 0; t < S; ++t)
            v += m(Eigen::Index(s), Eigen::Index(t)) * cand_sets[t][i][c].pixels[q];
          dev[i][c].pixels[q] = float(v);
        }
      }
    n_all += ToEigen(model.CrossInformation(dev, dev, vm, bin));
  }
  for (Eigen::Index c = 0; c < n_all.rows(); ++c)
    for (Eigen::Index c2 = 0; c2 < n_all.cols(); ++c2) {
      const double dof = (proj[size_t(c) % P] * proj[size_t(c2) % P]).trace();
      n_all(c, c2) *= dof > 0.5 ? (1 / double(na) + 1 / double(nb)) / dof : 0.0;
    }
  return n_all;
}

/// The goodness of fit's template: the mean of the S sets' images at the estimate (the main
/// streams' among them; the steps' last images where they ended there). One set's image carries
/// Poisson noise of w photons per ray, a share of the residuals' variance that the tests allow
/// for but that varies with the streams: the tests' value then depends on the seed more than
/// their null distribution says. The mean of S independent ones carries w / S.
void MeanTemplate(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                  size_t final_level, size_t s_all, OptimumDerivatives* od) {
  Simulated first;
  std::vector<Images> at;
  for (size_t s = 0; s < s_all && run.Budget(); ++s) {
    Simulated sim = run.Images(best, final_level, spec.seed + kDerivativeSetSeedStride * s,
                               Stage::kFinal, nullptr);
    at.push_back(sim.photons);
    if (s == 0) first = std::move(sim);
  }
  if (at.size() == s_all) {
    od->mean_sim = std::move(first);
    od->mean_sim.photons = MeanImages(at, 0, 1);
    for (double& w : od->mean_sim.photons_per_ray) w /= double(s_all);
    od->mean_sets = s_all;
  }
}

/// The final steps' estimating equation at theta_c (the sets' point), with what its root's steps
/// need again: the halves' candidate columns and mean images, the chosen combination of each
/// parameter's traced and smoothed columns, and the equation's value there.
struct CrossFittedEquation {
  Columns cand_a, cand_b;
  Images ca, cb;
  Eigen::MatrixXd combination;
  Eigen::VectorXd g_all;
};

/// Builds the equation from the S derivative sets and fills od's score fields (the response,
/// the variances, the smoothing weights, the candidates' response and variance).
CrossFittedEquation BuildEquation(FitModel& model, const FitSpec& spec,
                                  const std::vector<Differences>& sets,
                                  const std::vector<double>& best, const Eigen::VectorXd& prior,
                                  const std::vector<double>& read_variance, double k, int bin,
                                  OptimumDerivatives* od_out) {
  OptimumDerivatives& od = *od_out;
  const size_t P = spec.parameters.size(), S = sets.size();
  // The estimating equation, cross-fitted over the two halves a (sets 0, 2, ...) and b
  // (1, 3, ...), each with its mean image c at theta_c (the plain count) and mean derivative
  // images J (as traced), J~ (per parameter as traced or smoothed) and weights W = 1/(c + r^2):
  //   U(theta) = J~_b^T W_b (e - c_a - J_a (theta - theta_c))
  //            + J~_a^T W_a (e - c_b - J_b (theta - theta_c)) = 0.
  // Each term's J~ and W come from rays independent of its template's and of e, so
  // E[e - c] = 0 makes U vanish on average at the truth in every pixel, dark ones included,
  // whatever J~ (the search's score, e / (count + one ray) - 1, is biased by -exp(-k mu) per
  // pixel: with smoothed derivatives reaching into a drop's dark ring it moved case A's index
  // by +10 bounds). The template is the mean of all S sets' images, not one: its shot noise
  // adds mu / (k S / 2) per term instead of mu / k. The smoothing ([1/4, 1/2, 1/4]) shrinks a
  // ray's pixel-edge dipole in a central difference about 20-fold while the derivative, smooth
  // over a pixel, passes. U is linear in theta: its root is theta_c + A^-1 g.
  const size_t na = (S + 1) / 2, nb = S / 2;
  std::vector<Images> centers;
  std::vector<Columns> cand_sets;  // each set's candidate columns, smoothed once
  for (const Differences& d : sets) {
    centers.push_back(d.mu.photons);
    cand_sets.push_back(Candidates(d.dmu));
  }
  const Images ca = MeanImages(centers, 0, 2), cb = MeanImages(centers, 1, 2);
  const Images vm = MeanImages(centers, 0, 1);  // the weights' mean image for the variances
  const Columns cand_a = MeanColumns(cand_sets, 0, 2), cand_b = MeanColumns(cand_sets, 1, 2);
  Simulated sim_a, sim_b;
  sim_a.photons = ca, sim_b.photons = cb;
  // Over the 2P candidate columns: the response A (2P x P), g, and U's variance at the truth:
  // the experiment's share B_e = (J~_a + J~_b)^T W (J~_a + J~_b), which with J~'s noise
  // included is exactly the spread a noisy J~ gives the root, and the templates' share B_t.
  Eigen::MatrixXd a_all = ToEigen(model.CrossInformation(cand_b, od.half_a.dmu, cb, bin)) +
                          ToEigen(model.CrossInformation(cand_a, od.half_b.dmu, ca, bin));
  Eigen::VectorXd g_all = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(2 * P));
  {
    const std::vector<double> ga = model.Score(sim_a, cand_b, cb, bin);
    const std::vector<double> gb = model.Score(sim_b, cand_a, ca, bin);
    for (size_t i = 0; i < 2 * P; ++i) g_all(Eigen::Index(i)) = ga[i] + gb[i];
  }
  const Columns cand_sum = Plus(cand_a, cand_b);
  Eigen::MatrixXd be_all = ToEigen(model.CrossInformation(cand_sum, cand_sum, vm, bin));
  // Gaussian priors (Parameter::prior_*): the term 2 Lambda (m - theta) in U, on the scale of
  // the two halves' sum (each about the full score), so the response gains 2 Lambda and U's
  // variance 4 Lambda (the prior's mean is a measurement with variance 1 / Lambda); the same
  // for either column of a parameter.
  for (size_t i = 0; i < P; ++i) {
    const double l = prior(Eigen::Index(i));
    if (!(l > 0)) continue;
    for (size_t c : {i, P + i}) {
      a_all(Eigen::Index(c), Eigen::Index(i)) += 2 * l;
      g_all(Eigen::Index(c)) += 2 * l * (spec.parameters[i].prior_mean - best[i]);
      for (size_t c2 : {i, P + i}) be_all(Eigen::Index(c), Eigen::Index(c2)) += 4 * l;
    }
  }
  const Eigen::MatrixXd bt_all =
      ToEigen(model.CrossInformation(cand_b, cand_b, vm, bin)) / (k * double(na)) +
      ToEigen(model.CrossInformation(cand_a, cand_a, vm, bin)) / (k * double(nb));
  // The derivatives' noise in B_e (DerivativeNoise).
  const Eigen::MatrixXd n_all = DerivativeNoise(model, sets, cand_sets, vm, bin, na, nb);
  // Per parameter a convex combination of its two columns, (1 - w) as traced + w smoothed,
  // with the weights that give the smallest variance of the root, summed over the parameters
  // in units of their Cramer-Rao bounds (the halves' cross product; SmoothingWeights). The
  // weights use the derivative sets only, never the experiment, so the equation stays
  // unbiased; each row combines its own parameter's two columns only and never extrapolates
  // (a free combination of all 2P columns, T = A^T V^-1, fitted the noise of V for weak
  // nuisances).
  const Matrix crb = InverseSpd(
      FisherInformation(od.half_a.mu.photons, od.half_a.dmu, od.half_b.dmu, read_variance));
  const Eigen::MatrixXd v_all = be_all + bt_all;
  Eigen::VectorXd scale = Eigen::VectorXd::Zero(Eigen::Index(P));
  for (size_t i = 0; i < P && !crb.empty(); ++i) scale(Eigen::Index(i)) = crb[i][i];
  const std::vector<double> weight =
      crb.empty() ? std::vector<double>(P, 1.0) : SmoothingWeights(a_all, v_all, scale);
  const Eigen::MatrixXd combination = SmoothingCombination(weight);
  od.score_response = combination * a_all;
  od.score_prior = 2 * prior;
  od.score_variance_experiment = combination * be_all * combination.transpose();
  od.score_variance_template = combination * bt_all * combination.transpose();
  od.score_derivative_noise = combination * n_all * combination.transpose();
  od.score_smoothing = weight;
  od.candidate_response = a_all, od.candidate_variance = v_all;
  od.score_scale = scale;
  od.score_dmu.assign(cand_sum.size(), {});
  for (size_t m = 0; m < cand_sum.size(); ++m)
    for (size_t i = 0; i < P; ++i) {
      Image im = cand_sum[m][i];
      for (size_t q = 0; q < im.pixels.size(); ++q)
        im.pixels[q] = (1 - weight[i]) * im.pixels[q] + weight[i] * cand_sum[m][P + i].pixels[q];
      od.score_dmu[m].push_back(std::move(im));
    }
  return {cand_a, cand_b, ca, cb, combination, g_all};
}

}  // namespace

OptimumDerivatives FinalSteps(Runner& run, const FitSpec& spec, std::vector<double>* best_io,
                              const FitResult& res) {
  FitModel& model = run.model();
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  std::vector<double>& best = *best_io;
  // Derivatives at the optimum from `jacobian_seeds` independent sets of ray streams (the
  // uncertainties' too) and the root of a cross-fitted estimating equation built from them
  // (docs/design/fit-estimator.md, "Finite rays"). With fixed ray streams a central difference
  // counts the rays that cross pixel edges, and at photon-matched rays that counting noise is
  // as large as the derivative itself for z and the index (a single set's index column has a
  // cosine of 0.62 with the exact one): the root of J^T r = 0 with such a J scatters up to 2x
  // the Cramer-Rao bound. When the root lies more than half a step (the stencil's half-width)
  // of any parameter from where the sets were taken, they are taken again there (at most three
  // rounds, after a pilot round of two sets, below): along the curved z-radius-index valley a
  // single linearisation stops short.
  OptimumDerivatives od;
  const std::vector<double> read_variance = ReadVariance(spec);
  const double k = spec.RaysPerPhoton();
  const int bin = model.BinAt(final_level);
  const Eigen::VectorXd prior = PriorPrecision(spec);
  bool steps_ran = false;
  const bool steps = FinalStepsRun(spec);
  size_t s_all = size_t(std::max(2, spec.rays.jacobian_seeds));
  // A pilot round first (with the final steps and more than two sets): two sets and their root.
  // Where that root lies more than half a step from the search's optimum (the quarter-ray
  // search leaves the index 2-3 bounds off in most fits), all sets are taken at the pilot's
  // root instead, which saves a whole round of S (P + 1) images; otherwise the pilot's two
  // sets are kept and the others join them where they were taken (the same sets as without
  // the pilot).
  bool pilot = steps && s_all > 2;
  std::vector<Differences> sets;  // the sets taken at `best`
  // Where the steps stop with Q above 1 (no step lowers it), the sets' noise has left the
  // response weak along some direction: twice the sets at the estimate (at most twice). Where
  // the estimate did not move, the sets already taken there are kept and the new ones join them.
  int more_sets = 0;
  auto MoreSets = [&](bool moved) {
    if (!(od.root_q > 1) || more_sets >= 2 || 2 * s_all > kMaxJacobianSeeds || !run.Budget())
      return false;
    ++more_sets, s_all *= 2;
    if (moved) sets.clear();
    return true;
  };
  for (int round = 0; round < 3 && res.status != FitStatus::kFlat && spec.uncertainties &&
                      (round == 0 || run.Budget());) {
    for (size_t s = sets.size(); s < (pilot ? 2 : s_all); ++s)
      sets.push_back(Differentiate(run, spec, best, final_level,
                                   spec.seed + kDerivativeSetSeedStride * s, Stage::kFisher,
                                   SetStencil(s, steps), s == 0 || steps));
    const size_t S = sets.size();
    od.half_a = AverageSets(sets, 0, 2), od.half_b = AverageSets(sets, 1, 2);
    if (!steps) {
      // (The sets are always taken: the uncertainties need them.) The profile-likelihood paths
      // then score with the sets other than the main streams' and respond with the halves'
      // cross information.
      od.score_dmu = AverageSets(sets, 1, 1).dmu;
      od.score_response = ToEigen(
          FisherInformation(od.half_a.mu.photons, od.half_a.dmu, od.half_b.dmu, read_variance));
      od.score_response.diagonal() += prior;
      od.score_prior = prior;
      break;
    }
    steps_ran = true;
    const CrossFittedEquation eq =
        BuildEquation(model, spec, sets, best, prior, read_variance, k, bin, &od);
    const auto lu = od.score_response.fullPivLu();
    if (!lu.isInvertible()) {
      if (!pilot) break;
      pilot = false;  // the full sets where the pilot's were taken
      continue;
    }
    // The root. The linear prediction c_h + J_h (theta - theta_c) carries J_h's counting noise
    // times the distance from theta_c, which can be a few sigma (the coarse optimum), and where
    // the equation is nearly singular (weak nuisances) its linear root can be far off: so each
    // step is tried with the halves' images traced at its end (S images, not S (P + 1)) and
    // kept only when the equation's value there, in units of the root's statistical spread,
    // Q = U^T (B_e + B_t)^-1 U, falls (else halved, at most twice); the steps end when the next one
    // is below a fifth of a sigma (Q < kPolishTolerance) or after four.
    const Eigen::MatrixXd b_total = od.score_variance_experiment + od.score_variance_template;
    const auto b_solver = b_total.completeOrthogonalDecomposition();
    auto Q = [&](const Eigen::VectorXd& v) { return v.dot(b_solver.solve(v)); };
    auto Select = [&](const std::vector<double>& ga, const std::vector<double>& gb,
                      const std::vector<double>& y) {
      Eigen::VectorXd g2 = Eigen::VectorXd::Zero(static_cast<Eigen::Index>(2 * P));
      for (size_t c = 0; c < 2 * P; ++c) g2(Eigen::Index(c)) = ga[c] + gb[c];
      Eigen::VectorXd v = eq.combination * g2;
      for (size_t i = 0; i < P; ++i)
        v(Eigen::Index(i)) += 2 * prior(Eigen::Index(i)) * (spec.parameters[i].prior_mean - y[i]);
      return v;
    };
    auto GAt = [&](const std::vector<double>& y) {
      Simulated at_a, at_b;  // the halves' mean images at y, as c_a and c_b at theta_c
      std::vector<Images> at(S);
      for (size_t s2 = 0; s2 < S; ++s2)
        at[s2] = run.Images(y, final_level, spec.seed + kDerivativeSetSeedStride * s2,
                            Stage::kFinal, nullptr)
                     .photons;
      at_a.photons = MeanImages(at, 0, 2), at_b.photons = MeanImages(at, 1, 2);
      return Select(model.Score(at_a, eq.cand_b, eq.cb, bin),
                    model.Score(at_b, eq.cand_a, eq.ca, bin), y);
    };
    Eigen::VectorXd g = eq.combination * eq.g_all;
    double q = Q(g);
    std::vector<double> x = best;
    bool stepped = false;
    for (int it = 0; it < 4 && q >= kPolishTolerance && std::isfinite(q) && run.Budget(); ++it) {
      const Eigen::VectorXd step = lu.solve(g);
      if (!step.allFinite()) break;
      bool accepted = false;
      for (double f = 1; f >= 0.25 && run.Budget(); f *= 0.5) {
        std::vector<double> y = x;
        for (size_t i = 0; i < P; ++i) y[i] += f * step(Eigen::Index(i));
        y = Clip(y, spec);
        const Eigen::VectorXd gy = GAt(y);
        const double qy = Q(gy);
        if (qy < q) {
          x = y, g = gy, q = qy, accepted = stepped = true;
          break;
        }
      }
      if (!accepted) break;
    }
    if (!pilot) od.root_q = q;
    bool far = false;
    for (size_t i = 0; i < P && stepped; ++i)
      far = far || std::abs(x[i] - best[i]) > 0.5 * spec.parameters[i].step;
    if (pilot) {  // not a round: the full sets follow, here or at the pilot's root
      pilot = false;
      if (far) best = x, sets.clear();
      continue;
    }
    if (!stepped && !MoreSets(false)) break;
    if (!stepped) continue;  // with more sets
    best = x;
    if (!far && !MoreSets(true)) break;
    if (!far) continue;  // with more sets
    sets.clear();
    ++round;
  }
  // The main streams' images at the root: the uncertainties' template, and the report's, the
  // residuals' and the goodness of fit's where the sets' mean below is not made.
  if (steps_ran && run.Budget()) {
    double e = 0;
    od.final_sim = run.Images(best, final_level, spec.seed, Stage::kFinal, &e);
  }
  // The goodness of fit's template (MeanTemplate).
  if (!spec.exact_images() && res.status != FitStatus::kFlat && spec.uncertainties && run.Budget())
    MeanTemplate(run, spec, best, final_level, s_all, &od);
  return od;
}

namespace {

/// Repeated fits with independent ray streams, from the optimum, at the final fraction.
void RepeatFits(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                FitResult* res_out) {
  FitResult& res = *res_out;
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
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

/// Error-function slices through the optimum: +-3 sigma (curvature), at least +-step/2, each
/// point the mean over two ray-stream sets. With fixed streams a slice is a staircase whose
/// steps can exceed its rise over one sigma; the two sets' differences, less their mean (the
/// level differs between sets, not the shape), measure that noise for the report.
void Slices(Runner& run, const FitSpec& spec, const std::vector<double>& best, FitResult* res_out) {
  FitResult& res = *res_out;
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  const uint64_t second = spec.seed + kDerivativeSetSeedStride;
  for (size_t i = 0; i < P; ++i) {
    ParameterResult& pr = res.parameters[i];
    const double half = std::max(3 * pr.sigma_curvature, 0.5 * spec.parameters[i].step);
    std::vector<double> diff;
    for (int k = 0; k < spec.slice_points && run.Budget(); ++k) {
      std::vector<double> th = best;
      th[i] = best[i] - half + 2 * half * k / (spec.slice_points - 1);
      if (th[i] < pr.lower || th[i] > pr.upper) continue;
      const double a = run.Eval(th, final_level, spec.seed, Stage::kSlice);
      const double b = run.Eval(th, final_level, second, Stage::kSlice);
      pr.slice_x.push_back(th[i]);
      pr.slice_error.push_back(0.5 * (a + b));
      diff.push_back(a - b);
    }
    const size_t n = diff.size();
    if (n >= 3) {
      double m = 0, v = 0;
      for (double d : diff) m += d / double(n);
      for (double d : diff) v += (d - m) * (d - m) / double(n - 1);
      pr.slice_noise = 0.5 * std::sqrt(v);  // sd of (a + b) / 2 = sd(a - b) / 2
    }
  }
}

}  // namespace

GoodnessOfFit TestedGoodness(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                             const Simulated& best_sim, const OptimumDerivatives& od,
                             const FitResult& res) {
  FitModel& model = run.model();
  const size_t P = spec.parameters.size();
  const size_t final_level = spec.rays.fractions.size() - 1;
  const int bin = model.BinAt(final_level);
  const bool mean = !od.mean_sim.photons.empty();
  const Simulated& at = mean ? od.mean_sim : best_sim;
  // Exact derivative images carry no noise: the image is stepped along them. The ray model's
  // without derivative sets (no final steps): no step.
  if (spec.exact_images()) return model.Goodness(at, bin, P, od.half_a.dmu, od.half_b.dmu);
  GoodnessOfFit plain = model.Goodness(at, bin, P);
  plain.template_sets = mean ? od.mean_sets : 1;
  if (!mean) return plain;
  std::vector<double> step = model.TemplateStep(at, bin, od.half_a.dmu, od.half_b.dmu);
  if (step.size() != P || res.parameters.size() != P) return plain;
  // A step the derivatives' noise made long (a weakly determined direction) is shortened to 3
  // reported sigmas: the estimate's own error from the ray streams is within that.
  double worst = 0;
  for (size_t j = 0; j < P; ++j)
    if (res.parameters[j].sigma > 0)
      worst = std::max(worst, std::abs(step[j]) / res.parameters[j].sigma);
  if (!std::isfinite(worst)) return plain;
  if (worst > 3)
    for (double& v : step) v *= 3 / worst;
  std::vector<double> there = best;
  for (size_t j = 0; j < P; ++j) there[j] += step[j];
  there = Clip(there, spec);
  if (there == best) return plain;
  OptimumDerivatives moved;
  MeanTemplate(run, spec, there, final_level, od.mean_sets, &moved);
  if (moved.mean_sim.photons.empty()) return plain;
  GoodnessOfFit g = model.Goodness(moved.mean_sim, bin, P);
  if (!(g.deviance < plain.deviance)) return plain;
  g.template_sets = od.mean_sets;
  g.estimate_deviance = plain.deviance;
  g.step.resize(P);
  for (size_t j = 0; j < P; ++j) g.step[j] = there[j] - best[j];
  return g;
}

Simulated EstimateUncertainties(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                                const OptimumDerivatives& od, FitResult* res_out) {
  FitResult& res = *res_out;
  const size_t P = spec.parameters.size();
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
  // (Gaussian priors add their precisions to the curvature and to the Fisher information: the
  // bound is then the Bayesian one, Van Trees.)
  const Eigen::VectorXd prior = PriorPrecision(spec);
  Eigen::MatrixXd JtJ =
      0.5 * (d.jacobian.transpose() * d2.jacobian + d2.jacobian.transpose() * d.jacobian);
  JtJ.diagonal() += prior;
  const Matrix cov = InverseSpd(FromEigen(JtJ));
  const double k = spec.RaysPerPhoton();
  // The estimate's covariance. With the final steps, the root of their estimating equation:
  // A^-1 (B_e + B_t) A^-T (the experiment's and the templates' noise through the chosen
  // derivatives, whose own noise B_e includes); sigma_derivatives is the part A^-1 N A^-T,
  // sigma_simulation the templates' and the derivatives'. Otherwise C (1 + 1/k), C the
  // deviance's curvature, of which C / k is the simulation's.
  Eigen::MatrixXd a_inv;
  if (od.score_response.size() > 0 && od.score_variance_experiment.size() > 0) {
    const auto lu = od.score_response.fullPivLu();
    if (lu.isInvertible()) a_inv = lu.inverse();
  }
  auto Sandwich = [&](const Eigen::MatrixXd& m) { return a_inv * m * a_inv.transpose(); };
  auto SetSigmas = [&](const Matrix& c) {
    Matrix t = c;
    std::vector<double> sim(P), der(P, 0.0);
    for (size_t i = 0; i < P; ++i) {
      for (size_t j = 0; j < P; ++j) t[i][j] *= 1 + 1 / k;
      sim[i] = c[i][i] / k;
    }
    if (a_inv.size() > 0) {
      t = FromEigen(Sandwich(od.score_variance_experiment + od.score_variance_template));
      const Eigen::MatrixXd n = Sandwich(od.score_derivative_noise);
      const Eigen::MatrixXd tm = Sandwich(od.score_variance_template);
      for (size_t i = 0; i < P; ++i) {
        const auto ii = Eigen::Index(i);
        der[i] = n(ii, ii), sim[i] = tm(ii, ii) + n(ii, ii);
      }
    }
    for (size_t i = 0; i < P; ++i) {
      res.parameters[i].sigma = std::sqrt(std::max(0.0, t[i][i]));
      res.parameters[i].sigma_derivatives = std::sqrt(std::max(0.0, der[i]));
      res.parameters[i].sigma_simulation = std::sqrt(std::max(0.0, sim[i]));
    }
    res.correlation = Correlation(t);
  };
  for (size_t i = 0; i < P && i < od.score_smoothing.size() && a_inv.size() > 0; ++i) {
    const double w = od.score_smoothing[i];
    char mixed[64];
    std::snprintf(mixed, sizeof mixed, "%.3g as traced + %.3g smoothed", 1 - w, w);
    res.parameters[i].score_derivative = w <= 0 ? "as traced" : w >= 1 ? "smoothed" : mixed;
  }
  if (!cov.empty()) {
    for (size_t i = 0; i < P; ++i) res.parameters[i].sigma_curvature = std::sqrt(cov[i][i]);
    SetSigmas(cov);
  }
  Matrix crb;
  if (spec.cramer_rao || cov.empty()) {
    Matrix fisher = FisherInformation(d.mu.photons, d.dmu, d2.dmu, ReadVariance(spec));
    for (size_t i = 0; i < fisher.size(); ++i) fisher[i][i] += prior(Eigen::Index(i));
    crb = InverseSpd(fisher);
  }
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
  } else if (cov.empty() && a_inv.size() > 0) {
    // Neither information from the two halves is positive definite, but the final steps'
    // estimating equation has an invertible response: its sandwich is the covariance the
    // sigmas come from whenever it exists (SetSigmas), and it needs neither.
    SetSigmas(Matrix(P, std::vector<double>(P, 0.0)));
    res.message +=
        "; the information from the two independent halves of the derivative sets is not "
        "positive definite (their ray noise along a weakly determined direction): sigmas from "
        "the final steps' estimating equation alone, no curvature or Cramer-Rao bound";
  } else if (cov.empty()) {
    res.message +=
        "; the curvature does not determine every parameter (information matrix not "
        "positive definite): their uncertainties are not reported";
  }
  if (spec.cramer_rao && crb.empty() && !cov.empty())
    res.message +=
        "; no Cramer-Rao bound: the information from the two independent halves of the "
        "derivative sets is not positive definite (their ray noise along a weakly determined "
        "direction; more jacobian_seeds or rays give one)";
  if (spec.repeat_seeds >= 2) RepeatFits(run, spec, best, &res);
  if (spec.slice_points >= 3) Slices(run, spec, best, &res);
  // Profile-likelihood intervals where the curvature interval may not be trustworthy.
  ProfileIntervals(run, spec, best, od, &res);
  return best_sim;
}

}  // namespace raymatch::fit::internal
