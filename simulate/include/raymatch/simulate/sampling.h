#pragma once
// Sampling helpers: piecewise-constant 1D/2D distributions (inverse CDF, as in pbrt's
// PiecewiseConstant2D) for tabulated light fields, and uniform disc sampling.
#include <cmath>
#include <vector>

#include "raymatch/core/image.h"

namespace raymatch::simulate {

/// Piecewise-constant density over [0, 1) with n bins.
class Distribution1D {
 public:
  Distribution1D() = default;
  explicit Distribution1D(const float* f, int n);
  /// Maps u in [0,1) to x in [0,1); `*bin` receives the bin index.
  double Sample(double u, int* bin) const;
  double integral() const { return integral_; }
  int size() const { return static_cast<int>(func_.size()); }
  double Density(int bin) const { return integral_ > 0 ? func_[bin] / integral_ : 0; }
  /// The normalised cdf (size() + 1 values) and the guide table (a power-of-two size; entry k is
  /// the largest i with cdf()[i] <= k / guide().size()), for the tracer's SIMD packets.
  const std::vector<double>& cdf() const { return cdf_; }
  const std::vector<int>& guide() const { return guide_; }

 private:
  std::vector<double> func_, cdf_;
  // Guide table: guide_[k] is the largest i with cdf_[i] <= k / guide_.size() (a power of two,
  // so k / size and u * size are exact); a search starts there and steps forward.
  std::vector<int> guide_;
  double integral_ = 0;
};

/// Piecewise-constant density over the unit square from an image (row 0 at the top maps to
/// y in [0, 1/height) ... the caller decides the orientation).
class Distribution2D {
 public:
  Distribution2D() = default;
  explicit Distribution2D(const Image& img);
  /// (u0, u1) uniform -> (x, y) in [0,1)^2 with density proportional to the image.
  void Sample(double u0, double u1, double* x, double* y) const;
  bool empty() const { return rows_.empty(); }
  const Distribution1D& marginal() const { return marginal_; }  ///< over rows
  const Distribution1D& row(int y) const { return rows_[y]; }   ///< in x, given row y
  int height() const { return static_cast<int>(rows_.size()); }

 private:
  std::vector<Distribution1D> rows_;  // conditional in x for each row
  Distribution1D marginal_;           // over rows
};

/// Uniform point in the unit disc by rejection from the square (4/pi tries on average). Cheaper
/// than a polar or concentric mapping (no sin/cos), and as the draws come from the ray's own
/// counter-based stream the result is still independent of threading.
template <class Rng>
inline void SampleUnitDisc(Rng& rng, double* x, double* y) {
  double a, b;
  do {
    a = 2 * rng.Uniform() - 1;
    b = 2 * rng.Uniform() - 1;
  } while (a * a + b * b >= 1.0);
  *x = a;
  *y = b;
}

/// Gauss-Legendre nodes and weights of order n on [a, b], appended to x and w.
void GaussLegendre(int n, double a, double b, std::vector<double>* x, std::vector<double>* w);

}  // namespace raymatch::simulate
