// A scene using a calibration reproduces the flat field the calibration was made from
// (issue: calibration; docs/calibration.md, "Spatial map from a flat-field image").
// The flat has a known non-uniform pattern (a 12 % gradient across x and a 6 % off-centre bump)
// with Poisson noise; the calibration's spatial map is made from it; a flat field simulated from
// a scene pointing at the calibration must match it pixel by pixel to within shot noise.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <random>

#include "raymatch/calibrate/lightfield.h"
#include "raymatch/core/calibration_file.h"
#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/tracer.h"
#include "temp_dir.h"

namespace raymatch {
namespace {

constexpr int kNx = 80, kNy = 60;
constexpr double kMean = 1000;     // photons per pixel
constexpr double kObjPixel = 0.5;  // um: 10 um pitch, 20x

double Pattern(double x, double y) {  // object-plane um, y up
  return 1 + 0.12 * x / (kNx * kObjPixel / 2) +
         0.06 * std::exp(-(std::pow(x + 6, 2) + std::pow(y - 4, 2)) / 50);
}

Image MeasuredFlat() {
  std::mt19937_64 rng(7);
  Image img(kNx, kNy);
  for (int r = 0; r < kNy; ++r)
    for (int c = 0; c < kNx; ++c) {
      const double x = (c + 0.5 - kNx / 2.0) * kObjPixel, y = (kNy / 2.0 - r - 0.5) * kObjPixel;
      img.at(c, r) = float(std::poisson_distribution<int>(kMean * Pattern(x, y))(rng));
    }
  return img;
}

/// Mean over pixels of (a - b)^2 / (a + b): 1 for two independent Poisson images of one mean.
double ChiSquarePerPixel(const Image& a, const Image& b) {
  double s = 0;
  for (size_t i = 0; i < a.size(); ++i)
    s += std::pow(a.pixels[i] - b.pixels[i], 2) / std::max(1.f, a.pixels[i] + b.pixels[i]);
  return s / a.size();
}

Image SimulateFlat(const testing::TempDir& dir, const CalibrationData& c, const std::string& name,
                   double defocus_um = 0) {
  WriteCalibrationFile(dir / (name + ".toml"), c);
  const simulate::Scene s = simulate::LoadScene(dir.Write(
      name + "_scene.toml", "seed = 3\ncalibration = \"" + name + ".toml\"\n[camera]\npixels = [" +
                                std::to_string(kNx) + ", " + std::to_string(kNy) +
                                "]\n[scan]\ndefocus_um = [" + std::to_string(defocus_um) + "]\n"));
  const simulate::Simulator sim(s);
  return sim.TracePlane(defocus_um, 0, sim.RaysForPhotonTarget(kMean)).counts;
}

/// Mean of the pixels within `border` of the image edge, over the mean of the rest.
double EdgeToCentre(const Image& img, int border) {
  double e = 0, c = 0;
  int ne = 0, nc = 0;
  for (int r = 0; r < img.height; ++r)
    for (int x = 0; x < img.width; ++x) {
      const bool edge =
          x < border || r < border || x >= img.width - border || r >= img.height - border;
      (edge ? e : c) += img.at(x, r), ++(edge ? ne : nc);
    }
  return (e / ne) / (c / nc);
}

TEST(CalibratedFlatField, SceneReproducesTheFlatFieldOfItsSpatialMap) {
  testing::TempDir dir;
  const Image flat = MeasuredFlat();
  CalibrationData c;
  c.angular_map = Image(16, 16, 1.f);  // uniform over |u|, |v| < 0.3
  c.angular_extent = 0.3;
  c.objective_focal_mm = 10, c.working_distance_mm = 20, c.na = 0.42, c.tube_focal_mm = 200;
  c.pixel_pitch_um = 10, c.wavelength_um = 0.462;
  const CalibrationData uniform = c;
  double lo, hi;
  c.spatial_map = calibrate::SpatialMapFromFlat(flat, kObjPixel, 4, c.field_size_um, &lo, &hi);
  // 20 x 15 bins of 4 px (2 um): the camera's view.
  EXPECT_EQ(c.spatial_map.width, 20);
  EXPECT_EQ(c.spatial_map.height, 15);
  EXPECT_DOUBLE_EQ(c.field_size_um[0], 40);
  EXPECT_DOUBLE_EQ(c.field_size_um[1], 30);
  EXPECT_LT(lo, 0.92);
  EXPECT_GT(hi, 1.08);

  // Round trip through the file (sidecar <stem>.spatial.tif).
  WriteCalibrationFile(dir / "rt.toml", c);
  const CalibrationData back = ReadCalibrationFile(dir / "rt.toml");
  ASSERT_EQ(back.spatial_map.size(), c.spatial_map.size());
  EXPECT_EQ(back.spatial_map.pixels, c.spatial_map.pixels);
  EXPECT_EQ(back.field_size_um[0], 40);

  // Expected chi^2 per pixel: 1 (two Poisson images) + the map's own noise (4 x 4 bin means,
  // 0.8 % -> +0.03) + the pattern's variation within a bin (+0.02); the tolerance 1.15 leaves
  // ~8 standard errors (sd of the mean of 4800 chi^2_1/1 terms: 0.02). A uniform field instead
  // leaves the pattern's ~5 % rms: about +1.3.
  const double with_map = ChiSquarePerPixel(flat, SimulateFlat(dir, c, "cal"));
  const double without = ChiSquarePerPixel(flat, SimulateFlat(dir, uniform, "uniform"));
  std::printf("chi^2 per pixel: with the spatial map %.3f, uniform field %.3f\n", with_map,
              without);
  EXPECT_GT(with_map, 0.9);
  EXPECT_LT(with_map, 1.15);
  EXPECT_GT(without, 1.8);
  // Orientation: a map flipped left-right (the gradient reversed) must not match.
  CalibrationData flipped = c;
  for (int r = 0; r < flipped.spatial_map.height; ++r)
    for (int x = 0; x < flipped.spatial_map.width; ++x)
      flipped.spatial_map.at(x, r) = c.spatial_map.at(c.spatial_map.width - 1 - x, r);
  EXPECT_GT(ChiSquarePerPixel(flat, SimulateFlat(dir, flipped, "flipped")), 2.0);
  // The map covers only the view; defocused by 30 um, rays up to 17 deg reach the view's edge
  // from up to 9 um outside it, so the simulator must continue the map's edge values: a uniform
  // map then gives a uniform image (edge ring of 8 px vs the rest: 1 within 1 %, shot noise
  // ~0.2 %), where a field cut at the view darkens the edge ring by ~40 %.
  CalibrationData uniform_map = c;
  uniform_map.spatial_map = Image(c.spatial_map.width, c.spatial_map.height, 1.f);
  EXPECT_NEAR(EdgeToCentre(SimulateFlat(dir, uniform_map, "defocused", 30), 8), 1.0, 0.01);
}

}  // namespace
}  // namespace raymatch
