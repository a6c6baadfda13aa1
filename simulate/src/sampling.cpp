#include "raymatch/simulate/sampling.h"

#include <algorithm>

#include "stages-inl.h"  // the static target: the stages' one-lane instantiation

namespace raymatch::simulate {

Distribution1D::Distribution1D(const float* f, int n) : func_(f, f + n), cdf_(n + 1, 0.0) {
  for (int i = 0; i < n; ++i) cdf_[i + 1] = cdf_[i] + std::max(0.0, func_[i]) / n;
  integral_ = cdf_[n];
  if (integral_ > 0)
    for (double& c : cdf_) c /= integral_;
  else
    for (int i = 0; i <= n; ++i) cdf_[i] = double(i) / n;
  // About one guide entry per bin (the power of two at or above n), at most 2^20 (large ray
  // lists: a few steps more). On a light field's continued table (a few hundred rows) one per
  // bin was faster than one per two bins or eight per bin: the guides stay near the
  // core's cache while the steps along a row's cdf, each a gather that waits on memory, get few.
  size_t g = 1;
  while (g < size_t(n) && g < (size_t(1) << 20)) g *= 2;
  guide_.resize(g);
  int i = 0;
  for (size_t k = 0; k < g; ++k) {
    const double at = double(k) / double(g);
    while (i + 1 <= n && cdf_[i + 1] <= at) ++i;
    guide_[k] = i;
  }
}

double Distribution1D::Sample(double u, int* bin) const {
  // The stage the packet path samples light-field tables with (stages-inl.h), on one lane. A
  // guide table (in place of a binary search over the cdf, whose mispredicted branches were
  // 44 % of a light-field image's time) gives the start.
  using L = stages::ScalarLanes;
  int64_t i = 0;
  const double x = stages::HWY_NAMESPACE::Sample1D<L>(cdf_.data(), 0, guide_.data(), 0, size(),
                                                      static_cast<int64_t>(guide_.size()), u, &i);
  *bin = static_cast<int>(i);
  return x;
}

Distribution2D::Distribution2D(const Image& img) {
  std::vector<float> row_sums(img.height);
  for (int y = 0; y < img.height; ++y) {
    rows_.emplace_back(&img.pixels[size_t(y) * img.width], img.width);
    row_sums[y] = static_cast<float>(rows_.back().integral());
  }
  marginal_ = Distribution1D(row_sums.data(), img.height);
}

void Distribution2D::Sample(double u0, double u1, double* x, double* y) const {
  int row;
  *y = marginal_.Sample(u1, &row);
  int col;
  *x = rows_[row].Sample(u0, &col);
}

/// Gauss-Legendre nodes and weights on [a, b] (Newton's iteration on P_n from the Chebyshev
/// guess; Golub and Welsch's eigenvalue method gives the same to rounding).
void GaussLegendre(int n, double a, double b, std::vector<double>* x, std::vector<double>* w) {
  for (int i = 0; i < n; ++i) {
    double z = std::cos(M_PI * (i + 0.75) / (n + 0.5)), dp = 1;
    for (int it = 0; it < 100; ++it) {
      double p0 = 1, p1 = z;  // P_0, P_1
      for (int k = 2; k <= n; ++k) {
        const double p2 = ((2.0 * k - 1) * z * p1 - (k - 1.0) * p0) / k;
        p0 = p1, p1 = p2;
      }
      if (n == 1) p1 = z, p0 = 1;
      dp = n * (z * p1 - p0) / (z * z - 1);
      const double dz = p1 / dp;
      z -= dz;
      if (std::abs(dz) < 1e-15) break;
    }
    x->push_back(a + (b - a) * (1 - z) / 2);
    w->push_back((b - a) / ((1 - z * z) * dp * dp));
  }
}

}  // namespace raymatch::simulate
