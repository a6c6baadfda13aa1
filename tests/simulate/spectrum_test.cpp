// The illumination spectrum (issue 22): a ray near a dispersive object draws its wavelength, so an
// image under a spectrum is the power-weighted mean of monochromatic images. Tolerances: a
// chi-square over the pixels with the Poisson variances of both sides (as motion_test.cpp).
#include <gtest/gtest.h>

#include <cmath>

#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"
#include "stats.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::testing {
namespace {

using simulate::Dispersion;
using simulate::DispersionLaw;
using simulate::LoadScene;
using simulate::PlaneResult;
using simulate::RunControl;
using simulate::Simulator;
using simulate::SpectrumSpec;
using simulate::SpectrumType;

constexpr uint64_t kRays = 3000000;

// A strongly dispersive drop in water: n(0.4) = 1.58, n(0.7) = 1.4116 against the medium's
// 1.333 (relative indices 1.185 and 1.059: ball-lens foci about 29 and 81 um behind the drop's
// centre, so the lines' images 22 um behind it differ clearly).
Dispersion Cauchy() {
  Dispersion d;
  d.law = DispersionLaw::kCauchy;
  d.coefficients = {1.33, 0.04};
  return d;
}

Scene Drop(uint64_t seed, double index) {
  Scene s = MicroscopeScene(seed);
  s.medium_index = 1.333;
  s.source.half_angle_deg = 20;
  s.source.field_radius_um = 30;  // covers the central 32 x 32 pixels and the cone
  s.objects = {SphereObject(9, index, {1, 0, 3})};
  return s;
}

PlaneResult Trace(const Scene& s) {
  RunControl rc;
  rc.threads = 2;
  return Simulator(s).TracePlane(25, 0, kRays, rc);  // 22 um past the drop: n shows
}

TEST(Spectrum, TwoLinesGiveTheWeightedSumOfMonochromaticImages) {
  Scene s = Drop(7, 0);
  SpectrumSpec& sp = s.source.spectrum;
  sp.type = SpectrumType::kLines;
  sp.wavelengths_um = {0.4, 0.7};
  sp.weights = {0.3, 0.7};
  s.objects[0].dispersion = Cauchy();
  s.objects[0].index = Cauchy().IndexAt(sp.mean_um());
  ASSERT_TRUE(s.is_spectral());
  const PlaneResult r = Trace(s);
  EXPECT_GT(r.counters.wavelength_draws, kRays / 100);  // the rays near the drop
  const Image blue = Trace(Drop(101, Cauchy().IndexAt(0.4))).counts;
  const Image red = Trace(Drop(102, Cauchy().IndexAt(0.7))).counts;
  const auto [chi2, n] = CentralChiSquare(r.counts, {blue, red}, {0.3, 0.7});
  EXPECT_LT(std::abs(chi2 - 1), 5 * std::sqrt(2 / n)) << "reduced chi-square " << chi2;
  // The test can tell: the image of the stronger line alone is not the same.
  const auto [chi2_red, n2] = CentralChiSquare(r.counts, {red}, {1.0});
  EXPECT_GT(chi2_red, 1 + 10 * std::sqrt(2 / n2)) << chi2_red;
}

TEST(Spectrum, ConstantIndexStaysMonochromaticBitForBit) {
  Scene s = Drop(7, 1.36), plain = Drop(7, 1.36);
  s.source.spectrum.type = SpectrumType::kGaussian;
  s.source.spectrum.center_um = 0.462;
  s.source.spectrum.fwhm_um = 0.025;
  EXPECT_FALSE(s.is_spectral());
  const PlaneResult a = Trace(s), b = Trace(plain);
  EXPECT_EQ(a.counts.pixels, b.counts.pixels);
  EXPECT_EQ(a.counters.wavelength_draws, 0u);
}

// Water through IAPWS R9-97 at each wavelength: the issue's figures, 1.33964 at 449.5 nm and
// 1.33812 at 474.5 nm (about 20 C), a change of 0.0015 across the LED's spectrum.
TEST(Spectrum, WaterFollowsIapwsPerWavelength) {
  Dispersion w;
  w.law = DispersionLaw::kWater;
  w.temperature_K = 293.15;
  w.density_kg_m3 = simulate::WaterDensityTanaka(293.15);
  for (double l : {0.4495, 0.462, 0.4745})
    EXPECT_EQ(w.IndexAt(l), simulate::WaterRefractiveIndex(293.15, w.density_kg_m3, l).n);
  EXPECT_NEAR(w.IndexAt(0.4495), 1.33964, 2e-4);
  EXPECT_NEAR(w.IndexAt(0.4745), 1.33812, 2e-4);
  EXPECT_NEAR(w.IndexAt(0.4495) - w.IndexAt(0.4745), 0.00152, 1e-4);
}

// Deterministic quantiles of the Gaussian draw have its centre and standard deviation (the
// truncation at +-3 FWHM = 7 sigma changes the variance by 1e-10).
TEST(Spectrum, GaussianDrawsHaveTheSpectrumsCentreAndWidth) {
  SpectrumSpec sp;
  sp.type = SpectrumType::kGaussian;
  sp.center_um = 0.462, sp.fwhm_um = 0.025;
  const int K = 200000;
  double m = 0, m2 = 0;
  for (int k = 0; k < K; ++k) {
    const double l = sp.Sample((k + 0.5) / K);
    m += l / K, m2 += l * l / K;
  }
  EXPECT_NEAR(m, 0.462, 1e-9);
  EXPECT_NEAR(std::sqrt(m2 - m * m), 0.025 / 2.3548200450309493, 1e-4 * 0.0106);
}

TEST(Spectrum, SceneFileSpectrumAndDispersionLaws) {
  TempDir dir;
  const std::string scene = R"(name = "s"
[source]
type = "cone"
half_angle_deg = 20
spectrum = { type = "lines", wavelengths_um = [0.45, 0.47], weights = [1, 3] }
[[object]]
type = "sphere"
radius_um = 10
sellmeier_b = [0.6961663, 0.4079426, 0.8974794]
sellmeier_c_um2 = [0.0046791, 0.0135121, 97.934003]
)" + kOpticsToml + "[camera]\npixels = [32, 32]\npixel_pitch_um = 20\n";
  const Scene s = LoadScene(dir.Write("s.toml", scene));
  EXPECT_TRUE(s.is_spectral());
  EXPECT_DOUBLE_EQ(s.wavelength_um, 0.465);              // the spectrum's mean
  EXPECT_NEAR(s.objects[0].index, 1.4645, 2e-4);         // fused silica at 465 nm
  EXPECT_DOUBLE_EQ(s.source.spectrum.weights[1], 0.75);  // normalised
  auto error = [&](const std::string& from, const std::string& to) {
    std::string t = scene;
    t.replace(t.find(from), from.size(), to);
    try {
      LoadScene(dir.Write("bad.toml", t));
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_NE(error("weights = [1, 3]", "weights = [1]").find("'source.spectrum.weights'"),
            std::string::npos);
  EXPECT_NE(error("sellmeier_b", "index = 1.4\nsellmeier_b").find("'object[0].index'"),
            std::string::npos);
  EXPECT_NE(error("[0.0046791, 0.0135121, 97.934003]", "[0.0046791]").find("sellmeier_c_um2"),
            std::string::npos);
}

}  // namespace
}  // namespace raymatch::testing
