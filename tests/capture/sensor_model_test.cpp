// The camera model of the simulated camera, frame files with sidecars, request checks.
#include "raymatch/capture/sensor_model.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "raymatch/capture/frames.h"
#include "raymatch/core/error.h"
#include "raymatch/core/image_io.h"
#include "temp_dir.h"

namespace raymatch::capture {
namespace {

PixelStats Stats(const Image& img) { return ComputeStats(img); }

TEST(SensorModel, DarkFrameHasBlackLevelAndReadNoise) {
  SensorModel m;  // 12-bit, 1 e-/DN, black 64 DN, read noise 6 e-
  const int n = 256;
  const Image dn = ExposeSensor(m, Image(n, n), 1.0, 42, 0);
  const PixelStats s = Stats(dn);
  // Expected: mean = black (symmetric noise, integer black: rounding adds no bias); variance =
  // read noise^2 + 1/12 (quantisation). Tolerances: 5 standard errors over N = 65536 pixels,
  // SE(mean) = 6 / 256 = 0.023 DN, SE(var) = var sqrt(2 / N) = 0.2 DN^2.
  EXPECT_NEAR(s.mean, 64.0, 5 * 6.0 / n) << "mean " << s.mean;
  EXPECT_NEAR(s.variance, 36.0 + 1.0 / 12, 5 * 36.1 * std::sqrt(2.0 / (n * n)))
      << "variance " << s.variance;
  for (float v : dn.pixels) EXPECT_EQ(v, std::round(v));  // integer code values
}

TEST(SensorModel, GainWellAndBitDepth) {
  SensorModel m;
  m.read_noise_e = 0;
  m.gain_e_per_dn = 2;
  Image e(4, 1);
  e.pixels = {0, 1000, 4500, 100000};
  const Image g1 = ExposeSensor(m, e, 1.0, 1, 0);
  EXPECT_EQ(g1.pixels[1], 64 + 500);
  EXPECT_EQ(g1.pixels[2], 64 + 2250);
  EXPECT_EQ(g1.pixels[3], 64 + 2250);  // the well holds 4500 e-
  const Image g4 = ExposeSensor(m, e, 4.0, 1, 0);
  EXPECT_EQ(g4.pixels[1], 64 + 2000);
  EXPECT_EQ(g4.pixels[2], 4095);  // 64 + 9000 clips at 12 bits
  m.bit_depth = 10;
  EXPECT_EQ(ExposeSensor(m, e, 1.0, 1, 0).pixels[2], 1023);
}

TEST(SensorModel, DeterministicPerSeedAndStream) {
  SensorModel m;
  const Image e(32, 32, 100.f);
  const Image a = ExposeSensor(m, e, 1, 5, 3), b = ExposeSensor(m, e, 1, 5, 3);
  EXPECT_EQ(a.pixels, b.pixels);
  EXPECT_NE(a.pixels, ExposeSensor(m, e, 1, 6, 3).pixels);
  EXPECT_NE(a.pixels, ExposeSensor(m, e, 1, 5, 4).pixels);
}

TEST(SensorModel, ValidateNamesTheField) {
  SensorModel m;
  m.gain_e_per_dn = 0;
  try {
    m.Validate();
    FAIL() << "no error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("gain_e_per_dn"), std::string::npos) << e.what();
  }
}

TEST(Frames, WriteReadRoundTripWithSidecar) {
  testing::TempDir dir;
  FrameSet set;
  set.image = Image(3, 2);
  set.image.pixels = {0, 1, 4095, 64, 65, 1000};
  Frame f;
  f.bit_depth = 12;
  f.pixel_format = "R12_CSI2P";
  f.exposure_us = 1234;
  f.analogue_gain = 2;
  f.black_level_dn = 64;
  f.temperature_c = 31.5;
  f.timestamp_utc = "2026-11-23T10:00:00Z";
  set.frames = {f};
  CameraInfo info;
  info.id = "test:camera";
  info.model = "hand-made";
  const std::filesystem::path p = dir.path() / "sub" / "img.tif";
  CheckOutputPath(p);
  WriteFrameSet(p, set, FrameSidecar(info, set, "round trip"));
  ImageFileInfo fi;
  const Image back = ReadImage(p.string(), &fi);
  EXPECT_EQ(fi.pixel_type, "uint16");
  EXPECT_EQ(back.pixels, set.image.pixels);
  std::ifstream in(dir.path() / "sub" / "img.json");
  const nlohmann::json j = nlohmann::json::parse(in);
  EXPECT_EQ(j["exposure_us"], 1234);
  EXPECT_EQ(j["analogue_gain"], 2);
  EXPECT_EQ(j["black_level_dn"], 64);
  EXPECT_EQ(j["temperature_c"], 31.5);
  EXPECT_EQ(j["format"]["bit_depth"], 12);
  EXPECT_EQ(j["frame_count"], 1);
  EXPECT_EQ(j["camera"]["id"], "test:camera");
  EXPECT_TRUE(j["provenance"].contains("command_line"));
  // Only the two files: no temporaries left.
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(dir.path() / "sub"), {}), 2);
}

TEST(Frames, OutputPathChecks) {
  testing::TempDir dir;
  EXPECT_THROW(CheckOutputPath(dir.path() / "x.png"), Error);
  const std::string file = dir.Write("plain", "x");
  EXPECT_THROW(CheckOutputPath(std::filesystem::path(file) / "x.tif"), Error);  // parent is a file
}

TEST(Frames, SignalLevelAndSuggestion) {
  Image dn(100, 1, 64.f + 300.f);  // 300 DN above black, 1 e-/DN, well 1000 -> 30 %
  const SignalLevel s = MeasureSignal(dn, 64, 4095, 1.0, 1000);
  EXPECT_NEAR(s.median_fraction, 0.3, 1e-9);
  EXPECT_EQ(s.clipped_fraction, 0);
  dn.pixels[0] = 4095;       // top code value
  dn.pixels[1] = 64 + 1000;  // at the full well (below the top code value)
  dn.pixels[2] = 64 + 900;   // bright, not clipped
  const SignalLevel c = MeasureSignal(dn, 64, 4095, 1.0, 1000);
  EXPECT_DOUBLE_EQ(c.clipped_fraction, 0.02);
  EXPECT_NEAR(c.peak_fraction, (4095 - 64) / 1000.0, 1e-9);
  CameraInfo info;
  EXPECT_DOUBLE_EQ(SuggestExposure(1000, 0.3, false, 0.6, info), 2000);
  EXPECT_DOUBLE_EQ(SuggestExposure(1000, 0.9, true, 0.6, info), 500);     // clipped: halve
  EXPECT_DOUBLE_EQ(SuggestExposure(1000, 0.0, false, 0.6, info), 10000);  // no signal
  info.exposure_min_us = 10, info.exposure_max_us = 1500;
  EXPECT_DOUBLE_EQ(SuggestExposure(1000, 0.3, false, 0.6, info), 1500);  // camera's limit
}

TEST(Settings, OutOfRangeRequestsNameTheLimit) {
  CameraInfo info;
  info.id = "x";
  info.width = 100, info.height = 50;
  info.exposure_min_us = 10, info.exposure_max_us = 1000;
  info.gain_min = 1, info.gain_max = 8;
  CaptureSettings s;
  s.exposure_us = 500;
  EXPECT_NO_THROW(ValidateSettings(info, s));
  s.exposure_us = 5000;
  try {
    ValidateSettings(info, s);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("10 to 1000 us"), std::string::npos) << e.what();
  }
  s.exposure_us = 500;
  s.analogue_gain = 16;
  EXPECT_THROW(ValidateSettings(info, s), Error);
  s.analogue_gain = 1;
  s.roi = {90, 0, 20, 10};
  EXPECT_THROW(ValidateSettings(info, s), Error);
  s.roi = {80, 40, 20, 10};
  EXPECT_NO_THROW(ValidateSettings(info, s));
}

}  // namespace
}  // namespace raymatch::capture
