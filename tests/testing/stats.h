#pragma once
// Shared statistical helpers for Monte Carlo tests.
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <utility>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::testing {

/// Standard error of a binomial fraction estimated from n trials with true probability p.
inline double BinomialSigma(double p, double n) { return std::sqrt(p * (1 - p) / n); }

/// z-score of an observed count k out of n against probability p.
inline double BinomialZ(double k, double n, double p) { return (k / n - p) / BinomialSigma(p, n); }

/// Reduced chi-square of a - sum_k w_k b_k over the central 32 x 32 pixels of independent
/// Poisson count images, with variance a + sum_k w_k^2 b_k; and the number of pixels used. An
/// image that is the weighted mean of the others in distribution gives 1 +- sqrt(2 / n).
inline std::pair<double, double> CentralChiSquare(const Image& a, const std::vector<Image>& b,
                                                  const std::vector<double>& w) {
  double chi2 = 0, n = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    if (std::abs(int(i % a.width) - a.width / 2) >= 16 ||
        std::abs(int(i / a.width) - a.height / 2) >= 16)
      continue;
    double mean = 0, var = a.pixels[i];
    for (size_t k = 0; k < b.size(); ++k) {
      mean += w[k] * b[k].pixels[i];
      var += w[k] * w[k] * b[k].pixels[i];
    }
    if (var <= 0) continue;
    chi2 += (a.pixels[i] - mean) * (a.pixels[i] - mean) / var;
    n += 1;
  }
  return {chi2 / n, n};
}

}  // namespace raymatch::testing
