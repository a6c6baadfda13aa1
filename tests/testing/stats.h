#pragma once
// Shared statistical helpers for Monte Carlo tests.
#include <cmath>
#include <cstdint>

namespace raymatch::testing {

/// Standard error of a binomial fraction estimated from n trials with true probability p.
inline double BinomialSigma(double p, double n) { return std::sqrt(p * (1 - p) / n); }

/// z-score of an observed count k out of n against probability p.
inline double BinomialZ(double k, double n, double p) { return (k / n - p) / BinomialSigma(p, n); }

}  // namespace raymatch::testing
