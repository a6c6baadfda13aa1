// `raymatch calibrate sphere` end to end on the sample: the light field and corrector calibrated
// from the sample's own images, then the drop's focus scan fitted for the drop and the
// nuisances. Known answers: the generator's truth.toml. Label slow (12-16 minutes on 2 cores). On
// the reduced sample (1/16 of the photons, as the golden pipeline test uses) the nine-parameter
// information is not positive definite at the default rays and the sigmas are wide, so the full
// exposure it is.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>

#include "raymatch/core/calibration_file.h"
#include "raymatch/core/html.h"  // ReadFileBytes
#include "raymatch/core/toml_reader.h"
#include "temp_dir.h"

namespace fs = std::filesystem;

namespace raymatch {
namespace {

int Raymatch(const std::string& args, const std::string& log) {
  return std::system((std::string(RAYMATCH_BIN) + " " + args + " >>" + log + " 2>&1").c_str());
}

// `calibrate lightfield` on the sample's pinhole and cone images, into `out`.
void CalibrateSampleLightField(const std::string& out, const std::string& log) {
  ASSERT_EQ(Raymatch("calibrate lightfield " + std::string(RAYMATCH_SOURCE_DIR) +
                         "/datasets-sample/lightfield -o " + out,
                     log),
            0)
      << ReadFileBytes(log);
}

// A fitted nuisance's value as the calibration file carries it (12 significant digits: equal to
// 1e-9); the drop's keys are not written.
void ExpectWrittenIntoTheCalibration(const CalibrationData& cal, const std::string& key,
                                     double best) {
  if (key == "camera.psf_sigma_um") EXPECT_NEAR(cal.psf_sigma_um, best, 1e-9);
  if (key == "light_field_edge.half_angle_deg") EXPECT_NEAR(cal.edge_half_angle_deg, best, 1e-9);
  if (key == "light_field_edge.width_deg") EXPECT_NEAR(cal.edge_width_deg, best, 1e-9);
  if (key == "light_field_edge.tilt_deg[0]") EXPECT_NEAR(cal.edge_tilt_deg[0], best, 1e-9);
  if (key == "light_field_edge.tilt_deg[1]") EXPECT_NEAR(cal.edge_tilt_deg[1], best, 1e-9);
}

// The sample generated at full exposure with a drop 2.6 % larger than the nominal diameter its
// metadata gives (46 um) and a PSF of 0.3 um, not the 0.21 lambda/NA = 0.231 um the calibration
// starts from: both start away from the truth, as with a real drop. The drop's five parameters,
// the PSF and the edge's tilt come out within 3 reported sigma of the truth (the sigmas include
// the fit's model-mismatch inflation, if any), every nuisance is written into the calibration
// file with the fit's values, and the calibration's provenance names the fit. The edge's
// half-angle is not checked: the width is held at 1 deg (the truth's is 1.2), and the half-angle
// absorbs the difference (docs/calibration.md).
TEST(SphereCalibration, SampleRecoversTheDropAndThePsfFromStartsAwayFromTheTruth) {
  testing::TempDir dir;
  const std::string data = dir / "sample", log = dir / "log.txt";
  ASSERT_EQ(std::system((std::string(RAYMATCH_GENERATOR) + " " + data +
                         " --drop-radius-um 23.6 --psf-sigma-um 0.3 >>" + log + " 2>&1")
                            .c_str()),
            0)
      << ReadFileBytes(log);
  ASSERT_EQ(Raymatch("calibrate lightfield " + data + "/lightfield -o " + (dir / "lf.toml"), log),
            0)
      << ReadFileBytes(log);
  ASSERT_EQ(Raymatch("calibrate corrector " + data + "/flatfield --base " + (dir / "lf.toml") +
                         " -o " + (dir / "cal.toml"),
                     log),
            0)
      << ReadFileBytes(log);
  ASSERT_EQ(Raymatch("calibrate sphere " + data + "/drop46 --base " + (dir / "cal.toml") + " -o " +
                         (dir / "sphere.toml"),
                     log),
            0)
      << ReadFileBytes(log);
  const toml::table truth = ParseTomlFile(data + "/truth.toml");
  double want_tilt[2] = {0, 0};
  auto t = [&](const char* table, const char* key) {
    return truth[table][key].value<double>().value();
  };
  const auto* c = truth["drop"]["center_um"].as_array();
  const std::map<std::string, double> want{
      {"object.drop.center_um[0]", c->get(0)->value<double>().value()},
      {"object.drop.center_um[1]", c->get(1)->value<double>().value()},
      {"object.drop.center_um[2]", c->get(2)->value<double>().value()},
      {"object.drop.radius_um", t("drop", "radius_um")},
      {"object.drop.index", t("drop", "index")},
      {"camera.psf_sigma_um", t("camera", "psf_sigma_um")}};
  // The truth's tilt (0.8 deg towards azimuth 120 deg) as [x, y] angles of the edge's axis.
  const double kDeg = 3.14159265358979323846 / 180, tilt = t("light_field", "tilt_deg") * kDeg,
               az = t("light_field", "tilt_azimuth_deg") * kDeg;
  want_tilt[0] = std::asin(std::sin(tilt) * std::cos(az)) / kDeg;
  want_tilt[1] = std::asin(std::sin(tilt) * std::sin(az)) / kDeg;
  std::ifstream js(dir / "sphere_sphere/fit.json");
  ASSERT_TRUE(js.good()) << ReadFileBytes(log);
  const auto j = nlohmann::json::parse(js);
  const CalibrationData cal = ReadCalibrationFile(dir / "sphere.toml");
  size_t checked = 0;
  for (const auto& p : j["parameters"]) {
    const std::string key = p["key"];
    const double best = p["best"], sigma = p["sigma"];
    ASSERT_GT(sigma, 0) << key;
    if (key == "object.drop.radius_um") EXPECT_EQ(p["start"].get<double>(), 23.0);  // nominal
    for (int a = 0; a < 2; ++a)
      if (key == "light_field_edge.tilt_deg[" + std::to_string(a) + "]") {
        EXPECT_LT(std::abs(best - want_tilt[a]), 3 * sigma)
            << key << " = " << best << " +- " << sigma;
        ++checked;
      }
    if (want.count(key)) {
      std::printf("%s = %.5f +- %.5f (truth %.5f)\n", key.c_str(), best, sigma, want.at(key));
      EXPECT_LT(std::abs(best - want.at(key)), 3 * sigma)
          << key << " = " << best << " +- " << sigma;
      ++checked;
    }
    ExpectWrittenIntoTheCalibration(cal, key, best);
  }
  EXPECT_EQ(checked, want.size() + 2);
  EXPECT_EQ(j["parameters"].size(), 9u);  // five of the drop, edge half-angle, PSF, tilt x and y
  EXPECT_NE(cal.provenance.dump().find("sphere_calibration"), std::string::npos);
}

// The wave model's calibration (`--optics mie`) end to end on a drop imaged by the wave model
// itself: the sample's measured light field (cut at the NA) continued by a known soft edge with a
// tilted axis, an 8 um water drop in air (monochromatic, 0.462 um), two planes at -R/2 and +R/2
// with Poisson noise at 1000 photons per pixel, a camera blur of 0.1 um beyond diffraction. The
// start is what a user has: the drop on the axis (0.3-0.4 um off), the nominal diameter 0.02 um
// large, water's index at the metadata's temperature (the truth 0.0005 above it), the edge 1 deg
// beyond the NA, untilted. The fit file and fit.json say the wave model; the goodness of fit is
// consistent (the ray model's PSF cannot make these images: it would be flagged); x and y, which
// no valley couples, within 3 sigma; the calibration file carries the fitted edge and PSF and a
// provenance naming the wave model. The drop's radius and index and the edge are not checked
// against the truth: for a monochromatic drop in air this fit stops in local minima along the
// radius-index valley on about half the noise seeds (docs/calibration.md, the table there).
TEST(SphereCalibration, WaveModelFitsAWaveImagedDropAndWritesItsCalibration) {
  testing::TempDir dir;
  const std::string log = dir / "log.txt";
  ASSERT_NO_FATAL_FAILURE(CalibrateSampleLightField(dir / "lf.toml", log));
  const CalibrationData lf = ReadCalibrationFile(dir / "lf.toml");
  const double kDeg = 3.14159265358979323846 / 180, na_deg = std::asin(lf.na_limit) / kDeg;
  const double n_water = 1.33885;  // IAPWS R9-97 at 293.15 K and 0.462 um (the sample's truth)
  const std::map<std::string, double> want{{"object.drop.center_um[0]", 0.3},
                                           {"object.drop.center_um[1]", -0.2},
                                           {"object.drop.center_um[2]", 0.4},
                                           {"object.drop.radius_um", 8.0},
                                           {"object.drop.index", n_water + 0.0005},
                                           {"light_field_edge.half_angle_deg", na_deg + 0.6},
                                           {"light_field_edge.tilt_deg[0]", 0.3},
                                           {"light_field_edge.tilt_deg[1]", -0.2},
                                           {"camera.psf_sigma_um", 0.1}};
  const fs::path drop = fs::path(dir / "drop");
  fs::create_directories(drop);
  {
    std::ofstream sc(drop / "truth.toml");
    sc.precision(10);
    sc << "name = \"wave\"\nseed = 7\ncalibration = \"" << (dir / "lf.toml") << "\"\n"
       << "[[object]]\nname = \"drop\"\ntype = \"sphere\"\ncenter_um = [0.3, -0.2, 0.4]\n"
       << "radius_um = 8\nindex = " << want.at("object.drop.index") << "\n"
       << "[light_field_edge]\nhalf_angle_deg = " << want.at("light_field_edge.half_angle_deg")
       << "\nwidth_deg = 1\ntilt_deg = [0.3, -0.2]\n"
       << "[camera]\npixels = [44, 44]\npsf_sigma_um = 0.1\n"
       << "[trace]\noptics = \"mie\"\nphotons_per_pixel = 1000\n"
       << "[scan]\ndefocus_um = [-4, 4]\n";
  }
  ASSERT_EQ(Raymatch("simulate " + (drop / "truth.toml").string() + " -o " + drop.string(), log), 0)
      << ReadFileBytes(log);
  {
    std::ofstream csv(drop / "scan.csv");
    csv << "defocus_um,file\n-4,wave_z-004.00um.tif\n4,wave_z+004.00um.tif\n";
    std::ofstream md(drop / "metadata.toml");
    md << "scan = \"scan.csv\"\nobject = \"water drop\"\nnominal_diameter_um = 16.02\n"
       << "temperature_K = 293.15\n[camera]\npixel_pitch_um = 10\nbit_depth = 16\n"
       << "gain_e_per_dn = 1\nwell_capacity_e = 65535\nread_noise_e = 0\n[optics]\n"
       << "objective_focal_mm = 10\nna = 0.42\nworking_distance_mm = 20\ntube_focal_mm = 200\n"
       << "wavelength_um = 0.462\n";
  }
  ASSERT_EQ(Raymatch("calibrate sphere " + drop.string() + " --optics mie --base " +
                         (dir / "lf.toml") + " -o " + (dir / "sphere.toml"),
                     log),
            0)
      << ReadFileBytes(log);
  std::ifstream js(dir / "sphere_sphere/fit.json");
  ASSERT_TRUE(js.good()) << ReadFileBytes(log);
  const auto j = nlohmann::json::parse(js);
  EXPECT_EQ(j["optics"], "mie");
  EXPECT_NE(ReadFileBytes(dir / "sphere_sphere/fit.toml").find("optics = 'mie'"),
            std::string::npos);
  const auto& g = j["goodness_of_fit"];
  EXPECT_FALSE(g["model_mismatch"].get<bool>()) << g.dump();
  EXPECT_LT(std::abs(g["deviance"].get<double>() - g["expected_deviance"].get<double>()),
            3 * g["expected_deviance_sd"].get<double>())
      << g.dump();
  const CalibrationData cal = ReadCalibrationFile(dir / "sphere.toml");
  size_t checked = 0;
  for (const auto& p : j["parameters"]) {
    const std::string key = p["key"];
    const double best = p["best"], sigma = p["sigma"];
    ASSERT_GT(sigma, 0) << key;
    ASSERT_EQ(want.count(key), 1u) << key;
    if (key == "object.drop.center_um[0]" || key == "object.drop.center_um[1]") {
      EXPECT_LT(std::abs(best - want.at(key)), 3 * sigma)
          << key << " = " << best << " +- " << sigma;
      ++checked;
    }
    ExpectWrittenIntoTheCalibration(cal, key, best);
  }
  EXPECT_EQ(checked, 2u);
  EXPECT_EQ(j["parameters"].size(), want.size());
  EXPECT_NE(cal.provenance.dump().find("wave model"), std::string::npos);
}

}  // namespace
}  // namespace raymatch
