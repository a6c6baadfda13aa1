// The main job's report parts that a reader checks by eye: the light field's radial profile
// with the sphere calibration's edge beyond the NA (pipeline/src/run_report.cpp).
#include "run_report.h"

#include <gtest/gtest.h>

#include <cmath>

namespace raymatch::pipeline::internal {
namespace {

/// A uniform light field inside the NA cut (64 x 64 over direction cosines +-0.5).
CalibrationData UniformField(double na) {
  CalibrationData cal;
  cal.angular_map = Image(64, 64);
  cal.angular_extent = 0.5;
  cal.na_limit = na;
  cal.cone_half_angle_deg = std::asin(na) * 180 / M_PI;
  for (int y = 0; y < 64; ++y)
    for (int x = 0; x < 64; ++x) {
      const double u = (2 * (x + 0.5) / 64 - 1) * 0.5, v = (1 - 2 * (y + 0.5) / 64) * 0.5;
      cal.angular_map.at(x, y) = std::hypot(u, v) < na ? 1.0f : 0.0f;
    }
  return cal;
}

TEST(RunReport, RadialProfileDrawsTheSphereCalibrationsEdgeBeyondTheNa) {
  const double na = 0.42, cut = std::asin(na) * 180 / M_PI;  // 24.83 deg
  CalibrationData cal = UniformField(na);
  cal.edge_half_angle_deg = 25.5, cal.edge_width_deg = 1.2;
  const compare::PlotPanel p = RadialProfilePanel(cal);
  ASSERT_EQ(p.series.size(), 3u) << "the profile, the edge beyond the NA and the NA's line";
  EXPECT_NE(p.title.find("edge beyond the NA 25.5"), std::string::npos) << p.title;
  // The map's profile: 1 inside the cut (relative to its largest ring), 0 beyond.
  const compare::Series& m = p.series[0];
  ASSERT_FALSE(m.x.empty());
  EXPECT_NEAR(m.y.front(), 1.0, 1e-6);
  const compare::Series& e = p.series[1];
  EXPECT_NE(e.label.find("edge"), std::string::npos);
  ASSERT_GT(e.x.size(), 10u);
  // It starts at the reference ring inside the cut, at the map's level there (1), and follows
  // (1 - tanh((t - 25.5) / 1.2)) / 2 relative to its value at the ring: half of that level at
  // 25.5 deg, below 1 % at 25.5 + 3 x 1.2 deg, where it ends.
  EXPECT_LT(e.x.front(), cut);
  EXPECT_GT(e.x.front(), cut - 3);
  EXPECT_NEAR(e.y.front(), 1.0, 1e-6);
  EXPECT_NEAR(e.x.back(), 25.5 + 3 * 1.2, 1e-9);
  auto soft = [](double t) { return 0.5 * (1 - std::tanh((t - 25.5) / 1.2)); };
  for (size_t k = 0; k < e.x.size(); ++k) {
    EXPECT_NEAR(e.y[k], soft(e.x[k]) / soft(e.x.front()), 1e-6) << "at " << e.x[k] << " deg";
    if (k > 0) EXPECT_LT(e.y[k], e.y[k - 1]);
  }
  EXPECT_LT(e.y.back(), 0.01);
  // The NA's line at asin(NA).
  const compare::Series& cut_line = p.series[2];
  ASSERT_EQ(cut_line.x.size(), 2u);
  EXPECT_NEAR(cut_line.x[0], cut, 1e-9);
  EXPECT_NEAR(cut_line.x[1], cut, 1e-9);
}

TEST(RunReport, RadialProfileWithoutAnEdgeIsTheMapAlone) {
  const compare::PlotPanel p = RadialProfilePanel(UniformField(0.42));
  ASSERT_EQ(p.series.size(), 1u);
  EXPECT_EQ(p.title.find("edge beyond"), std::string::npos) << p.title;
}

}  // namespace
}  // namespace raymatch::pipeline::internal
