// The five-parameter sphere fit at the sample's photon count per pixel (2500) over independent
// noise realisations (label "slow": a few minutes per fit on 2 cores). Checks, per parameter:
//  * every fit's value within 3 reported sigma of the truth;
//  * the reported sigma agrees with the scatter over realisations within a factor 1.5, and that
//    scatter is within 2x of the Cramer-Rao bound the fit reports (both pooled over parameters:
//    6 realisations alone would let a sample standard deviation scatter by ~30 %).
// The image has 2 um pixels at the object (48 x 40, a 96 x 80 um field around the 46 um drop):
// the photon count per pixel is the sample's, the pixel count a quarter of 1 um pixels', which
// keeps six fits affordable; the statistics do not depend on the pixel size. Ray factor 2: the
// fixed ray pattern's share of the variance (1/k) stays below the experiment's.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <sstream>

#include "raymatch/core/image_io.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "temp_dir.h"

namespace raymatch::fit {
namespace {

std::string Scene(double x, double y, double z, double r, double n, int seed) {
  std::ostringstream s;
  s << "name = \"drop\"\nseed = " << seed << "\n[source]\ntype = \"cone\"\nhalf_angle_deg = 27\n"
    << "[[object]]\nname = \"drop\"\ntype = \"sphere\"\ncenter_um = [" << x << ", " << y << ", " << z
    << "]\nradius_um = " << r << "\nindex = " << n << "\n[objective]\nfocal_length_mm = 10\nna = 0.42\n"
    << "working_distance_mm = 20\n[tube_lens]\nfocal_length_mm = 200\n[camera]\npixels = [48, 40]\n"
    << "pixel_pitch_um = 40\n[trace]\nphotons_per_pixel = 2500\n";
  return s.str();
}

TEST(FitStatistics, FiveParameterSphereAtTheSamplePhotonCount) {
  const double truth[5] = {1.3, -0.7, 0.8, 23, 1.33885};
  const int kRealisations = 6;
  std::vector<std::vector<double>> best(5), sigma(5), crb(5);
  for (int k = 0; k < kRealisations; ++k) {
    testing::TempDir dir;
    const std::string ts = dir.Write("truth.toml", Scene(1.3, -0.7, 0.8, 23, 1.33885, 100 + k));
    const simulate::Scene s = simulate::LoadScene(ts);
    const simulate::Simulator sim(s);
    WriteFloatImage(dir / "exp.tif", sim.TracePlane(-10, 0, sim.RaysPerImage()).counts, "experiment");
    dir.Write("model.toml", Scene(0, 0, 0, 22.5, 1.335, 1));
    const std::string fit = dir.Write(
        "fit.toml",
        "scene = \"model.toml\"\nseed = " + std::to_string(7 + k) +
            "\n[[image]]\nfile = \"exp.tif\"\ndefocus_um = -10\n"
            "[[parameter]]\nkey = \"object.drop.center_um[0]\"\nlower = -3\nupper = 3\nstep = 0.2\n"
            "[[parameter]]\nkey = \"object.drop.center_um[1]\"\nlower = -3\nupper = 3\nstep = 0.2\n"
            "[[parameter]]\nkey = \"object.drop.center_um[2]\"\nlower = -4\nupper = 4\nstep = 0.4\n"
            "[[parameter]]\nkey = \"object.drop.radius_um\"\nlower = 21\nupper = 25\nstep = 0.2\n"
            "[[parameter]]\nkey = \"object.drop.index\"\nlower = 1.32\nupper = 1.35\nstep = 0.002\n"
            "[rays]\nray_factor = 2\n[uncertainty]\nrepeat_seeds = 0\nslice_points = 0\n");
    const FitResult r = RunFit(LoadFitSpec(fit));
    ASSERT_TRUE(r.converged) << r.message;
    std::printf("realisation %d: %zu evaluations, %.0f s; (best - truth)/sigma:", k, r.evaluations.size(),
                r.total_seconds);
    for (int i = 0; i < 5; ++i) std::printf(" %+.2f", (r.parameters[i].best - truth[i]) / r.parameters[i].sigma);
    std::printf("\n");
    for (int i = 0; i < 5; ++i) {
      const ParameterResult& p = r.parameters[i];
      EXPECT_NEAR(p.best, truth[i], 3 * p.sigma) << p.key << " realisation " << k;
      best[i].push_back(p.best), sigma[i].push_back(p.sigma), crb[i].push_back(p.sigma_cramer_rao);
    }
  }
  // Pooled over parameters and realisations (30 values): the RMS of (best - truth)/sigma is 1
  // for an honest sigma (its sampling scatter is ~13 %), and the RMS of (best - truth)/CRB is
  // sqrt(1 + 1/k) = 1.22 at ray factor 2 for an efficient fit.
  double z_sigma = 0, z_crb = 0;
  for (int i = 0; i < 5; ++i)
    for (int k = 0; k < kRealisations; ++k) {
      z_sigma += std::pow((best[i][k] - truth[i]) / sigma[i][k], 2) / (5 * kRealisations);
      z_crb += std::pow((best[i][k] - truth[i]) / crb[i][k], 2) / (5 * kRealisations);
    }
  z_sigma = std::sqrt(z_sigma), z_crb = std::sqrt(z_crb);
  std::printf("pooled RMS of (best - truth)/sigma %.2f, of (best - truth)/CRB %.2f\n", z_sigma, z_crb);
  EXPECT_GT(z_sigma, 1 / 1.5);
  EXPECT_LT(z_sigma, 1.5);
  EXPECT_LT(z_crb, 2.0);
}

}  // namespace
}  // namespace raymatch::fit
