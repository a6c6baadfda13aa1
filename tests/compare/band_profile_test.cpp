// The paper's Fig. 8 profile (issue 23): the band of +-1 standard deviation of the difference of
// two band sums against Poisson counts of known mean.
#include "raymatch/compare/band_profile.h"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "raymatch/core/error.h"

namespace raymatch::compare {
namespace {

Image PoissonImage(int w, int h, double mean, uint32_t seed) {
  std::mt19937_64 rng(seed);
  std::poisson_distribution<int> draw(mean);
  Image im(w, h);
  for (float& v : im.pixels) v = float(draw(rng));
  return im;
}

// Two independent images of mean 50 per pixel, rows 5-24 summed over 400 columns: each band sum
// is Poisson with mean 1000, their difference has sd sqrt(2000); the chi-square per column is 1
// within 5 of its standard deviations sqrt(2 / 400), and 68.3 % of the columns lie within the
// band (binomial sd 2.3 %: 5 of them allowed). With B the expectation itself the band is
// sqrt(sum A) and the chi-square per column again 1.
TEST(BandProfile, BandIsTheShotNoiseOfTheDifference) {
  const int W = 400;
  const Image a = PoissonImage(W, 30, 50, 1), b = PoissonImage(W, 30, 50, 2);
  const BandProfile p = RowBandProfile(a, b, 5, 25);
  ASSERT_EQ(p.columns, W);
  double within = 0, sum_a = 0;
  for (int y = 5; y < 25; ++y) sum_a += a.at(7, y);
  EXPECT_EQ(p.a[7], sum_a);
  for (int x = 0; x < W; ++x) {
    EXPECT_DOUBLE_EQ(p.difference[x], p.b[x] - p.a[x]);
    EXPECT_DOUBLE_EQ(p.sd[x], std::sqrt(p.a[x] + p.b[x]));
    within += std::abs(p.difference[x]) <= p.sd[x];
  }
  EXPECT_NEAR(p.chi2 / W, 1, 5 * std::sqrt(2.0 / W));
  const double share = within / W, sd = std::sqrt(0.683 * 0.317 / W);
  EXPECT_NEAR(share, 0.683, 5 * sd);
  Image expected(W, 30, 50.f);
  const BandProfile q = RowBandProfile(a, expected, 5, 25, false);
  EXPECT_DOUBLE_EQ(q.sd[3], std::sqrt(q.a[3]));
  EXPECT_NEAR(q.chi2 / W, 1, 5 * std::sqrt(2.0 / W));
  // The band is not the difference's sd when the images are summed over a wrong band: rows of
  // twice the mean give a chi-square per column far from 1.
  Image bright = PoissonImage(W, 30, 100, 3);
  EXPECT_GT(RowBandProfile(a, bright, 5, 25).chi2 / W, 10);
}

TEST(BandProfile, BadRowsAndSizesAreNamed) {
  const Image a(10, 8), b(10, 9);
  auto error = [](const Image& x, const Image& y, int r0, int r1) {
    try {
      RowBandProfile(x, y, r0, r1);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error(a, b, 0, 4).find("differ in size"), std::string::npos);
  EXPECT_NE(error(a, a, 4, 4).find("0 <= R0 < R1 <= 8"), std::string::npos);
  EXPECT_NE(error(a, a, 0, 9).find("0 <= R0 < R1 <= 8"), std::string::npos);
  Image neg(10, 8);
  neg.at(2, 3) = -1;
  EXPECT_NE(error(neg, a, 0, 8).find("column 2, row 3"), std::string::npos);
}

}  // namespace
}  // namespace raymatch::compare
