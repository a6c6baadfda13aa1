// The illumination spectrum (issue 22): a ray near a dispersive object draws its wavelength, so an
// image under a spectrum is the power-weighted mean of monochromatic images. Tolerances: a
// chi-square over the pixels with the Poisson variances of both sides (as motion_test.cpp).
#include <gtest/gtest.h>

#include <cmath>

#include "raymatch/core/array_io.h"
#include "raymatch/simulate/index_field.h"
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

// A water density field under a spectrum: a ray sees the grid's index at its own wavelength
// (IAPWS R9-97 through WaterMapTable's affine map of the grid's index at wavelength_um). A water
// drop whose density falls from 1040 kg/m^3 at its centre to 998 at its surface (a gradient-index
// lens), under lines at 0.3 and 1.0 um (water's index about 1.355 and 1.328 at its surface), in a
// medium of index 1.34 between them (the drop converges one line and diverges the other): the
// image is the weighted sum of the two monochromatic images, whose grids are computed at each
// line.
TEST(Spectrum, WaterDensityFieldFollowsTheRaysWavelength) {
  TempDir dir;
  const std::string drop = testing::DensityDropObject(dir, 10, 9, 9, "center_um = [1, 0, 3]\n");
  auto scene = [&](const std::string& light, uint64_t seed) {
    return LoadScene(dir.Write(
        "s" + std::to_string(seed) + ".toml",
        "seed = " + std::to_string(seed) + "\n" + light + R"(
[source]
type = "collimated"
field_radius_um = 30
)" +
            (light.empty() ? "spectrum = { type = \"lines\", wavelengths_um = [0.3, 1.0], "
                             "weights = [0.5, 0.5] }\n"
                           : "") +
            drop + R"([camera]
pixels = [64, 64]
pixel_pitch_um = 20
[trace]
partial_reflection = "off"
)" + kOpticsToml));
  };
  const Scene s = scene("", 7);
  ASSERT_TRUE(s.is_spectral());
  EXPECT_NEAR(s.wavelength_um, 0.65, 1e-12);  // the grid is held at the spectrum's mean
  const PlaneResult r = Trace(s);
  EXPECT_GT(r.counters.wavelength_draws, kRays / 100);
  const Image blue = Trace(scene("wavelength_um = 0.3\n", 101)).counts;
  const Image red = Trace(scene("wavelength_um = 1.0\n", 102)).counts;
  const auto [chi2, n] = CentralChiSquare(r.counts, {blue, red}, {0.5, 0.5});
  EXPECT_LT(std::abs(chi2 - 1), 5 * std::sqrt(2 / n)) << "reduced chi-square " << chi2;
  // The test can tell: the grid at its own wavelength (the spectrum's mean) for every ray is not
  // the same image.
  const Image mean = Trace(scene("wavelength_um = 0.65\n", 103)).counts;
  const auto [chi2_mean, n2] = CentralChiSquare(r.counts, {mean}, {1.0});
  EXPECT_GT(chi2_mean, 1 + 10 * std::sqrt(2 / n2)) << chi2_mean;
}

// A grid's AffineView gives offset + scale x the grid's index and scale x its gradient, through
// single evaluations (rz and 3D grids) and through the 3D integrator's cells, sharing the grid.
TEST(Spectrum, AffineViewOfAGridMapsIndexAndGradient) {
  simulate::IndexField g3;
  g3.type = simulate::IndexFieldType::kGrid3D;
  g3.nx = 5, g3.ny = 4, g3.nz = 3;
  g3.spacing_um = {1, 1.5, 2}, g3.origin_um = {-2, -2, -2};
  for (int i = 0; i < 60; ++i) g3.values.push_back(1.33 + 0.001 * ((i * 7) % 11));
  simulate::IndexField rz = g3;
  rz.type = simulate::IndexFieldType::kGridRZ;
  rz.nx = 6, rz.ny = 1, rz.nz = 10, rz.origin_um = {0, 0, -4};
  for (const simulate::IndexField* f : {&g3, &rz}) {
    simulate::IndexField v = f->AffineView();
    v.SetMap(-0.02, 1.01);
    for (const Vec3 p : {Vec3(0.3, -0.7, 0.4), Vec3(1.9, 0.2, -1.1), Vec3(-1.5, 1.2, 1.7)}) {
      double n, m;
      Vec3 gn, gm;
      f->Eval(p, &n, &gn);
      v.Eval(p, &m, &gm);
      EXPECT_NEAR(m, -0.02 + 1.01 * n, 1e-14);
      EXPECT_NEAR(Length(gm - gn * 1.01), 0, 1e-14);
      if (f == &g3) {  // the integrator's path: the cell's polynomial
        simulate::IndexField::EvalInCell(v.Cell(p), p, &m, &gm);
        EXPECT_NEAR(m, -0.02 + 1.01 * n, 1e-14);
        EXPECT_NEAR(Length(gm - gn * 1.01), 0, 1e-14);
      }
    }
  }
}

// The affine map of a water field's index between wavelengths (WaterIndexMap): close to exact
// over the states of a strong pressure wave (900-1060 kg/m^3, 280-340 K) across 0.40-0.53 um
// from 0.462 um (below 1e-5, a tenth of the sample's index bound); exact for one state; the
// table's linear interpolation between nodes h apart errs by at most h^2 / 8 max|n''| (water:
// |n''| < 1 um^-2 above 0.3 um; 8e-8 measured near 0.4 um).
TEST(Spectrum, WaterIndexMapIsCloseToExact) {
  std::vector<double> rho, T;
  for (int i = 0; i < 400; ++i) {
    rho.push_back(900 + 160.0 * i / 399);
    T.push_back(280 + 60.0 * ((i * 37) % 400) / 399);  // scrambled against the density
  }
  double worst = 0;
  for (double l = 0.40; l <= 0.53; l += 0.005) {
    const simulate::AffineIndexMap m = simulate::WaterIndexMap(rho, T, 0.462, l);
    worst = std::max(worst, m.max_error);
    for (size_t i = 0; i < rho.size(); i += 57)  // max_error is the largest residual
      EXPECT_LE(
          std::abs(m.offset + m.scale * simulate::WaterRefractiveIndex(T[i], rho[i], 0.462).n -
                   simulate::WaterRefractiveIndex(T[i], rho[i], l).n),
          m.max_error + 1e-15);
  }
  EXPECT_LT(worst, 1e-5);
  EXPECT_GT(worst, 1e-8);  // the map is not trivially exact over such states
  const simulate::AffineIndexMap one = simulate::WaterIndexMap({1000}, {293.15}, 0.462, 0.7);
  EXPECT_NEAR(one.offset + one.scale * simulate::WaterRefractiveIndex(293.15, 1000, 0.462).n,
              simulate::WaterRefractiveIndex(293.15, 1000, 0.7).n, 1e-15);
  const simulate::WaterMapTable table(rho, T, 0.462, 0.40, 0.53);
  const double h = 0.13 / 128;
  for (double l : {0.4013, 0.4471, 0.5299}) {
    const simulate::AffineIndexMap a = table.At(l), b = simulate::WaterIndexMap(rho, T, 0.462, l);
    EXPECT_NEAR(a.offset + a.scale * 1.34, b.offset + b.scale * 1.34, h * h / 8 * 1.0) << l;
  }
}

}  // namespace
}  // namespace raymatch::testing
