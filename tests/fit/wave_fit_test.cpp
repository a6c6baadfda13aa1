// Fits with the exact wave image model (optics = "mie") judged as an instrument: over
// independent noise realisations of a wave-optics experiment, the errors against the reported
// sigma and the Cramer-Rao bound.
#include <gtest/gtest.h>

#include <cmath>
#include <set>
#include <sstream>

#include "model.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "raymatch/fit/fit.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/wave_image.h"
#include "temp_dir.h"

namespace raymatch::fit {
namespace {

// A 4 um cell-like sphere (index 1.40 in water, relative index 1.05) under an 8 deg cone, 0.5 um
// object pixels, 1500 photons per pixel, one plane 3 um past its centre; coarse wave sampling
// (few illumination nodes, a small window) keeps an evaluation near 30 ms: the model is the same
// for experiment and fit. A low relative index keeps the sphere's morphology-dependent
// resonances weak: at relative index 1.4 (a drop in air) they put deviance spikes of thousands
// every 0.02-0.06 um of radius into a monochromatic image's likelihood (docs/wave-optics.md),
// and the curvature at the optimum no longer describes its scatter.
std::string WaveScene(double x, double y, double z, double r, double n) {
  std::ostringstream s;
  s << "name = \"w\"\nwavelength_um = 0.462\nmedium_index = 1.333\n[source]\ntype = "
       "\"cone\"\nhalf_angle_deg = 8\n"
    << "[[object]]\nname = \"s\"\ntype = \"sphere\"\ncenter_um = [" << x << ", " << y << ", " << z
    << "]\nradius_um = " << r << "\nindex = " << n << "\n"
    << "[objective]\nfocal_length_mm = 10\nna = 0.42\n[tube_lens]\nfocal_length_mm = 200\n"
    << "[camera]\npixels = [40, 40]\npixel_pitch_um = 10\n"
    << "[trace]\nphotons_per_pixel = 1500\noptics = \"mie\"\n"
    << "[trace.mie]\nnodes_per_panel = 4\npanel_width = 0.05\nmargin_um = 6\n";
  return s.str();
}

const char* kParameters =
    "[[parameter]]\nkey = \"object.s.center_um[0]\"\nlower = -1\nupper = 1\nstep = 0.1\n"
    "[[parameter]]\nkey = \"object.s.center_um[1]\"\nlower = -1\nupper = 1\nstep = 0.1\n"
    "[[parameter]]\nkey = \"object.s.center_um[2]\"\nlower = -2\nupper = 2\nstep = 0.2\n"
    "[[parameter]]\nkey = \"object.s.radius_um\"\nlower = 3.5\nupper = 4.5\nstep = 0.05\n"
    "[[parameter]]\nkey = \"object.s.index\"\nlower = 1.37\nupper = 1.43\nstep = 0.002\n"
    "[uncertainty]\nslice_points = 0\n";

// Six realisations; errors pooled over the five parameters (30 values). For an unbiased
// estimator with honest sigmas, sum (error / sigma)^2 is chi-square with 30 degrees of freedom:
// RMS(error / sigma) lies in [0.70, 1.32] with 99 % probability; sigma within 15 % of the
// Cramer-Rao bound (a model without noise of its own reaches it); each parameter's mean error
// within 3 of its standard error. Sigmas 3x too large, or an error of a few sigmas, fail.
TEST(WaveFit, ErrorsMatchSigmaAndTheBoundOverRealisations) {
  testing::TempDir dir;
  const double truth[5] = {0.15, -0.1, 0.3, 4.0, 1.40};
  const std::string truth_scene = dir.Write("truth.toml", WaveScene(0.15, -0.1, 0.3, 4.0, 1.40));
  const simulate::Scene ts = simulate::LoadScene(truth_scene);
  const Image expected = simulate::MieImager(ts).Expected(3.0, 2);
  dir.Write("start.toml", WaveScene(0.0, 0.0, 0.0, 4.03, 1.399));
  double pooled = 0;
  int values = 0;
  std::vector<double> sum(5, 0), sigma_sum(5, 0);
  const int kRealisations = 6;
  for (int k = 0; k < kRealisations; ++k) {
    const std::string tif = dir / ("exp" + std::to_string(k) + ".tif");
    WriteFloatImage(tif, simulate::PoissonSample(expected, 1000 + k, 0), "wave experiment");
    std::ostringstream f;
    f << "scene = \"start.toml\"\n[[image]]\nfile = \"" << tif << "\"\ndefocus_um = 3\n"
      << kParameters;
    const FitSpec spec = LoadFitSpec(dir.Write("fit" + std::to_string(k) + ".toml", f.str()));
    ASSERT_TRUE(spec.exact_images());
    FitOptions o;
    o.threads = 2;
    const FitResult r = RunFit(spec, o);
    ASSERT_EQ(r.parameters.size(), 5u);
    // An exact model's image is a function of the parameters alone: none is computed twice
    // (the uncertainties' derivatives are the polish's last stencil, whatever their seed).
    std::set<std::vector<double>> points;
    for (const Evaluation& e : r.evaluations)
      EXPECT_TRUE(points.insert(e.theta).second) << "evaluation of stage " << StageName(e.stage);
    for (size_t i = 0; i < 5; ++i) {
      const ParameterResult& p = r.parameters[i];
      SCOPED_TRACE(p.key + " realisation " + std::to_string(k));
      ASSERT_GT(p.sigma, 0);
      EXPECT_NEAR(p.sigma / p.sigma_cramer_rao, 1.0, 0.15);
      const double e = p.best - truth[i];
      pooled += (e / p.sigma) * (e / p.sigma);
      ++values;
      sum[i] += e;
      sigma_sum[i] += p.sigma;
    }
  }
  const double rms = std::sqrt(pooled / values);
  EXPECT_GT(rms, 0.70);
  EXPECT_LT(rms, 1.32);
  for (size_t i = 0; i < 5; ++i) {
    const double mean = sum[i] / kRealisations, se = sigma_sum[i] / kRealisations / std::sqrt(6.0);
    EXPECT_LT(std::abs(mean), 3 * se) << "parameter " << i;
  }
}

// An evaluation that only moves the sphere across the axis reuses the last wave imager's fields
// (MieImageModel): its images are those a new model computes, bit for bit, and a change of z
// after it computes new fields.
TEST(WaveFit, LateralMovesReuseTheFieldsAndGiveTheSameImages) {
  testing::TempDir dir;
  dir.Write("s.toml", WaveScene(0, 0, 0, 4, 1.4));
  Image flat(40, 40);
  for (size_t q = 0; q < flat.size(); ++q) flat.pixels[q] = float(1450 + q % 97);
  WriteFloatImage(dir / "e.tif", flat, "flat");
  const FitSpec spec = LoadFitSpec(dir.Write("f.toml",
                                             "scene = \"s.toml\"\n[[image]]\nfile = \"e.tif\"\n"
                                             "defocus_um = 3\n" +
                                                 std::string(kParameters)));
  ASSERT_TRUE(spec.exact_images());
  const std::vector<std::vector<double>> thetas = {{0.1, -0.1, 0.2, 4.0, 1.4},
                                                   {0.5, 0.3, 0.2, 4.0, 1.4},   // across
                                                   {-0.4, 0.3, 0.2, 4.0, 1.4},  // across
                                                   {-0.4, 0.3, 0.6, 4.0, 1.4},  // z
                                                   {0.2, 0.0, 0.6, 4.0, 1.4}};  // across
  FitModel reuse(spec, 2, nullptr);
  for (size_t k = 0; k < thetas.size(); ++k) {
    SCOPED_TRACE("evaluation " + std::to_string(k));
    const Simulated a = reuse.Expected(thetas[k], 1, 1, nullptr);
    const Simulated b = FitModel(spec, 2, nullptr).Expected(thetas[k], 1, 1, nullptr);
    ASSERT_EQ(a.photons.size(), 1u);
    EXPECT_EQ(a.photons[0].pixels, b.photons[0].pixels);
  }
}

// A start two fringe orders off (index 0.10 above the truth, radius 0.3 um): the wave fit alone
// stops in another fringe order's valley (deviance about 60 times its expectation). Each [search]
// stage alone gets it to the truth within its sigmas: scanning the radius and then the index at
// the wave model, each over its bounds with the others held; or a ray fit from the start (the
// ray model has no fringes to be caught in). The evaluations say which stage asked for them.
TEST(WaveFit, SearchStagesFindTheValleyFromAStartFringeOrdersOff) {
  testing::TempDir dir;
  const double truth[5] = {0.15, -0.1, 0.3, 4.0, 1.40};
  const std::string truth_scene = dir.Write("truth.toml", WaveScene(0.15, -0.1, 0.3, 4.0, 1.40));
  const Image expected = simulate::MieImager(simulate::LoadScene(truth_scene)).Expected(3.0, 2);
  WriteFloatImage(dir / "e.tif", simulate::PoissonSample(expected, 7, 0), "wave experiment");
  dir.Write("start.toml", WaveScene(0.0, 0.0, 0.0, 4.3, 1.50));
  std::string fit = "scene = \"start.toml\"\n[[image]]\nfile = \"e.tif\"\ndefocus_um = 3\n" +
                    std::string(kParameters);
  fit.replace(fit.find("lower = 1.37\nupper = 1.43"), 25, "lower = 1.28\nupper = 1.52");
  fit.replace(fit.find("step = 0.002"), 12, "step = 0.002\npoints = 25");
  FitOptions o;
  o.threads = 2;
  const FitResult plain = RunFit(LoadFitSpec(dir.Write("plain.toml", fit)), o);
  EXPECT_GT(std::abs(plain.parameters[4].best - truth[4]), 0.03);
  EXPECT_TRUE(plain.goodness.mismatch);

  const struct {
    const char* search;
    int starts, scans;
  } stages[] = {{"scan = [\"object.s.radius_um\", \"object.s.index\"]", 0, 21 + 25},
                {"start = \"rays\"", 20, 0}};
  for (const auto& st : stages) {
    SCOPED_TRACE(st.search);
    const FitSpec spec =
        LoadFitSpec(dir.Write("search.toml", fit + "[search]\n" + st.search + "\n"));
    EXPECT_EQ(spec.start_fit != nullptr, st.starts > 0);
    if (spec.start_fit) EXPECT_FALSE(spec.start_fit->exact_images());
    const FitResult r = RunFit(spec, o);
    EXPECT_FALSE(r.goodness.mismatch) << r.goodness.verdict;
    for (size_t i = 0; i < 5; ++i) {
      SCOPED_TRACE(r.parameters[i].key);
      EXPECT_LT(std::abs(r.parameters[i].best - truth[i]), 4 * r.parameters[i].sigma);
      EXPECT_EQ(r.parameters[i].start, spec.parameters[i].start);
    }
    int starts = 0, scans = 0;
    for (const Evaluation& e : r.evaluations) {
      starts += e.stage == Stage::kStart;
      scans += e.stage == Stage::kScan;
    }
    if (st.starts > 0)
      EXPECT_GT(starts, st.starts);
    else
      EXPECT_EQ(starts, 0);
    EXPECT_EQ(scans, st.scans);
    EXPECT_EQ(r.evaluations.front().stage, st.starts > 0 ? Stage::kStart : Stage::kScan);
  }
  // Hops: the plain fit, then the fit again from its optimum one fringe order of the index
  // (lambda / diameter = 0.058) down and up; the lower error wins and the hops go on that way.
  {
    const FitResult r =
        RunFit(LoadFitSpec(dir.Write(
                   "hop.toml", fit + "[search]\nhop = \"object.s.index\"\nhop_step = 0.058\n")),
               o);
    EXPECT_FALSE(r.goodness.mismatch) << r.goodness.verdict;
    for (size_t i = 0; i < 5; ++i)
      EXPECT_LT(std::abs(r.parameters[i].best - truth[i]), 4 * r.parameters[i].sigma)
          << r.parameters[i].key;
    EXPECT_LT(r.best_error, plain.best_error);
    int hops = 0;
    for (const Evaluation& e : r.evaluations) hops += e.stage == Stage::kHop;
    EXPECT_GT(hops, 0);
    // The losing fits' time is itemised with the hops, the winner's in its own items: together
    // the fit's whole time.
    double hop_s = 0, items = 0;
    for (const auto& [name, t] : r.seconds) {
      if (name.starts_with("hops")) hop_s = t;
      items += t;
    }
    EXPECT_GT(hop_s, 0);
    EXPECT_LE(items, r.total_seconds * 1.001);
    EXPECT_GT(items, 0.99 * r.total_seconds);
    std::printf(
        "plain: index %.4f error %.1f; hops: index %.4f error %.1f, %d hop evaluations of %zu\n",
        plain.parameters[4].best, plain.best_error, r.parameters[4].best, r.best_error, hops,
        r.evaluations.size());
  }
  // A parameter with one point (its step wider than its range) is scanned at its start.
  std::string one = fit;
  one.replace(one.find("step = 0.05"), 11, "step = 2");
  const FitResult r = RunFit(
      LoadFitSpec(dir.Write("one.toml", one + "[search]\nscan = [\"object.s.radius_um\"]\n")), o);
  ASSERT_EQ(r.evaluations.front().stage, Stage::kScan);
  EXPECT_EQ(r.evaluations.front().theta[3], 4.3);
  EXPECT_TRUE(std::isfinite(r.evaluations.front().error));
  EXPECT_EQ(r.evaluations[1].stage, Stage::kLm);
}

TEST(WaveFit, FitFileChoosesTheOptics) {
  testing::TempDir dir;
  std::string rays_scene = WaveScene(0, 0, 0, 4, 1.4);
  rays_scene.replace(rays_scene.find("optics = \"mie\"\n"), 15, "");
  rays_scene = rays_scene.substr(0, rays_scene.find("[trace.mie]"));
  dir.Write("s.toml", rays_scene);
  Image flat(40, 40);
  for (size_t q = 0; q < flat.size(); ++q) flat.pixels[q] = float(1450 + q % 97);
  WriteFloatImage(dir / "e.tif", flat, "flat");
  const std::string base = "scene = \"s.toml\"\n[[image]]\nfile = \"e.tif\"\ndefocus_um = 3\n" +
                           std::string(kParameters);
  EXPECT_FALSE(LoadFitSpec(dir.Write("a.toml", base)).exact_images());
  const FitSpec mie = LoadFitSpec(dir.Write("b.toml", "optics = \"mie\"\n" + base));
  EXPECT_TRUE(mie.exact_images());
  EXPECT_EQ(mie.rays.fractions, std::vector<double>{1.0});
  EXPECT_EQ(mie.repeat_seeds, 0);
  // A scene the wave model cannot image: the error names the fit file's optics key.
  dir.Write("two.toml", rays_scene +
                            "[[object]]\nname = \"t\"\ntype = \"sphere\"\n"
                            "center_um = [9, 0, 0]\nradius_um = 2\nindex = 1.4\n");
  try {
    LoadFitSpec(dir.Write("c.toml", "optics = \"mie\"\n" + std::string("scene = \"two.toml\"\n") +
                                        base.substr(base.find("[[image]]"))));
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("concentric"), std::string::npos) << e.what();
  }
  // A physical-optics scene is a model without simulation noise; one it cannot image (a point
  // source) is refused with the reason, naming the scene.
  std::string phys_scene = rays_scene;
  phys_scene.replace(phys_scene.find("[trace]\n"), 8, "[trace]\noptics = \"physical\"\n");
  dir.Write("phys.toml", phys_scene);
  const FitSpec phys = LoadFitSpec(
      dir.Write("p.toml", "scene = \"phys.toml\"\n" + base.substr(base.find("[[image]]"))));
  EXPECT_TRUE(phys.exact_images());
  EXPECT_EQ(phys.optics, "physical");
  EXPECT_EQ(mie.optics, "mie");
  EXPECT_EQ(LoadFitSpec(dir.Write("o.toml", "optics = \"physical\"\n" + base)).optics, "physical");
  std::string point_scene = phys_scene;
  const std::string cone = "type = \"cone\"";
  point_scene.replace(point_scene.find(cone), cone.size(),
                      "type = \"point\"\nposition_um = [0, 0, -100]");
  dir.Write("point.toml", point_scene);
  try {
    LoadFitSpec(
        dir.Write("q.toml", "scene = \"point.toml\"\n" + base.substr(base.find("[[image]]"))));
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("plane-wave"), std::string::npos) << e.what();
  }
  // [search]: a ray start only before an exact model, scans of the fit's own parameters, no
  // stages for a grid; each error names the key.
  struct Bad {
    std::string fit, key, says;
  };
  const Bad bad[] = {
      {base + "[search]\nstart = \"rays\"\n", "search.start", "the rays already"},
      {"optics = \"mie\"\n" + base + "[search]\nscan = [\"object.s.radius\"]\n", "search.scan",
       "object.s.radius_um"},
      {"optics = \"mie\"\n" + base + "[search]\nscan = [\"object.s.index\", \"object.s.index\"]\n",
       "search.scan", "twice"},
      {"optics = \"mie\"\nmethod = \"grid\"\nmax_evaluations = 10000000\n" + base +
           "[search]\nstart = \"rays\"\n",
       "search.start", "every point"},
      {"optics = \"mie\"\n" + base + "[search]\nstart = \"ray\"\n", "search.start", "rays"},
      {"optics = \"mie\"\n" + base + "[search]\nhop = \"object.s.radius\"\nhop_step = 0.1\n",
       "search.hop", "not a [[parameter]]"},
      {"optics = \"mie\"\n" + base + "[search]\nhop = \"object.s.index\"\n", "search.hop_step",
       "hop_step > 0"},
      {"optics = \"mie\"\n" + base + "[search]\nhop = \"object.s.index\"\nhop_step = 0.5\n",
       "search.hop_step", "leaves the parameter's bounds"},
      {"optics = \"mie\"\n" + base + "[search]\nhop_step = 0.01\n", "search.hop_step", "needs hop"},
  };
  int i = 0;
  for (const Bad& b : bad) {
    try {
      LoadFitSpec(dir.Write("bad" + std::to_string(i++) + ".toml", b.fit));
      ADD_FAILURE() << "expected an error for " << b.fit;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(b.key), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find(b.says), std::string::npos) << e.what();
    }
  }
}

// A coated sphere (a cell's nucleus, r 2 um, n 1.40, in its cytoplasm, r 4 um, n 1.36, in water):
// the nucleus's radius and index from one image 3 um past its centre, within 4 sigma, with sigma
// at the Cramer-Rao bound (an exact model); a key that moves one of the two spheres is refused
// where the fit file names it.
TEST(WaveFit, CoatedSphereCoreFromOneImage) {
  testing::TempDir dir;
  auto scene = [](double r, double n) {
    return WaveScene(0, 0, 0, 4.0, 1.36) +
           "[[object]]\nname = \"nucleus\"\ntype = \"sphere\"\ncenter_um = [0, 0, 0]\n"
           "radius_um = " +
           std::to_string(r) + "\nindex = " + std::to_string(n) + "\n";
  };
  // The [[object]] table follows [trace.mie] in the text: move it before [objective].
  auto ordered = [](std::string text) {
    const size_t at = text.find("[[object]]\nname = \"nucleus\"");
    const std::string nucleus = text.substr(at);
    text.erase(at);
    return text.insert(text.find("[objective]"), nucleus);
  };
  const simulate::Scene truth =
      simulate::LoadScene(dir.Write("truth.toml", ordered(scene(2.0, 1.40))));
  ASSERT_EQ(truth.objects.size(), 2u);
  WriteFloatImage(dir / "e.tif",
                  simulate::PoissonSample(simulate::MieImager(truth).Expected(3.0, 2), 77, 0),
                  "coated wave experiment");
  dir.Write("start.toml", ordered(scene(2.06, 1.395)));
  const std::string base =
      "scene = \"start.toml\"\n[[image]]\nfile = \"e.tif\"\ndefocus_um = 3\n"
      "[uncertainty]\nslice_points = 0\n"
      "[[parameter]]\nkey = \"object.nucleus.radius_um\"\nlower = 1.5\nupper = 2.5\n"
      "step = 0.05\n[[parameter]]\nkey = \"object.nucleus.index\"\nlower = 1.37\n"
      "upper = 1.43\nstep = 0.002\n";
  FitOptions o;
  o.threads = 2;
  const FitResult r = RunFit(LoadFitSpec(dir.Write("fit.toml", base)), o);
  const double want[2] = {2.0, 1.40};
  for (size_t i = 0; i < 2; ++i) {
    const ParameterResult& p = r.parameters.at(i);
    SCOPED_TRACE(p.key);
    ASSERT_GT(p.sigma, 0);
    EXPECT_NEAR(p.sigma / p.sigma_cramer_rao, 1.0, 0.15);
    EXPECT_LT(std::abs(p.best - want[i]), 4 * p.sigma) << p.best << " +- " << p.sigma;
  }
  try {
    LoadFitSpec(dir.Write("moves.toml", base + "[[parameter]]\nkey = \"object.s.center_um[0]\"\n"
                                               "lower = -1\nupper = 1\nstep = 0.1\n"));
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("object.s.center_um[0]"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("coated sphere"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace raymatch::fit
