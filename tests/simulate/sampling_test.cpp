// Samplers against their densities (chi-square, pbrt/Mitsuba style) with fixed seeds.
#include "raymatch/simulate/sampling.h"

#include <gtest/gtest.h>

#include "raymatch/core/rng.h"

namespace raymatch::simulate {
namespace {

// 16x16 map with a ramp and a hole; 1.6M samples; 255 degrees of freedom (254 non-empty bins
// minus one): the 99.9 % quantile of chi-square(253) is about 330.
TEST(Distribution2D, ChiSquareAgainstTheMap) {
  Image map(16, 16);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) map.at(x, y) = 1.0f + x + 0.5f * y;
  map.at(3, 4) = 0;
  map.at(10, 12) = 0;
  Distribution2D dist(map);
  std::vector<double> h(256, 0);
  const int N = 1600000;
  RayRng rng(99, 0, 0);
  for (int i = 0; i < N; ++i) {
    double x, y;
    dist.Sample(rng.Uniform(), rng.Uniform(), &x, &y);
    ASSERT_GE(x, 0);
    ASSERT_LT(x, 1);
    h[int(y * 16) * 16 + int(x * 16)] += 1;
  }
  double total = 0;
  for (float v : map.pixels) total += v;
  double chi2 = 0;
  for (int i = 0; i < 256; ++i) {
    const double e = N * map.pixels[i] / total;
    if (e == 0) {
      EXPECT_EQ(h[i], 0) << "sample in an empty cell " << i;
      continue;
    }
    chi2 += (h[i] - e) * (h[i] - e) / e;
  }
  EXPECT_LT(chi2, 330);
}

TEST(UnitDisc, UniformOverArea) {
  // Fraction inside radius 0.5 must be 0.25 (binomial sigma 4.3e-4 for 1M samples).
  RayRng rng(5, 0, 0);
  int inside = 0;
  const int N = 1000000;
  for (int i = 0; i < N; ++i) {
    double x, y;
    SampleUnitDisc(rng, &x, &y);
    ASSERT_LE(x * x + y * y, 1 + 1e-12);
    inside += x * x + y * y < 0.25;
  }
  EXPECT_NEAR(double(inside) / N, 0.25, 4 * 4.33e-4);
}

}  // namespace
}  // namespace raymatch::simulate

TEST(Distribution1D, BinsAtExactCdfValuesAndAcrossEmptyBins) {
  // Weights 1, 0, 2, 1 (n = 4): cdf 0, 1/4, 1/4, 3/4, 1, all exact in binary. A u equal to a cdf
  // value belongs to the bin that starts there (std::upper_bound's rule); the empty bin is never
  // chosen.
  const float f[] = {1, 0, 2, 1};
  const raymatch::simulate::Distribution1D d(f, 4);
  const struct {
    double u;
    int bin;
    double x;
  } cases[] = {{0.0, 0, 0.0},     {0.1, 0, 0.4 / 4},  {0.25, 2, 2.0 / 4},
               {0.5, 2, 2.5 / 4}, {0.75, 3, 3.0 / 4}, {0.875, 3, 3.5 / 4}};
  for (const auto& c : cases) {
    int bin = -1;
    const double x = d.Sample(c.u, &bin);
    EXPECT_EQ(bin, c.bin) << "u = " << c.u;
    EXPECT_NEAR(x, c.x, 1e-15) << "u = " << c.u;
  }
}
