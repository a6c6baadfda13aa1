// The camera read-out model (core/camera_readout.h): code values against the linear camera model
// of EMVA 1288 (Release 4.0, section 2: mean = dark + e/K, variance = sigma_r^2/K^2 + 1/12 for
// the quantisation), with tolerances from the sample size.
#include "raymatch/core/camera_readout.h"

#include <gtest/gtest.h>

#include <cmath>

namespace raymatch {
namespace {

CameraReadout Camera(double gain, double dark, double read, double well, int bits) {
  CameraReadout c;
  c.gain_e_per_dn = gain, c.dark_dn = dark, c.read_noise_e = read, c.well_capacity_e = well,
  c.bit_depth = bits;
  return c;
}

TEST(CameraReadout, WithoutReadNoiseCodeValuesAreRoundedElectronsOverGainPlusDark) {
  Image e(4, 1);
  e.pixels = {0, 10, 11, 2500};
  ReadoutCounts n;
  const Image dn = ToCodeValues(e, Camera(4, 64, 0, 0, 12), 1, 0, &n);
  EXPECT_EQ(dn.pixels, (std::vector<float>{64, 67 /* 66.5 rounds away from 0 */, 67, 689}));
  EXPECT_EQ(n.saturated, 0u);
  EXPECT_EQ(n.clipped_low, 0u);
}

TEST(CameraReadout, MeanAndVarianceFollowTheLinearModel) {
  // 40000 pixels of 1000 electrons, gain 2 e/DN, 6 e read noise, dark 100 DN: shot noise is the
  // caller's (the counts are a Poisson sample already), so the variance is read noise and
  // quantisation only: (6/2)^2 + 1/12 = 9.083 DN^2.
  Image e(200, 200, 1000.f);
  const Image dn = ToCodeValues(e, Camera(2, 100, 6, 0, 12), 42, 3);
  double m = 0, v = 0;
  for (float x : dn.pixels) m += x;
  m /= double(dn.size());
  for (float x : dn.pixels) v += (x - m) * (x - m);
  v /= double(dn.size() - 1);
  const double var = 9.0 + 1.0 / 12;
  // 5 standard errors: of the mean sqrt(var/N), of the variance var sqrt(2/(N-1)).
  EXPECT_NEAR(m, 600.0, 5 * std::sqrt(var / 40000));
  EXPECT_NEAR(v, var, 5 * var * std::sqrt(2.0 / 39999));
}

TEST(CameraReadout, FullWellTopCodeAndZeroAreClippedAndCounted) {
  Image e(3, 1);
  e.pixels = {1e6f, 100.f, 0.f};
  ReadoutCounts n;
  // The well (4500 e) clips the first pixel: 4500 / 1.1 = 4091 DN, below the 12-bit top.
  Image dn = ToCodeValues(e, Camera(1.1, 0, 0, 4500, 12), 1, 0, &n);
  EXPECT_EQ(dn.pixels[0], 4091.f);
  EXPECT_EQ(n.saturated, 1u);
  EXPECT_EQ(n.clipped_low, 1u);  // the empty pixel reads 0
  // A gain below the well's: the converter's top code value (2^8 - 1) clips first.
  dn = ToCodeValues(e, Camera(1, 0, 0, 4500, 8), 1, 0, &n);
  EXPECT_EQ(dn.pixels[0], 255.f);
  EXPECT_EQ(dn.pixels[1], 100.f);
  EXPECT_EQ(n.saturated, 1u);
}

TEST(CameraReadout, ReadNoiseBelowZeroIsClippedAtCodeZero) {
  // No dark level: half of the empty pixels would read below zero.
  Image e(100, 100, 0.f);
  ReadoutCounts n;
  const Image dn = ToCodeValues(e, Camera(1, 0, 5, 0, 12), 9, 0, &n);
  for (float x : dn.pixels) EXPECT_GE(x, 0.f);
  // P(round(5 g) <= 0) = P(g < 0.1) = 0.540; binomial sd sqrt(0.54 * 0.46 / 1e4) = 0.005.
  EXPECT_NEAR(double(n.clipped_low) / 1e4, 0.540, 5 * 0.005);
}

TEST(CameraReadout, TheSameStreamGivesTheSameFrameAndAnotherStreamAnother) {
  Image e(50, 20, 300.f);
  const CameraReadout c = Camera(1, 10, 4, 0, 12);
  EXPECT_EQ(ToCodeValues(e, c, 5, 1).pixels, ToCodeValues(e, c, 5, 1).pixels);
  EXPECT_NE(ToCodeValues(e, c, 5, 1).pixels, ToCodeValues(e, c, 5, 2).pixels);
  EXPECT_NE(ToCodeValues(e, c, 5, 1).pixels, ToCodeValues(e, c, 6, 1).pixels);
}

}  // namespace
}  // namespace raymatch
