// raymatch sensitivity (issue 23): the Fisher information of scene keys against closed forms, its
// agreement with the bounds a fit reports at the same point, and the design's choice of planes.
#include "raymatch/fit/sensitivity.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <sstream>

#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "temp_dir.h"

namespace raymatch::fit {
namespace {

// A drop under a 27 deg cone imaged with 1 um pixels at the object (as fit_test.cpp's).
std::string SceneText(double x, double r, double n, double ppp, bool with_drop = true) {
  std::ostringstream s;
  s << "name = \"drop\"\nseed = 1\n[source]\ntype = \"cone\"\nhalf_angle_deg = 27\n";
  if (with_drop)
    s << "[[object]]\nname = \"drop\"\ntype = \"sphere\"\ncenter_um = [" << x
      << ", 0, 0]\nradius_um = " << r << "\nindex = " << n << "\n";
  s << "[objective]\nfocal_length_mm = 10\nna = 0.42\nworking_distance_mm = 20\n"
    << "[tube_lens]\nfocal_length_mm = 200\n[camera]\npixels = [64, 56]\npixel_pitch_um = 20\n";
  if (ppp > 0) s << "[trace]\nphotons_per_pixel = " << ppp << "\n";
  return s.str();
}

SensitivitySpec Spec(const std::string& path, std::vector<std::string> keys) {
  SensitivitySpec s;
  s.scene_file = path;
  s.scene = ParseTomlFile(path);
  s.keys = std::move(keys);
  s.defocus_um = {-10};
  s.threads = 2;
  return s;
}

// A linear-in-parameter image and a Poisson amplitude, in closed form: an additive background b
// (image[0].background_photons) changes every pixel by exactly 1 per photon, so its information
// is sum 1 / mu and its bound 1 / sqrt(sum 1 / mu); for a flat field of P photons per pixel over
// N pixels that is sqrt(P / N). The exposure's relative bound is 1 / sqrt(sum mu) (a Poisson
// amplitude): 1 / sqrt(P N). The background cannot be told from an unknown exposure in a flat
// field: the information is singular then, and the error says so.
TEST(Sensitivity, BackgroundAndExposureBoundsMatchTheClosedForms) {
  testing::TempDir dir;
  const double ppp = 400;
  SensitivitySpec s =
      Spec(dir.Write("flat.toml", SceneText(0, 0, 0, ppp, false)), {"image[0].background_photons"});
  s.exposure_nuisance = false;
  const SensitivityResult r = RunSensitivity(s);
  double inv = 0, sum = 0;
  for (float v : r.mu[0].pixels) inv += 1 / double(v), sum += v;
  ASSERT_EQ(r.keys.size(), 1u);
  EXPECT_NEAR(r.keys[0].crb, 1 / std::sqrt(inv), 1e-6 * r.keys[0].crb);  // the derivative is exact
  const double N = 64 * 56;
  // The mean image is a Monte Carlo sample (4 sets of 4 rays per photon): sum 1 / mu exceeds
  // N / P by the relative variance 1 / (16 P) and the photon target's pilot is good to 0.4 %.
  EXPECT_NEAR(r.keys[0].crb, std::sqrt(ppp / N), 0.01 * std::sqrt(ppp / N));
  EXPECT_NEAR(r.exposure_relative_crb, 1 / std::sqrt(sum), 0.01 / std::sqrt(sum));
  EXPECT_NEAR(r.exposure_relative_crb, 1 / std::sqrt(ppp * N), 0.01 / std::sqrt(ppp * N));
  EXPECT_EQ(r.keys[0].crb_mc_error, 0);  // exact derivatives: no Monte Carlo error
  s.exposure_nuisance = true;
  try {
    RunSensitivity(s);
    FAIL() << "a background under an unknown exposure in a flat field has no information";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("not positive definite"), std::string::npos) << e.what();
  }
}

// Two correlated parameters in closed form: an image's background level b and slope g_x are
// linear in the expected image, mu' = mu + b + g_x (x - x_c), with derivative images 1 and
// (x - x_c) (exact: the same rays at every value). For a Poisson image the information is
// I = sum_q d_q d_q^T / mu_q, and with the exposure a nuisance (derivative image mu, at b = 0)
// the keys' block of the inverse of the 3 x 3 information. A drop off the image's centre makes
// 1 / mu asymmetric in x, so the two keys are correlated; on a flat field they are not. Every
// bound, the correlation and the Fisher matrix of the keys (the Schur complement) must be these
// to rounding with the exposure known: what is checked is the assembly of the information from
// derivative images and its inversion, with two keys that interact. With the exposure profiled
// out, its information is the cross product of the mean images of the even and the odd sets
// (unbiased by their noise), not sum mu: that differs by the sets' relative variance (4 sets of
// 4 rays per photon at 300 photons: about 2e-4), which the near-degeneracy of level and
// exposure amplifies in the Schur complement; 1 % is allowed there.
TEST(Sensitivity, TwoCorrelatedLinearKeysMatchTheirClosedForm) {
  testing::TempDir dir;
  const std::string scene = dir.Write("drop.toml", SceneText(18, 14, 1.335, 300));
  for (const bool nuisance : {false, true}) {
    SensitivitySpec s = Spec(scene, {"image[0].background_photons", "image[0].background_slope_x"});
    s.exposure_nuisance = nuisance;
    const SensitivityResult r = RunSensitivity(s);
    ASSERT_EQ(r.mu.size(), 1u);
    const Image& mu = r.mu[0];
    // The information of (b, g_x, log exposure), in closed form from mu.
    double I[3][3] = {};
    for (int y = 0; y < mu.height; ++y)
      for (int x = 0; x < mu.width; ++x) {
        const double m = mu.at(x, y);
        const double d[3] = {1, x - 0.5 * (mu.width - 1), m};
        for (int i = 0; i < 3; ++i)
          for (int j = 0; j < 3; ++j) I[i][j] += d[i] * d[j] / m;
      }
    // The keys' information with the exposure profiled out: I_kk - I_ke I_ee^-1 I_ek.
    double F[2][2];
    for (int i = 0; i < 2; ++i)
      for (int j = 0; j < 2; ++j) F[i][j] = I[i][j] - (nuisance ? I[i][2] * I[2][j] / I[2][2] : 0);
    const double det = F[0][0] * F[1][1] - F[0][1] * F[1][0];
    const double var[2] = {F[1][1] / det, F[0][0] / det};
    const double corr = -F[0][1] / det / std::sqrt(var[0] * var[1]);
    SCOPED_TRACE(nuisance ? "exposure a nuisance" : "exposure known");
    const double tol = nuisance ? 1e-2 : 1e-6;
    for (int i = 0; i < 2; ++i) {
      EXPECT_NEAR(r.keys[i].crb, std::sqrt(var[i]), tol * std::sqrt(var[i])) << r.keys[i].key;
      EXPECT_NEAR(
          r.keys[i].crb_exposure_known,
          std::sqrt(i == 0 ? I[1][1] : I[0][0]) / std::sqrt(I[0][0] * I[1][1] - I[0][1] * I[0][1]),
          1e-6 * r.keys[i].crb_exposure_known);
      for (int j = 0; j < 2; ++j)
        EXPECT_NEAR(r.fisher[i][j], F[i][j], tol * std::sqrt(F[i][i] * F[j][j]));
    }
    // A correlation that matters, so the off-diagonal term is really tested.
    EXPECT_GT(std::abs(corr), 0.05);
    EXPECT_NEAR(r.correlation[0][1], corr, tol);
  }
}

// The bounds agree with those a fit reports at its optimum (the same photons, ray factor and
// steps; the exposure a nuisance in both), within the Monte Carlo errors of the two estimates.
TEST(Sensitivity, BoundsAgreeWithTheFitsCramerRaoBound) {
  testing::TempDir dir;
  const std::string exp_scene = dir.Write("exp.toml", SceneText(0.4, 23, 1.335, 400));
  {
    const simulate::Scene s = simulate::LoadScene(exp_scene);
    const simulate::Simulator sim(s);
    WriteFloatImage(dir / "exp.tif", sim.TracePlane(-10, 0, sim.RaysPerImage()).counts, "test");
  }
  const std::string model = dir.Write("model.toml", SceneText(0, 23, 1.335, 400));
  const std::string fit_file = dir.Write(
      "fit.toml",
      "scene = \"model.toml\"\nseed = 3\n[rays]\nray_factor = 4\n[uncertainty]\nrepeat_seeds = "
      "0\nslice_points = 0\n[[image]]\nfile = \"exp.tif\"\ndefocus_um = -10\n"
      "[[parameter]]\nkey = \"object.drop.center_um[0]\"\nlower = -2\nupper = 2\nstep = 0.2\n"
      "[[parameter]]\nkey = \"object.drop.radius_um\"\nlower = 21\nupper = 25\nstep = 0.2\n");
  const FitResult fr = RunFit(LoadFitSpec(fit_file));
  ASSERT_TRUE(fr.converged) << fr.message;
  toml::table at_best = ParseTomlFile(model);
  SetSceneValue(at_best, "object.drop.center_um[0]", fr.parameters[0].best, model);
  SetSceneValue(at_best, "object.drop.radius_um", fr.parameters[1].best, model);
  SensitivitySpec s = Spec(model, {"object.drop.center_um[0]", "object.drop.radius_um"});
  s.scene = at_best;
  s.steps = {0.2, 0.2};
  s.sets = 6;
  const SensitivityResult r = RunSensitivity(s);
  for (size_t i = 0; i < 2; ++i) {
    const double fit_crb = fr.parameters[i].sigma_cramer_rao;
    // The fit's bound comes from 2 derivative sets: its Monte Carlo error is taken as twice the
    // sensitivity's own (6 sets), in quadrature, and 3 of those combined errors are allowed.
    const double tol = 3 * std::sqrt(5.0) * r.keys[i].crb_mc_error;
    EXPECT_NEAR(r.keys[i].crb, fit_crb, tol) << r.keys[i].key;
    EXPECT_GT(r.keys[i].crb_mc_error, 0);
    EXPECT_LT(r.keys[i].crb_mc_error, 0.05 * r.keys[i].crb);
    // An unknown exposure can only lose information.
    EXPECT_LE(r.keys[i].crb_exposure_known, r.keys[i].crb * (1 + 1e-12));
  }
  ASSERT_EQ(r.dmu.size(), 1u);
  ASSERT_EQ(r.dmu[0].size(), 2u);
}

// The design's ranking in a case with a known answer: per-image information diag(100, 1),
// diag(1, 100) and diag(30, 30). One plane: the third (bounds 0.183 each, geometric mean 0.183,
// against 0.316 for the others); two planes sharing the photons: the first two
// (diag(101, 101) / 2: 0.141 each) beat the first with the third (0.124 and 0.254: 0.178).
TEST(Sensitivity, DesignRanksChoicesByTheirBounds) {
  const std::vector<std::vector<std::vector<double>>> per_image = {
      {{100, 0}, {0, 1}}, {{1, 0}, {0, 100}}, {{30, 0}, {0, 30}}};
  size_t compared = 0;
  std::vector<DesignChoice> one = RankDesigns(per_image, {-5, 5, 0}, 1, {0, 1}, &compared);
  EXPECT_EQ(compared, 3u);
  ASSERT_FALSE(one.empty());
  EXPECT_EQ(one[0].defocus_um, std::vector<double>{0});
  EXPECT_NEAR(one[0].objective, 1 / std::sqrt(30.0), 1e-12);
  std::vector<DesignChoice> two = RankDesigns(per_image, {-5, 5, 0}, 2, {0, 1}, &compared);
  EXPECT_EQ(compared, 3u);
  EXPECT_EQ(two[0].defocus_um, (std::vector<double>{-5, 5}));
  EXPECT_NEAR(two[0].crb[0], std::sqrt(2 / 101.0), 1e-12);
  // Only the first key: the first plane alone, and it again in the best pair.
  one = RankDesigns(per_image, {-5, 5, 0}, 1, {0}, &compared);
  EXPECT_EQ(one[0].defocus_um, std::vector<double>{-5});
}

// End to end, a case built to have a best plane: a drop's radius from candidate planes 10 um
// before it and 200 um before and after it, where the NA spreads every point over about 90 um,
// wider than the 64 um field: the design picks -10 um, and with two planes keeps it.
TEST(Sensitivity, DesignPicksThePlaneThatShowsTheDrop) {
  testing::TempDir dir;
  SensitivitySpec s = Spec(dir.Write("drop.toml", SceneText(0, 23, 1.335, 100)),
                           {"object.drop.radius_um", "object.drop.center_um[0]"});
  s.defocus_um = {-200, -10, 200};
  s.ray_factor = 1;
  s.design_planes = 2;
  s.design_keys = {"object.drop.radius_um"};
  const SensitivityResult r = RunSensitivity(s);
  ASSERT_EQ(r.design_best.size(), 2u);
  EXPECT_EQ(r.design_best[0].defocus_um, std::vector<double>{-10});
  const auto& pair = r.design_best[1].defocus_um;
  EXPECT_NE(std::find(pair.begin(), pair.end(), -10.0), pair.end());
  EXPECT_EQ(r.design_choices, 3u);
  // The chosen plane alone holds almost all the information.
  EXPECT_LT(r.keys[0].crb_per_image[1], 0.2 * r.keys[0].crb_per_image[0]);
}

TEST(Sensitivity, BadInputIsNamed) {
  testing::TempDir dir;
  const std::string path = dir.Write("drop.toml", SceneText(0, 9, 1.36, 100));
  auto error = [&](SensitivitySpec s) {
    try {
      RunSensitivity(s);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error(Spec(path, {"object.drop.colour"})).find("no 'colour' in object 'drop'"),
            std::string::npos);
  EXPECT_NE(error(Spec(path, {"image[3].defocus_um"})).find("with i < 1"), std::string::npos);
  SensitivitySpec odd = Spec(path, {"object.drop.radius_um"});
  odd.sets = 3;
  EXPECT_NE(error(odd).find("sets"), std::string::npos);
  SensitivitySpec dark =
      Spec(dir.Write("dark.toml", SceneText(0, 9, 1.36, 0)), {"object.drop.radius_um"});
  EXPECT_NE(error(dark).find("--photons-per-pixel"), std::string::npos);
}

}  // namespace
}  // namespace raymatch::fit
