// Profile-likelihood intervals where the curvature interval may not be trustworthy
// (docs/design/fit-estimator.md, "Profile-likelihood intervals").
//
// The profile deviance of parameter i, D_p(theta_i) = min over the others of D, is what a
// likelihood-ratio interval needs. With fixed ray streams the deviance itself cannot be read
// at the scale of one sigma: rays crossing pixel edges make it a staircase whose steps are
// several units of deviance (bench/fit_accuracy.py case B: along one axis through the optimum
// the scatter about the parabola is comparable to its rise over +-3 sigma), so a profile from
// deviance differences would be noise. Its slope is smooth: by the
// envelope theorem dD_p/dtheta_i is the gradient of D along theta_i at the conditional optimum,
// and to first order in the distance to that optimum it is the efficient score
//   -2 (sc_i - F_i,rest F_rest,rest^-1 sc_rest) = -2 (C sc)_i / C_ii
// (C = F^-1; Neyman's C(alpha) score; Cox and Hinkley, Theoretical Statistics, 1974, 9.3), the
// score sc = sum_q dmu_q (e_q / T_q - 1) (FitModel::PoissonScore) with the final steps'
// derivative images from the independent ray-stream sets and C = A^-1, the inverse of their
// estimating equation's response, taken relative to its value at the optimum (the root of
// that equation); the staircase averages over every pixel. Along the
// linearised profile path theta(t) = best + t C e_i / sqrt(C_ii) (the others at their
// conditional optimum for a quadratic deviance; t in units of sigma_i = sqrt(C_ii)) the image
// is traced exactly, so the curvature of the model (a bending valley, an image that is not
// linear over the interval) enters; the score is integrated to the profile deviance. For a
// quadratic deviance g = -(C sc)_i / sigma_i = t and Delta = t^2: the interval is +-sigma.
#include "profile.h"

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
using std::isnan;  // Boost 1.74's pchip.hpp calls isnan unqualified (qualified in later Boost)
#include <boost/math/interpolators/pchip.hpp>
#include <cstdio>
#include <optional>

#include "runner.h"

namespace raymatch::fit::internal {

ProfileCurve ProfileFromScores(const std::vector<double>& t, const std::vector<double>& g,
                               double level) {
  const size_t n = t.size();
  ProfileCurve out;
  if (n < 2 || g.size() != n) return out;
  // g(x): the monotone piecewise-cubic (PCHIP, Fritsch and Carlson, SIAM J. Numer. Anal. 17,
  // 238 (1980)) interpolant of the samples, which keeps a rising slope rising between them (the
  // Poisson amplitude's 1/A-shaped slope: ends within 0.003 sigma where quadratics through three
  // samples are 0.09 off); with three or two samples (a bound cut the path) a quadratic or a line.
  std::optional<boost::math::interpolators::pchip<std::vector<double>>> pchip;
  if (n >= 4) pchip.emplace(std::vector<double>(t), std::vector<double>(g));
  auto Interp = [&](double x) {
    if (pchip) return (*pchip)(x);
    if (n == 2) return g[0] + (g[1] - g[0]) * (x - t[0]) / (t[1] - t[0]);
    double v = 0;
    for (size_t j = 0; j < 3; ++j) {
      double l = 1;
      for (size_t m = 0; m < 3; ++m)
        if (m != j) l *= (x - t[m]) / (t[j] - t[m]);
      v += l * g[j];
    }
    return v;
  };
  const double span = t.back() - t.front();
  const double s0 = std::max(0.0, (g[1] - g[0]) / (t[1] - t[0]));
  const double s1 = std::max(0.0, (g[n - 1] - g[n - 2]) / (t[n - 1] - t[n - 2]));
  auto G = [&](double x) {
    if (x < t.front()) return g.front() + s0 * (x - t.front());
    if (x > t.back()) return g.back() + s1 * (x - t.back());
    return Interp(x);
  };
  // Delta = 2 int g on a fine grid (trapezoid; 1200 steps per span), from one span below the
  // first sample to one above the last.
  const int steps = 3600;
  const double x0 = t.front() - span, h = 3 * span / steps;
  std::vector<double> x(steps + 1), d(steps + 1, 0.0);
  x[0] = x0;
  for (int s = 1; s <= steps; ++s) {
    x[s] = x0 + h * s;
    d[s] = d[s - 1] + h * (G(x[s - 1]) + G(x[s]));
  }
  // The minimum within the sampled range.
  int lo = steps / 3, hi = 2 * steps / 3, imin = lo;
  for (int s = lo; s <= hi; ++s)
    if (d[s] < d[imin]) imin = s;
  const double dmin = d[imin];
  out.min_t = x[imin];
  auto Cross = [&](int from, int dir, double* where, bool* open) {
    for (int s = from; s + dir >= 0 && s + dir <= steps; s += dir) {
      const double a = d[s] - dmin, b = d[s + dir] - dmin;
      if (b >= level) {
        *where = x[s] + (x[s + dir] - x[s]) * (level - a) / std::max(b - a, 1e-300);
        return;
      }
    }
    *where = dir > 0 ? x[steps] : x[0];
    *open = true;
  };
  Cross(imin, +1, &out.upper_t, &out.upper_open);
  Cross(imin, -1, &out.lower_t, &out.lower_open);
  for (double tk : t) {
    const int s = std::clamp(int(std::lround((tk - x0) / h)), 0, steps);
    out.delta.push_back(d[s] - dmin);
  }
  return out;
}

namespace {

/// Why parameter i's curvature interval may not be trustworthy ("" where it is).
std::string ProfileReason(const FitSpec& spec, const FitResult& res, size_t i) {
  if (spec.profile == ProfileMode::kNever) return "";
  if (spec.profile == ProfileMode::kAlways) return "requested (profile = \"always\")";
  const ParameterResult& p = res.parameters[i];
  char buf[200];
  if (p.sigma_curvature <= 0) return "the deviance's curvature is not positive definite";
  if (p.sigma > spec.parameters[i].step) {
    std::snprintf(buf, sizeof buf,
                  "sigma is %.2f steps: the derivatives (+-step/2) saw the image over less than "
                  "the interval",
                  p.sigma / spec.parameters[i].step);
    return buf;
  }
  size_t jmax = i;
  double cmax = 0;
  for (size_t j = 0; j < res.correlation.size(); ++j)
    if (j != i && std::abs(res.correlation[i][j]) > cmax)
      cmax = std::abs(res.correlation[i][j]), jmax = j;
  if (cmax > spec.profile_correlation) {
    std::snprintf(buf, sizeof buf, "correlation %.3f with %s", res.correlation[i][jmax],
                  spec.parameters[jmax].key.c_str());
    return buf;
  }
  return "";
}

}  // namespace

void ProfileIntervals(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                      const OptimumDerivatives& od, FitResult* res) {
  const size_t P = spec.parameters.size();
  if (spec.error != ErrorFunction::kPoisson || od.score_dmu.empty() || res->parameters.size() != P)
    return;
  std::vector<size_t> which;
  for (size_t i = 0; i < P; ++i) {
    res->parameters[i].profile_reason = ProfileReason(spec, *res, i);
    if (!res->parameters[i].profile_reason.empty()) which.push_back(i);
  }
  if (which.empty()) return;
  FitModel& model = run.model();
  const size_t level = spec.rays.fractions.size() - 1;
  const int bin = model.BinAt(level);
  // C: the inverse of the response A of the final steps' estimating equation, whose root's
  // conditional path along parameter i is C e_i.
  if (od.score_response.size() == 0) return;
  const auto lu = od.score_response.fullPivLu();
  if (!lu.isInvertible()) return;
  const Eigen::MatrixXd C = lu.inverse();
  auto Score = [&](const std::vector<double>& th, Eigen::VectorXd* sc) {
    double e = 0;
    const Simulated mu = run.Images(th, level, spec.seed, Stage::kProfile, &e);
    const std::vector<double> s = model.PoissonScore(mu, od.score_dmu, bin);
    *sc = Eigen::Map<const Eigen::VectorXd>(s.data(), Eigen::Index(P));
    for (size_t j = 0; j < P && od.score_prior.size() == Eigen::Index(P); ++j)  // priors' score
      (*sc)(Eigen::Index(j)) +=
          od.score_prior(Eigen::Index(j)) * (spec.parameters[j].prior_mean - th[j]);
  };
  // Scores relative to the one at the optimum: the main streams' template differs from the
  // final steps' (the sets' mean), so their score at that root is not zero but a constant of
  // their noise (and of the one-ray template's -exp(-k mu) in dark pixels); the path's change
  // is what the profile needs.
  Eigen::VectorXd sc0;
  Score(best, &sc0);
  auto ScoreBy = [&](const std::vector<double>& th, Eigen::VectorXd* sc) {
    Score(th, sc);
    *sc -= sc0;
  };
  for (size_t i : which) {
    ParameterResult& pr = res->parameters[i];
    if (!(pr.sigma > 0)) continue;
    // The path in units of the reported sigma (which adds the simulation's and the derivatives'
    // noise to C's): theta(t) = best + t r sigma_C u, r = sigma / sigma_C, so the model's
    // curvature is probed over the interval that is reported. The profile deviance from C's
    // score, Delta_C, is scaled to that sigma: Delta = Delta_C / r^2 (t^2 for a quadratic).
    // (A response that is not positive definite along i has no such path: no interval.)
    if (!(C(Eigen::Index(i), Eigen::Index(i)) > 0)) continue;
    const double sigma_c = std::sqrt(C(Eigen::Index(i), Eigen::Index(i)));
    const double r = pr.sigma / sigma_c;
    const Eigen::VectorXd u = C.col(Eigen::Index(i)) / sigma_c;
    auto G = [&](const Eigen::VectorXd& sc) { return -(C * sc)(Eigen::Index(i)) / sigma_c / r; };
    std::vector<std::pair<double, double>> points{{0.0, 0.0}};  // (t, g)
    bool lower_at_bound = false, upper_at_bound = false;
    for (double t : {-1.0, -2.0, 1.0, 2.0}) {  // (t may move to a bound below)
      if (!run.Budget() || (t < 0 ? lower_at_bound : upper_at_bound)) continue;
      // Where the path leaves the parameter's box, the last point is (just inside) the bound.
      const Parameter& par = spec.parameters[i];
      const double to = best[i] + t * pr.sigma, edge = t < 0 ? par.lower : par.upper;
      if ((t < 0 && to <= par.lower) || (t > 0 && to >= par.upper)) {
        (t < 0 ? lower_at_bound : upper_at_bound) = true;  // no point beyond this one
        t = 0.999 * (edge - best[i]) / pr.sigma;
        if (std::abs(t) < 0.05) continue;  // at the bound already
      }
      std::vector<double> th = best;
      for (size_t j = 0; j < P; ++j) th[j] += t * r * u(Eigen::Index(j));
      Eigen::VectorXd sc;
      ScoreBy(Clip(th, spec), &sc);
      points.push_back({t, G(sc)});
    }
    if (points.size() < 2) continue;
    std::sort(points.begin(), points.end());
    std::vector<double> tsorted, gsorted;
    for (const auto& [t, g] : points) tsorted.push_back(t), gsorted.push_back(g);
    const ProfileCurve c = ProfileFromScores(tsorted, gsorted);
    pr.profile_t = tsorted, pr.profile_delta = c.delta;
    // (A mismatch inflation, applied later, scales the interval with sigma: ProfileValues.)
    pr.profile_lower_sigmas = c.lower_t, pr.profile_upper_sigmas = c.upper_t;
    pr.profile_lower_open = c.lower_open || (lower_at_bound && c.lower_t <= tsorted.front());
    pr.profile_upper_open = c.upper_open || (upper_at_bound && c.upper_t >= tsorted.back());
  }
}

void ProfileValues(FitResult* res) {
  for (ParameterResult& p : res->parameters) {
    if (p.profile_reason.empty() || p.profile_t.empty()) continue;
    const double lo = p.best + p.profile_lower_sigmas * p.sigma;
    const double hi = p.best + p.profile_upper_sigmas * p.sigma;
    p.profile_lower = std::max(p.lower, lo), p.profile_upper = std::min(p.upper, hi);
    p.profile_lower_open = p.profile_lower_open || lo < p.lower;
    p.profile_upper_open = p.profile_upper_open || hi > p.upper;
    // Say so where the interval is not best +- sigma: by a quarter sigma or more on a side.
    // Quote it where it is wider or lopsided; where it is narrower on both sides, sigma (the
    // wider) stays the one to quote: that has been seen only where two parameters correlate
    // above 0.97 (a sphere's index and the light field's edge), where the path's projection
    // with the final steps' response C is itself uncertain (docs/design/fit-estimator.md).
    const bool narrower = !p.profile_lower_open && !p.profile_upper_open &&
                          p.profile_lower_sigmas > -0.75 && p.profile_upper_sigmas < 0.75;
    if (p.profile_lower_open || p.profile_upper_open ||
        std::abs(p.profile_lower_sigmas + 1) > 0.25 || std::abs(p.profile_upper_sigmas - 1) > 0.25)
      res->message += "; " + p.key + ": the profile-likelihood interval [" + Fmt(p.profile_lower) +
                      (p.profile_lower_open ? " or below" : "") + ", " + Fmt(p.profile_upper) +
                      (p.profile_upper_open ? " or above" : "") + "] is " +
                      (narrower ? "narrower than" : "not") + " best +- sigma (" + p.profile_reason +
                      "): " + (narrower ? "quote sigma, the wider" : "quote it");
  }
}

}  // namespace raymatch::fit::internal
