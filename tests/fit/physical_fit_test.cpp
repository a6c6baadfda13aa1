// Fits and sensitivity studies with the physical-optics image model (optics = "physical"):
// the fit engine takes it through the same image-model interface as the exact sphere model.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <sstream>

#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/core/toml_reader.h"
#include "raymatch/fit/fit.h"
#include "raymatch/fit/sensitivity.h"
#include "raymatch/simulate/physical_image.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/wave_image.h"
#include "temp_dir.h"

namespace raymatch::fit {
namespace {

// A 3 um sphere of 1.40 in water under a collimated axial wave (one plane wave: an evaluation
// near 0.1 s), 0.5 um object pixels, 1000 photons per pixel, one plane 3 um past its centre.
std::string PhysicalScene(double x, double y, double z, const char* optics = "physical") {
  std::ostringstream s;
  s << "name = \"p\"\nwavelength_um = 0.55\nmedium_index = 1.333\n[source]\ntype = "
       "\"collimated\"\n"
    << "[[object]]\nname = \"s\"\ntype = \"sphere\"\ncenter_um = [" << x << ", " << y << ", " << z
    << "]\nradius_um = 3\nindex = 1.40\n"
    << "[objective]\nfocal_length_mm = 10\nna = 0.42\n[tube_lens]\nfocal_length_mm = 200\n"
    << "[camera]\npixels = [40, 40]\npixel_pitch_um = 10\n"
    << "[trace]\nphotons_per_pixel = 1000\noptics = \"" << optics << "\"\n";
  return s.str();
}

const char* kPosition =
    "[[parameter]]\nkey = \"object.s.center_um[0]\"\nlower = -1\nupper = 1\nstep = 0.05\n"
    "[[parameter]]\nkey = \"object.s.center_um[1]\"\nlower = -1\nupper = 1\nstep = 0.05\n"
    "[[parameter]]\nkey = \"object.s.center_um[2]\"\nlower = -2\nupper = 2\nstep = 0.2\n"
    "[uncertainty]\nslice_points = 0\n";

// The sphere's position from images the physical model made, over four noise realisations,
// from a start 0.15 um across and 0.5 um along the axis away. The field rays' lattice and the
// FFT window are laid out from the objects' own bounds, so a move is a rigid shift of the
// sampling and the image is smooth in these parameters. Pooled over 12 values, sum (error /
// sigma)^2 is chi-square with 12 degrees of freedom: RMS(error / sigma) lies in [0.51, 1.54]
// with 99 % probability; each sigma within 15 % of the Cramer-Rao bound (no noise of the
// model's own). Sigmas 3x off, or a bias of a few sigmas, fail.
TEST(PhysicalFit, PositionFromItsOwnImagesOverRealisations) {
  testing::TempDir dir;
  const double truth[3] = {0.1, -0.05, 0.2};
  const std::string truth_scene = dir.Write("truth.toml", PhysicalScene(0.1, -0.05, 0.2));
  const Image expected =
      simulate::PhysicalImager(simulate::LoadScene(truth_scene)).Expected(3.0, 2);
  dir.Write("start.toml", PhysicalScene(-0.05, 0.1, -0.3));
  double pooled = 0;
  int values = 0;
  for (int k = 0; k < 4; ++k) {
    const std::string tif = dir / ("exp" + std::to_string(k) + ".tif");
    WriteFloatImage(tif, simulate::PoissonSample(expected, 300 + k, 0), "physical experiment");
    std::ostringstream f;
    f << "scene = \"start.toml\"\n[[image]]\nfile = \"" << tif << "\"\ndefocus_um = 3\n"
      << kPosition;
    const FitSpec spec = LoadFitSpec(dir.Write("fit" + std::to_string(k) + ".toml", f.str()));
    ASSERT_TRUE(spec.exact_images());
    ASSERT_EQ(spec.optics, "physical");
    FitOptions o;
    o.threads = 2;
    const FitResult r = RunFit(spec, o);
    ASSERT_EQ(r.parameters.size(), 3u);
    for (size_t i = 0; i < 3; ++i) {
      const ParameterResult& p = r.parameters[i];
      SCOPED_TRACE(p.key + " realisation " + std::to_string(k));
      ASSERT_GT(p.sigma, 0);
      EXPECT_NEAR(p.sigma / p.sigma_cramer_rao, 1.0, 0.15);
      const double e = (p.best - truth[i]) / p.sigma;
      pooled += e * e;
      ++values;
    }
    std::printf("realisation %d: %s\n", k, r.goodness.verdict.c_str());
  }
  const double rms = std::sqrt(pooled / values);
  std::printf("RMS(error / sigma) over %d values: %.2f\n", values, rms);
  EXPECT_GT(rms, 0.51);
  EXPECT_LT(rms, 1.54);
}

// A sensitivity study takes the physical model: its bounds on the sphere's position come within
// 10 % of the exact model's at the same scene (the physical image is 0.3 chi-square per pixel
// off the exact one here; its derivative images a few per cent), and an image model without
// noise gives the bound no Monte Carlo error.
TEST(PhysicalFit, SensitivityBoundsComeCloseToTheExactModels) {
  testing::TempDir dir;
  double crb[2][2];
  for (int m = 0; m < 2; ++m) {
    const std::string path = dir.Write(m ? "mie.toml" : "phys.toml",
                                       PhysicalScene(0.1, -0.05, 0.2, m ? "mie" : "physical"));
    SensitivitySpec s;
    s.scene_file = path;
    s.scene = ParseTomlFile(path);
    s.keys = {"object.s.center_um[0]", "object.s.center_um[2]"};
    s.defocus_um = {3};
    s.threads = 2;
    const SensitivityResult r = RunSensitivity(s, false);
    ASSERT_EQ(r.keys.size(), 2u);
    for (int k = 0; k < 2; ++k) {
      crb[m][k] = r.keys[size_t(k)].crb;
      EXPECT_GT(crb[m][k], 0);
      EXPECT_EQ(r.keys[size_t(k)].crb_mc_error, 0);
    }
  }
  std::printf("bounds: x %.5f (exact %.5f) um, z %.5f (exact %.5f) um\n", crb[0][0], crb[1][0],
              crb[0][1], crb[1][1]);
  EXPECT_NEAR(crb[0][0] / crb[1][0], 1.0, 0.10);
  EXPECT_NEAR(crb[0][1] / crb[1][1], 1.0, 0.10);
}

}  // namespace
}  // namespace raymatch::fit
