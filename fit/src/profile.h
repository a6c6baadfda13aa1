#pragma once
// Profile-likelihood intervals (docs/design/fit-estimator.md, "Profile-likelihood intervals").
// Not installed.
#include <string>
#include <vector>

namespace raymatch::fit {
struct FitSpec;
struct FitResult;
}  // namespace raymatch::fit

namespace raymatch::fit::internal {

class Runner;
struct OptimumDerivatives;

/// A profile deviance curve in units of the curvature's sigma: Delta(t) = D_profile - its
/// minimum, where the parameter is best + t sigma and the others are at their conditional
/// optimum.
struct ProfileCurve {
  double lower_t = -1, upper_t = 1;  ///< where Delta first reaches `level` on either side
  bool lower_open = false, upper_open = false;  ///< no crossing within the range (see below)
  double min_t = 0;                             ///< where Delta is smallest
  std::vector<double> delta;                    ///< Delta at the given t
};

/// The profile deviance from its slope: g(t) = (1/2) dDelta/dt at sorted points t (g = t for a
/// quadratic deviance with sigma 1; at least two points). g is interpolated (monotone cubic
/// with four points or more, else quadratic or linear), extrapolated
/// linearly (slope not below 0) to one sampled span beyond either end, and integrated; a side
/// with no crossing of `level` up to there is open (its t is the end of that range).
ProfileCurve ProfileFromScores(const std::vector<double>& t, const std::vector<double>& g,
                               double level = 1);

/// For the parameters whose curvature interval may not be trustworthy (spec.profile; the reason
/// in ParameterResult::profile_reason), the profile deviance along the linearised profile path
/// from the efficient score with the averaged derivative images (fit/src/profile.cpp).
void ProfileIntervals(Runner& run, const FitSpec& spec, const std::vector<double>& best,
                      const OptimumDerivatives& od, FitResult* res);

/// After the sigmas are final (mismatch inflation included): the interval's ends as values,
/// best + t x sigma, clipped to the parameter's bounds.
void ProfileValues(FitResult* res);

}  // namespace raymatch::fit::internal
