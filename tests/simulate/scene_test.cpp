// Scene files: strict reading with file:line:col errors (docs/scene-format.md).
#include "raymatch/simulate/scene.h"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <sstream>

#include "angular_map.h"
#include "raymatch/core/array_io.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/simulate/tracer.h"
#include "sources.h"
#include "stats.h"
#include "temp_dir.h"

namespace raymatch::simulate {
namespace {

const char* kGood = R"(name = "t"
[source]
type = "cone"
half_angle_deg = 20
[[object]]
type = "sphere"
radius_um = 10
index = 1.33
[objective]
focal_length_mm = 10
na = 0.42
[tube_lens]
focal_length_mm = 200
[camera]
pixels = [32, 16]
pixel_pitch_um = 20
)";

std::string LoadError(const std::string& text) {
  testing::TempDir dir;
  const std::string p = dir.Write("scene.toml", text);
  try {
    LoadScene(p);
  } catch (const Error& e) {
    const std::string w = e.what();
    return w.substr(w.find("scene.toml"));
  }
  return "";
}

std::string Replace(std::string s, const std::string& a, const std::string& b) {
  const size_t i = s.find(a);
  EXPECT_NE(i, std::string::npos) << a;
  return s.replace(i, a.size(), b);
}

TEST(SceneFile, GoodSceneLoads) {
  testing::TempDir dir;
  const Scene s = LoadScene(dir.Write("scene.toml", kGood));
  EXPECT_EQ(s.camera.nx, 32);
  EXPECT_EQ(s.camera.ny, 16);
  EXPECT_DOUBLE_EQ(s.objects.at(0).radius_um, 10);
  EXPECT_DOUBLE_EQ(Magnification(s.optics), -20);
  EXPECT_EQ(s.trace.partial_reflection, PartialReflection::kUnpolarized);
}

// Values that load but are unlikely to be meant get a warning, not an error: a sphere below the
// wavelength under the ray model (a radius in mm) and an object much wider than the view.
TEST(SceneFile, ImplausibleValuesWarn) {
  testing::TempDir dir;
  const std::string good = kGood;
  EXPECT_TRUE(LoadScene(dir.Write("good.toml", good)).warnings.empty());
  std::string tiny = good;
  const size_t at = tiny.find("radius_um = ");
  ASSERT_NE(at, std::string::npos);
  tiny.replace(at, tiny.find('\n', at) - at, "radius_um = 0.03");
  const Scene s = LoadScene(dir.Write("tiny.toml", tiny));
  ASSERT_EQ(s.warnings.size(), 1u);
  EXPECT_NE(s.warnings[0].find("radius_um = 0.03 is below the wavelength"), std::string::npos)
      << s.warnings[0];
  std::string huge = good;
  huge.replace(huge.find("radius_um = "),
               huge.find('\n', huge.find("radius_um = ")) - huge.find("radius_um = "),
               "radius_um = 3000");
  const Scene h = LoadScene(dir.Write("huge.toml", huge));
  ASSERT_EQ(h.warnings.size(), 1u);
  EXPECT_NE(h.warnings[0].find("more than twice the camera's view"), std::string::npos)
      << h.warnings[0];
}

TEST(SceneFile, WaterMaterialUsesIapws) {
  testing::TempDir dir;
  const Scene s = LoadScene(dir.Write(
      "scene.toml", Replace(std::string(kGood) + "", "index = 1.33",
                            "material = \"water\"\ntemperature_K = 298.15\ndensity_kg_m3 = "
                            "997.047435")));
  EXPECT_NEAR(s.objects[0].index, 1.3370, 2e-3);  // at 0.462 um, higher than 1.3329 at 589 nm
}

TEST(SceneFile, ErrorsSayWhereAndWhat) {
  const std::string g = kGood;
  EXPECT_EQ(LoadError(Replace(g, "radius_um = 10", "radius_um = -10")),
            "scene.toml:7:13: error: 'object[0].radius_um': expected a positive number, got -10");
  EXPECT_NE(LoadError(Replace(g, "na = 0.42", "na = 1.0"))
                .find("scene.toml:11:6: error: 'objective.na': NA = n sin(theta) must be below "
                      "the medium's index n = medium_index = 1.0"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(g, "pixels = [32, 16]", "pixels = [0, 16]"))
                .find("scene.toml:15:10: error: 'camera.pixels': expected two whole numbers"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(g, "index = 1.33", "index = 1.33\nradius = 3"))
                .find("scene.toml:9:1: error: unknown key 'object[0].radius'"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(g, "half_angle_deg = 20", "half_angle_deg = \"wide\""))
                .find("scene.toml:4:18: error: 'source.half_angle_deg': expected a number, got a "
                      "string"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(g, "[camera]\npixels = [32, 16]\npixel_pitch_um = 20\n", ""))
                .find("missing required key 'camera'"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(g, "type = \"sphere\"", "type = \"cube\""))
                .find("expected one of \"sphere\", \"ellipsoid\", \"box\", \"mesh\""),
            std::string::npos);
  EXPECT_NE(LoadError("name = \n").find("scene.toml:1:"), std::string::npos);  // syntax
}

// Issue 15 defect 3: NA = n sin(theta) with n the medium (a water-dipping NA 1.0 objective is
// valid in water, not in air); the acceptance sine is NA / n.
TEST(SceneFile, CameraReadoutIsReadWithKeyedErrors) {
  testing::TempDir dir;
  const std::string readout =
      "pixel_pitch_um = 20\n[camera.readout]\ngain_e_per_dn = 1.1\ndark_dn = 64\n";
  const Scene s =
      LoadScene(dir.Write("scene.toml", Replace(kGood, "pixel_pitch_um = 20\n", readout)));
  ASSERT_TRUE(s.camera.readout.has_value());
  EXPECT_EQ(s.camera.readout->gain_e_per_dn, 1.1);
  EXPECT_EQ(s.camera.readout->dark_dn, 64);
  EXPECT_EQ(s.camera.readout->bit_depth, 12);  // default
  EXPECT_FALSE(LoadScene(dir.Write("plain.toml", kGood)).camera.readout.has_value());
  EXPECT_NE(LoadError(Replace(kGood, "pixel_pitch_um = 20\n", readout + "bit_depth = 17\n"))
                .find("'camera.readout.bit_depth'"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(kGood, "pixel_pitch_um = 20\n",
                              "pixel_pitch_um = 20\n[camera.readout]\ndark_dn = 1\n"))
                .find("'camera.readout.gain_e_per_dn'"),
            std::string::npos);
  EXPECT_NE(LoadError(Replace(kGood, "pixel_pitch_um = 20\n", readout + "offset = 3\n"))
                .find("'camera.readout.offset'"),
            std::string::npos);
}

// [exposure] and velocity_um_per_us (issue 22): the motion, its bounds, and keyed errors.
TEST(SceneFile, MotionNeedsAPulse) {
  testing::TempDir dir;
  const std::string moving = "index = 1.33\nvelocity_um_per_us = [10, 0, 0]\n";
  const std::string pulse = "[exposure]\nshape = \"tophat\"\nduration_us = 0.1\n";
  const Scene s = LoadScene(dir.Write("m.toml", Replace(kGood, "index = 1.33\n", moving) + pulse));
  EXPECT_TRUE(s.has_motion());
  EXPECT_DOUBLE_EQ(s.objects[0].SweepUm(s.exposure.max_offset_us()), 0.5);  // 10 um/us x 0.05 us
  EXPECT_NE(
      std::find(Simulator(s).Effects().begin(), Simulator(s).Effects().end(), "motion:tophat"),
      Simulator(s).Effects().end());
  const Scene still = LoadScene(dir.Write("s.toml", std::string(kGood) + pulse));
  EXPECT_FALSE(still.has_motion());
  EXPECT_EQ(still.objects[0].SweepUm(still.exposure.max_offset_us()), 0);
  EXPECT_NE(LoadError(Replace(kGood, "index = 1.33\n", moving)).find("no [exposure] table"),
            std::string::npos);
  // Objects with different velocities (one static) each move on their own.
  const Scene two = LoadScene(
      dir.Write("two.toml", Replace(kGood, "index = 1.33\n", moving) +
                                "[[object]]\ntype = \"sphere\"\nradius_um = 2\ncenter_um = [0, 0, "
                                "-30]\nindex = 1.5\n" +
                                pulse));
  EXPECT_TRUE(two.has_motion());
  EXPECT_EQ(two.objects[1].SweepUm(two.exposure.max_offset_us()), 0);
  EXPECT_NE(LoadError(std::string(kGood) + "[exposure]\nshape = \"gaussian\"\n")
                .find("'exposure.fwhm_us'"),
            std::string::npos);
  dir.Write("bad.csv", "time_us,power\n0,1\n0,2\n");
  EXPECT_NE(LoadError(std::string(kGood) + "[exposure]\nshape = \"file\"\nfile = \"" +
                      (dir / "bad.csv") + "\"\n")
                .find("bad.csv:3:1: error: the first column must increase"),
            std::string::npos);
}

TEST(SceneFile, NaIsQuotedInTheMedium) {
  testing::TempDir dir;
  const Scene s = LoadScene(
      dir.Write("scene.toml", Replace(Replace(kGood, "na = 0.42", "na = 1.0"), "name = \"t\"",
                                      "name = \"t\"\nmedium_index = 1.33")));
  EXPECT_DOUBLE_EQ(s.optics.na, 1.0);
  EXPECT_DOUBLE_EQ(AcceptanceSin(s), 1.0 / 1.33);
  EXPECT_NE(LoadError(Replace(Replace(kGood, "na = 0.42", "na = 1.4"), "name = \"t\"",
                              "name = \"t\"\nmedium_index = 1.33"))
                .find("'objective.na': NA = n sin(theta) must be below"),
            std::string::npos);
}

// Issue 15 defect 7: whether a water density was given or defaulted is kept for the sidecar.
TEST(SceneFile, WaterDensityGivenOrDefaultedIsRecorded) {
  testing::TempDir dir;
  const Scene given = LoadScene(dir.Write(
      "a.toml", Replace(kGood, "index = 1.33",
                        "material = \"water\"\ntemperature_K = 298.15\ndensity_kg_m3 = 997.0")));
  EXPECT_EQ(given.objects[0].density_source, "given");
  EXPECT_DOUBLE_EQ(given.objects[0].density_kg_m3, 997.0);
  const Scene defaulted = LoadScene(dir.Write(
      "b.toml", Replace(kGood, "index = 1.33", "material = \"water\"\ntemperature_K = 298.15")));
  EXPECT_EQ(defaulted.objects[0].density_source, "defaulted");
  EXPECT_NEAR(defaulted.objects[0].density_kg_m3, 997.05, 0.01);  // Tanaka 2001 at 25 C
  EXPECT_EQ(LoadScene(dir.Write("c.toml", kGood)).objects[0].density_source, "");
}

TEST(SceneFile, ObjectBeyondTheObjectiveIsRejected) {
  EXPECT_NE(LoadError(Replace(kGood, "radius_um = 10", "radius_um = 10\ncenter_um = [0, 0, 2e4]"))
                .find("reaches the objective"),
            std::string::npos);
}

// A scene that points at a calibration file takes its light field, corrector and optics.
TEST(SceneFile, CalibrationFileSuppliesSourceCorrectorAndOptics) {
  testing::TempDir dir;
  CalibrationData c;
  c.angular_map = Image(8, 8, 1.f);
  c.angular_extent = 0.3;
  c.ring_outer_mm = {2, 4};
  c.transmissions = {1, 0.9};
  c.transmission_sigma = {0, 0.01};
  c.corrector_distance_mm = 20;
  c.objective_focal_mm = 10, c.working_distance_mm = 20, c.na = 0.42, c.tube_focal_mm = 180;
  c.pixel_pitch_um = 12, c.wavelength_um = 0.405;
  WriteCalibrationFile(dir / "cal.toml", c);
  const Scene s =
      LoadScene(dir.Write("s.toml", "calibration = \"cal.toml\"\n[camera]\npixels = [16, 16]\n"));
  EXPECT_EQ(s.source.type, SourceType::kLightField);
  EXPECT_EQ(s.source.angular_extent, 0.3);
  EXPECT_TRUE(s.optics.corrector.enabled);
  EXPECT_EQ(s.optics.corrector.transmissions, (std::vector<double>{1, 0.9}));
  EXPECT_EQ(s.optics.tube_focal_mm, 180);
  EXPECT_EQ(s.camera.pixel_pitch_um, 12);
  EXPECT_EQ(s.wavelength_um, 0.405);
  // What the scene read, for the main job's step reuse: the calibration and its map, once each.
  EXPECT_EQ(s.input_files, (std::vector<std::string>{dir / "cal.toml", dir / "cal.angular.tif"}));
  // A spectrum table is one more; a scene that names no file has none.
  dir.Write("led.csv", "wavelength_um,relative_power\n0.44,0\n0.46,1\n0.48,0\n");
  const Scene spectral = LoadScene(
      dir.Write("s2.toml",
                "calibration = \"cal.toml\"\n[source]\nspectrum = { file = \"led.csv\" }\n"
                "[camera]\npixels = [16, 16]\n"));
  EXPECT_EQ(spectral.input_files,
            (std::vector<std::string>{dir / "cal.toml", dir / "cal.angular.tif", dir / "led.csv"}));
  EXPECT_TRUE(LoadScene(dir.Write("s3.toml", kGood)).input_files.empty());
  EXPECT_NE(LoadError("calibration = \"missing.toml\"\n[camera]\npixels = [4, 4]\n")
                .find("scene.toml:1:15: error: 'calibration'"),
            std::string::npos);
}

// [light_field_edge] continues a calibrated map beyond its NA cut under the soft edge
// E(theta) = (1 - tanh((theta - edge) / width)) / 2 relative to E on the continued ring (1.5 map
// pixels inside the cut, s_r). Known answer: a map uniform inside the cut sends the fraction
// A_out / (A_in + A_out) of its rays beyond the NA, with
// A_in = pi s_na^2 and A_out = int_{s_na}^1 2 pi s E(asin s) / E(asin s_r) ds in direction
// cosines (midpoint rule, 2e5 steps). Those rays end as outside_na; the tolerance is 4 binomial
// standard deviations.
TEST(SceneFile, LightFieldEdgeSendsTheSoftEdgesShareOfRaysBeyondTheNa) {
  testing::TempDir dir;
  CalibrationData c = testing::NaCutCalibration([](double, double) { return 1.0; }, 10);
  WriteCalibrationFile(dir / "cal.toml", c);
  const double kPi = 3.14159265358979323846;
  for (const auto& [edge, width] : {std::pair{26.0, 1.0}, std::pair{29.0, 2.0}}) {
    auto E = [&](double s) {
      return 0.5 * (1 - std::tanh((std::asin(s) * 180 / kPi - edge) / width));
    };
    double a_out = 0;
    const int steps = 200000;
    // The continued ring, 1.5 map pixels inside the cut.
    const double ring = c.na_limit - 1.5 * (2 * c.angular_extent / c.angular_map.width);
    for (int i = 0; i < steps; ++i) {
      const double s = c.na_limit + (1 - c.na_limit) * (i + 0.5) / steps;
      a_out += 2 * kPi * s * E(s) / E(ring) * (1 - c.na_limit) / steps;
    }
    const double p = a_out / (kPi * c.na_limit * c.na_limit + a_out);
    const Scene s = LoadScene(dir.Write(
        "s.toml",
        "calibration = \"cal.toml\"\n[light_field_edge]\nhalf_angle_deg = " + std::to_string(edge) +
            "\nwidth_deg = " + std::to_string(width) + "\n[camera]\npixels = [16, 16]\n"));
    EXPECT_EQ(s.source.edge_half_angle_deg, edge);
    const Simulator sim(s);
    const uint64_t rays = 400000;
    const PlaneResult r = sim.TracePlane(0, 0, rays);
    const double got = double(r.counters.fates[static_cast<int>(Fate::kOutsideNa)]) / rays;
    EXPECT_NEAR(got, p, 4 * std::sqrt(p * (1 - p) / rays)) << "edge " << edge << " width " << width;
  }
  // Without a cut (na_limit 0) the edge has nothing to continue: an error naming the table.
  c.na_limit = 0;
  WriteCalibrationFile(dir / "cal0.toml", c);
  EXPECT_NE(LoadError("calibration = \"" + (dir / "cal0.toml") +
                      "\"\n[light_field_edge]\nhalf_angle_deg = 26\n"
                      "width_deg = 1\n[camera]\npixels = [4, 4]\n")
                .find("light_field_edge.half_angle_deg"),
            std::string::npos);
}

// A light field's tables are built once per map and edge and shared by the Simulators that use
// them (a fit builds one per evaluation): a scene traced again after another edge gives its own
// image to the bit, another edge or another map of the same size a different one; the measured
// part (inside the reference ring), which fits trace as their own population, does not depend on
// the edge, so it is shared across edges too.
TEST(SceneFile, LightFieldTablesAreSharedOnlyWhereMapAndEdgeAgree) {
  testing::TempDir dir;
  CalibrationData c = testing::NaCutCalibration([](double, double) { return 1.0; }, 10);
  WriteCalibrationFile(dir / "cal.toml", c);
  WriteCalibrationFile(
      dir / "cal2.toml",
      testing::NaCutCalibration([](double u, double) { return u > 0 ? 2.0 : 1.0; }, 10));
  auto image = [&](const std::string& cal, double edge, double width) {
    const Scene s = LoadScene(
        dir.Write("s.toml", "calibration = \"" + cal + "\"\n[light_field_edge]\nhalf_angle_deg = " +
                                std::to_string(edge) + "\nwidth_deg = " + std::to_string(width) +
                                "\n[camera]\npixels = [16, 16]\n"));
    return Simulator(s).TracePlane(0, 0, 100000).counts.pixels;
  };
  const std::vector<float> a = image("cal.toml", 26, 1);
  EXPECT_NE(image("cal.toml", 29, 2), a);
  EXPECT_NE(image("cal.toml", 26, 1.5), a);
  EXPECT_NE(image("cal2.toml", 26, 1), a);
  EXPECT_EQ(image("cal.toml", 26, 1), a);
  // The measured part, computed afresh (ContinuedMap keeps nothing): the same for any edge.
  SourceSpec ss;
  ss.type = SourceType::kLightField;
  ss.angular_extent = c.angular_extent;
  ss.map_na_limit = c.na_limit;
  ss.angular_map = c.angular_map;
  ss.edge_part = SourceSpec::EdgePart::kInside;
  double extent = 0;
  ss.edge_half_angle_deg = 26, ss.edge_width_deg = 1, ss.edge_tilt_deg = {0, 0};
  const Image in_a = ContinuedMap(ss, &extent);
  ss.edge_half_angle_deg = 29, ss.edge_width_deg = 2, ss.edge_tilt_deg = {1.2, -0.4};
  EXPECT_EQ(ContinuedMap(ss, &extent).pixels, in_a.pixels);
}

// The edge's axis tilted by t = (sin tx, sin ty) in direction cosines: from the reference ring
// s_r (kEdgeRingPixels map pixels inside the cut) outwards, across the cut, the map is its ring
// value times E(|w - t|) / E(|s_r e_phi - t|) at each azimuth phi. Known answer for
// a map uniform inside the cut: the modelled part's weight on either side of u = 0, integrated
// in polar coordinates (midpoint rule, 2000 x 4000 steps; the map's 2x2 points per fine cell of
// 1/256 of the extent agree to 0.5 %). A tilt towards +u moves the edge outwards there: the
// +u half carries more light than the -u half (1.56x at 1.2 deg with a 1 deg edge width; 3.6x
// beyond the cut alone). The measured part (inside the ring, unchanged: pi s_r^2) and the
// modelled part add up to the whole map, cell by cell.
TEST(SceneFile, LightFieldEdgeTiltMovesTheEdgeAndThePartsAddUp) {
  SourceSpec ss;
  const int n = 64;
  ss.type = SourceType::kLightField;
  ss.angular_extent = 0.5;
  ss.map_na_limit = 0.42;
  ss.angular_map = testing::NaCutAngularMap(n, ss.angular_extent, ss.map_na_limit,
                                            [](double, double) { return 1.0; });
  ss.edge_half_angle_deg = 26, ss.edge_width_deg = 1.0, ss.edge_tilt_deg = {1.2, -0.4};
  const double kPi = 3.14159265358979323846, deg = kPi / 180;
  const double tu = std::sin(1.2 * deg), tv = std::sin(-0.4 * deg), s_na = 0.42;
  const double s_r = s_na - kEdgeRingPixels * (2 * ss.angular_extent / n);  // the ring
  auto E = [&](double u, double v) {
    return 0.5 * (1 - std::tanh((std::asin(std::hypot(u - tu, v - tv)) / deg - 26) / 1.0));
  };
  double want[2] = {0, 0};  // beyond the cut: u < 0, u > 0
  const int ns = 2000, na = 4000;
  for (int i = 0; i < ns; ++i) {
    const double s = s_r + (0.62 - s_r) * (i + 0.5) / ns, ds = (0.62 - s_r) / ns;
    for (int j = 0; j < na; ++j) {
      const double phi = 2 * kPi * (j + 0.5) / na, c = std::cos(phi), sn = std::sin(phi);
      want[c > 0] += E(s * c, s * sn) / E(s_r * c, s_r * sn) * s * ds * 2 * kPi / na;
    }
  }
  double extent = 0;
  ss.edge_part = SourceSpec::EdgePart::kBeyond;
  const Image beyond = ContinuedMap(ss, &extent);
  ss.edge_part = SourceSpec::EdgePart::kInside;
  const Image inside = ContinuedMap(ss, &extent);
  ss.edge_part = SourceSpec::EdgePart::kAll;
  const Image all = ContinuedMap(ss, &extent);
  ASSERT_EQ(beyond.width, all.width);
  const double cell = 2 * extent / all.width;
  double got[2] = {0, 0}, in = 0;
  for (int y = 0; y < all.height; ++y)
    for (int x = 0; x < all.width; ++x) {
      const size_t p = size_t(y) * all.width + x;
      EXPECT_NEAR(inside.pixels[p] + beyond.pixels[p], all.pixels[p], 1e-6) << x << " " << y;
      got[x >= all.width / 2] += beyond.pixels[p] * cell * cell;
      in += inside.pixels[p] * cell * cell;
    }
  EXPECT_GT(extent, 0.62);
  for (int h = 0; h < 2; ++h) EXPECT_NEAR(got[h] / want[h], 1, 0.005) << "half " << h;
  EXPECT_GT(want[1] / want[0], 1.5);
  EXPECT_NEAR(in / (kPi * s_r * s_r), 1, 0.002);  // the measurement, unchanged
}

// The annotated example in docs/scene-format.md must stay a valid scene.
TEST(SceneFile, DocumentedExampleLoads) {
  std::ifstream in(std::string(RAYMATCH_SOURCE_DIR) + "/docs/scene-format.md");
  ASSERT_TRUE(in);
  std::stringstream ss;
  ss << in.rdbuf();
  const std::string doc = ss.str();
  const size_t a = doc.find("```toml\n"), b = doc.find("```", a + 7);
  ASSERT_NE(a, std::string::npos);
  testing::TempDir dir;
  const Scene s = LoadScene(dir.Write("example.toml", doc.substr(a + 8, b - a - 8)));
  EXPECT_EQ(s.name, "drop46");
  EXPECT_EQ(s.optics.corrector.transmissions.size(), 9u);
  EXPECT_EQ(s.defocus_um.size(), 9u);
}

// photons_per_pixel sets the ray count so that the flat-field mean hits per pixel equal it.
TEST(SceneFile, PhotonTargetGivesTheRequestedMeanCount) {
  testing::TempDir dir;
  Scene s = LoadScene(dir.Write("scene.toml", kGood));
  // The target is the background (flat-field) level, also when an object enlarges the source
  // field: measure it in a corner far from the 10 um sphere.
  s.camera.nx = s.camera.ny = 64;
  s.objects[0].center_um = {0, 0, 0};
  Simulator sim(s);
  const uint64_t rays = sim.RaysForPhotonTarget(500);
  const PlaneResult r = sim.TracePlane(0, 0, rays);
  Image corner(16, 16);
  for (int y = 0; y < 16; ++y)
    for (int x = 0; x < 16; ++x) corner.at(x, y) = r.counts.at(x, y);
  const PixelStats st = ComputeStats(corner);
  // The pilot's estimate has relative error ~1/sqrt(pilot hits) (~2e-3); the corner mean
  // ~1/sqrt(500 * 256) (3e-3). 2 % is > 4 sigma of both.
  EXPECT_NEAR(st.mean, 500, 10);
}

}  // namespace
}  // namespace raymatch::simulate

namespace raymatch::simulate {
namespace {

// A ray-list source: each listed ray is drawn with probability proportional to its weight and
// starts where the list says it crosses the object plane. Ideal imaging in focus sends every
// ray from (x, y) to the pixel of (x, y) whatever its direction: two rays (weights 3 and 1, one
// tilted) must fill exactly their two pixels, in the ratio 3 : 1 within binomial noise.
TEST(RayListSource, WeightsAndPositionsAreHonoured) {
  testing::TempDir dir;
  NdArray a;
  a.shape = {2, 5};
  a.values = {10.25, -5.25, 0.0, 0.0,  3.0,   // object-plane pixel (52, 42) of 64 x 64 at 0.5 um
              -8.25, 6.25,  0.1, 0.05, 1.0};  // pixel (15, 19)
  WriteNpy(dir / "rays.npy", a);
  const std::string optics =
      "[objective]\nfocal_length_mm = 10\nna = 0.42\n[tube_lens]\nfocal_length_mm = 200\n";
  const std::string list = "[source]\ntype = \"ray_list\"\nfile = \"";
  const Scene s =
      LoadScene(dir.Write("scene.toml", list + "rays.npy\"\n" + optics +
                                            "[camera]\npixels = [64, 64]\npixel_pitch_um = 10\n"));
  const Simulator sim(s);
  EXPECT_EQ(sim.Effects().at(0), "source:ray_list");  // the sidecar names the source
  const uint64_t n = 40000;
  const Image img = sim.TracePlane(0, 0, n).counts;
  const double A = img.at(52, 42), B = img.at(15, 19);
  double total = 0;
  for (float v : img.pixels) total += v;
  EXPECT_EQ(A + B, double(n));
  EXPECT_EQ(total, double(n));
  EXPECT_LT(std::abs(testing::BinomialZ(A, n, 0.75)), 4.0);
  // Bad lists: a direction beyond the unit circle, a wrong shape.
  a.values[2] = 0.9, a.values[3] = 0.5;
  WriteNpy(dir / "bad.npy", a);
  const std::string camera = "[camera]\npixels = [4, 4]\npixel_pitch_um = 10\n";
  EXPECT_NE(LoadError(list + (dir / "bad.npy") + "\"\n" + optics + camera)
                .find("ray 0: direction cosines need u^2 + v^2 < 1"),
            std::string::npos);
  a.shape = {5, 2};
  WriteNpy(dir / "shape.npy", a);
  EXPECT_NE(LoadError(list + (dir / "shape.npy") + "\"\n" + optics + camera).find("shape (N, 5)"),
            std::string::npos);
}

}  // namespace
}  // namespace raymatch::simulate
