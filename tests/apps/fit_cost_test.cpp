// raymatch bench fit (pipeline/src/fit_cost.cpp): each realisation's fit is the fit a user runs
// on that experiment, the realisations are independent, and bad input is refused before any fit.
#include "raymatch/pipeline/fit_cost.h"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "temp_dir.h"

namespace raymatch::pipeline {
namespace {

// A 9 um drop (n 1.36) 6 um before focus under a 27 deg cone, 1 um pixels at the object.
std::string Drop(double r, int seed, int nx = 32, double photons_per_pixel = 400) {
  std::ostringstream s;
  s << "name = \"drop\"\nseed = " << seed << "\n[source]\ntype = \"cone\"\nhalf_angle_deg = 27\n"
    << "[[object]]\nname = \"drop\"\ntype = \"sphere\"\ncenter_um = [0.3, -0.2, 0]\n"
    << "radius_um = " << r << "\nindex = 1.36\n"
    << "[objective]\nfocal_length_mm = 10\nna = 0.42\nworking_distance_mm = 20\n"
    << "[tube_lens]\nfocal_length_mm = 200\n[camera]\npixels = [" << nx
    << ", 28]\npixel_pitch_um = 20\n[trace]\nphotons_per_pixel = " << photons_per_pixel << "\n";
  return s.str();
}

struct Case {
  testing::TempDir dir;
  FitCostOptions o;
  explicit Case(int truth_nx = 32, double truth_photons = 400) {
    dir.Write("truth.toml", Drop(9.0, 1, truth_nx, truth_photons));
    dir.Write("model.toml", Drop(8.8, 1));
    // A placeholder experiment of the right size: the study replaces its pixels.
    const simulate::Simulator sim(simulate::LoadScene(dir.Write("p.toml", Drop(9.0, 7))));
    WriteFloatImage(dir / "exp.tif", sim.TracePlane(-6, 0, sim.RaysPerImage()).counts, "exp");
    o.fit_file = dir.Write(
        "fit.toml",
        "scene = \"model.toml\"\nseed = 40\n[[image]]\nfile = \"exp.tif\"\ndefocus_um = -6\n"
        "[[parameter]]\nkey = \"object.drop.radius_um\"\nlower = 8\nupper = 10\nstep = 0.1\n"
        "[rays]\nray_factor = 1\n[uncertainty]\nrepeat_seeds = 0\nslice_points = 0\n");
    o.truth_scene = dir / "truth.toml";
    o.realisations = 2;
    o.seed_base = 100;
    o.ray_factors = {2};
    o.progress = false;
    o.output_dir = dir / "out";
  }
};

// Realisation k at a setting is RunFit on the truth traced with seed SEED_BASE + k and the fit
// file's seed + k, at that setting: the same estimate to the last bit.
TEST(FitCost, EachRealisationIsTheFitAUserRunsOnThatExperiment) {
  Case c;
  const FitCostResult r = RunFitCostStudy(c.o);
  ASSERT_EQ(r.settings.size(), 2u);
  EXPECT_EQ(r.settings[0].knob, "as written");
  EXPECT_EQ(r.settings[1].knob, "ray_factor");
  ASSERT_EQ(r.fits.size(), 4u);
  ASSERT_EQ(r.truth.size(), 1u);
  EXPECT_EQ(r.truth[0], 9.0);
  for (const FitCostFit& f : r.fits) {
    SCOPED_TRACE("setting " + std::to_string(f.setting) + ", realisation " +
                 std::to_string(f.realisation));
    simulate::Scene truth = simulate::LoadScene(c.o.truth_scene);
    truth.trace.seed = c.o.seed_base + uint64_t(f.realisation);
    const simulate::Simulator sim(truth);
    fit::FitSpec spec = fit::LoadFitSpec(c.o.fit_file);
    spec.images[0].photons = sim.TracePlane(-6, 0, sim.RaysPerImage()).counts;
    spec.seed += uint64_t(f.realisation);
    if (f.setting == 1) spec.rays.ray_factor = 2;
    const fit::FitResult direct = fit::RunFit(spec);
    EXPECT_EQ(f.best[0], direct.parameters[0].best);
    EXPECT_EQ(f.sigma[0], direct.parameters[0].sigma);
    EXPECT_TRUE(f.converged);
  }
  // Independent realisations: other experiments, other estimates.
  EXPECT_NE(r.fits[0].best[0], r.fits[2].best[0]);
  // The summary is the fits' own: the RMS error over the two in the mean bound.
  const double e0 = r.fits[0].best[0] - 9, e1 = r.fits[2].best[0] - 9;
  EXPECT_NEAR(r.settings[0].rms_error_over_crb[0],
              std::sqrt((e0 * e0 + e1 * e1) / 2) / r.cramer_rao[0], 1e-12);
  std::ifstream js(c.dir / "out/fit_cost.json");
  const nlohmann::json j = nlohmann::json::parse(js);
  EXPECT_EQ(j["settings"].size(), 2u);
  EXPECT_EQ(j["settings"][1]["knob"], "ray_factor");
  EXPECT_TRUE(std::filesystem::exists(c.dir / "out/fit_cost.csv"));
  EXPECT_TRUE(std::filesystem::exists(c.dir / "out/fits.csv"));
  EXPECT_TRUE(std::filesystem::exists(c.dir / "out/fit_cost.png"));
}

// Bad input is refused, naming what is wrong, before any fit runs or any file is written.
TEST(FitCost, BadInputIsRefusedBeforeAnyFit) {
  const auto Refused = [](FitCostOptions o, const std::string& what) {
    try {
      RunFitCostStudy(o);
      ADD_FAILURE() << "not refused: " << what;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
    }
    EXPECT_FALSE(std::filesystem::exists(o.output_dir)) << what;
  };
  Case wide(40);  // the truth's camera 40 x 28, the fit's images 32 x 28
  Refused(wide.o, "32 x 28 pixels, but the truth scene");
  Case dim(32, 40);  // the truth's flat field 40 photons per pixel, the fit's images 400
  Refused(dim.o, "set [trace] photons_per_pixel in the truth scene");
  Case c;
  FitCostOptions o = c.o;
  o.realisations = 1;
  Refused(o, "expected 2 or more");
  o = c.o;
  o.jacobian_seeds = {1};
  Refused(o, "jacobian_seeds 1: expected 2 to 64");
  o = c.o;
  o.ray_factors = {2000};  // beyond what the fit file's ray_factor takes
  Refused(o, "expected a ray factor in [1/1024, 1024]");
  o = c.o;
  o.last_fractions = {1.5};
  Refused(o, "expected a fraction in (0, 1]");
}

}  // namespace
}  // namespace raymatch::pipeline
