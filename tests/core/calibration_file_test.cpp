#include "raymatch/core/calibration_file.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "raymatch/core/error.h"
#include "temp_dir.h"

namespace raymatch {
namespace {

CalibrationData Sample() {
  CalibrationData d;
  d.angular_map = Image(4, 3);
  for (size_t i = 0; i < d.angular_map.size(); ++i) d.angular_map.pixels[i] = 0.5f * i;
  d.angular_extent = 0.5;
  d.na_limit = 0.42;
  d.cone_half_angle_deg = 24.1;
  d.edge_half_angle_deg = 25.7, d.edge_width_deg = 1.2, d.edge_tilt_deg = {-0.4, 0.7};
  d.psf_sigma_um = 0.23;
  d.key_sigma = {{"light_field_edge.half_angle_deg", 0.062},
                 {"light_field_edge.tilt_deg[0]", 0.012}};
  d.light_field_note = "measured \"up to\" NA";
  d.ring_outer_mm = {1, 2, 3};
  d.transmissions = {1, 0.97, 0.9};
  d.transmission_sigma = {0, 0.01, 0.02};
  d.corrector_distance_mm = 20;
  d.objective_focal_mm = 10, d.working_distance_mm = 20, d.na = 0.42, d.tube_focal_mm = 200;
  d.pixel_pitch_um = 10, d.wavelength_um = 0.462;
  d.provenance = {{"tool", "raymatch"}, {"command_line", "raymatch calibrate 'a b'"}};
  return d;
}

TEST(CalibrationFile, RoundTrip) {
  testing::TempDir dir;
  const CalibrationData a = Sample();
  WriteCalibrationFile(dir / "cal.toml", a);
  EXPECT_TRUE(std::filesystem::exists(dir / "cal.angular.tif"));
  const CalibrationData b = ReadCalibrationFile(dir / "cal.toml");
  EXPECT_EQ(b.angular_map.pixels, a.angular_map.pixels);
  EXPECT_EQ(b.angular_extent, a.angular_extent);
  EXPECT_EQ(b.na_limit, a.na_limit);
  EXPECT_EQ(b.light_field_note, a.light_field_note);
  EXPECT_EQ(b.edge_half_angle_deg, a.edge_half_angle_deg);
  EXPECT_EQ(b.edge_width_deg, a.edge_width_deg);
  EXPECT_EQ(b.edge_tilt_deg, a.edge_tilt_deg);
  EXPECT_EQ(b.psf_sigma_um, a.psf_sigma_um);
  EXPECT_EQ(b.key_sigma, a.key_sigma);
  EXPECT_EQ(b.transmissions, a.transmissions);
  EXPECT_EQ(b.transmission_sigma, a.transmission_sigma);
  EXPECT_EQ(b.ring_outer_mm, a.ring_outer_mm);
  EXPECT_EQ(b.tube_focal_mm, 200);
  EXPECT_EQ(b.provenance["command_line"], "raymatch calibrate 'a b'");
}

TEST(CalibrationFile, StrictReader) {
  testing::TempDir dir;
  WriteCalibrationFile(dir / "cal.toml", Sample());
  std::ifstream in(dir / "cal.toml");
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  text.replace(text.find("na = 0.42"), 9, "na = 1.42");
  dir.Write("bad.toml", text);
  try {
    ReadCalibrationFile(dir / "bad.toml");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("'optics.na': expected a number in (0, 1)"),
              std::string::npos)
        << e.what();
  }
  // The edge's tilt: two angles, each within 10 degrees.
  text = ss.str();
  const size_t at = text.find("edge_tilt_deg = [");
  ASSERT_NE(at, std::string::npos) << text;
  text.replace(at, text.find(']', at) - at + 1, "edge_tilt_deg = [12, 0]");
  dir.Write("bad.toml", text);
  try {
    ReadCalibrationFile(dir / "bad.toml");
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find(
                  "'light_field.edge_tilt_deg': expected [x, y] in degrees, each within 10"),
              std::string::npos)
        << e.what();
  }
  std::filesystem::remove(dir / "cal.angular.tif");
  EXPECT_THROW(ReadCalibrationFile(dir / "cal.toml"), Error);
}

}  // namespace
}  // namespace raymatch
