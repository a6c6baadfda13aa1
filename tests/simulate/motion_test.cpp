// Motion during the exposure (issue 22): a moving object's image is the exposure-weighted mean of
// static images along its path. The mean is taken over K static images at the pulse's quantile
// midpoints (equal weights) or at evenly spaced times (weights from the pulse), each traced with
// its own seed; the comparison is a chi-square over the pixels with the Poisson variances of both
// sides, so its tolerance follows from the shot noise.
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <functional>

#include "raymatch/simulate/scene.h"
#include "raymatch/simulate/shapes.h"
#include "raymatch/simulate/tracer.h"
#include "stats.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::testing {
namespace {

using simulate::ExposureSpec;
using simulate::PlaneResult;
using simulate::PulseShape;
using simulate::RunControl;
using simulate::Simulator;

constexpr uint64_t kRays = 3000000;
// The same source field for moving and static scenes (the automatic one grows with the path):
// the same rays per unit area.
constexpr double kField = 60;

Scene MovingDrop(Vec3 velocity, const ExposureSpec& e) {
  Scene s = MicroscopeScene(7);
  s.source.half_angle_deg = 20;
  s.source.field_radius_um = kField;
  s.objects = {SphereObject(9, 1.36, {0, 0, 2})};
  s.objects[0].velocity_um_per_us = velocity;
  s.exposure = e;
  return s;
}

PlaneResult Trace(const Scene& s, uint64_t rays = kRays) {
  RunControl rc;
  rc.threads = 2;
  return Simulator(s).TracePlane(0, 0, rays, rc);
}

/// Static images of a moving scene at times t_k (seeds 100 + k): every object at
/// center_um + v t_k, no velocity.
std::vector<Image> StaticAlongPath(const Scene& moving, const std::vector<double>& t) {
  std::vector<Image> out;
  for (size_t k = 0; k < t.size(); ++k) {
    Scene s = moving;
    s.trace.seed = 100 + k;
    s.exposure = ExposureSpec();
    for (simulate::ObjectSpec& o : s.objects) {
      o.center_um = o.center_um + o.velocity_um_per_us * t[k];
      o.velocity_um_per_us = {};
    }
    out.push_back(Trace(s).counts);
  }
  return out;
}

/// Expects the moving image to be the weighted mean of the static ones within 5 standard
/// deviations of a reduced chi-square (sd sqrt(2 / n)), and the static image at the pulse's
/// centre to be far from it (the test can tell motion from none).
void ExpectMeanOfStatic(const Scene& moving, const std::vector<double>& t,
                        const std::vector<double>& w) {
  const PlaneResult m = Trace(moving);
  EXPECT_GT(m.counters.motion_draws, kRays / 20);
  const auto [chi2, n] = CentralChiSquare(m.counts, StaticAlongPath(moving, t), w);
  EXPECT_LT(std::abs(chi2 - 1), 5 * std::sqrt(2 / n)) << "reduced chi-square " << chi2;
  const auto [chi2_static, n2] = CentralChiSquare(m.counts, StaticAlongPath(moving, {0}), {1.0});
  EXPECT_GT(chi2_static, 1 + 10 * std::sqrt(2 / n2)) << "motion not visible: " << chi2_static;
}

TEST(Motion, ZeroVelocityIsBitIdenticalToNoMotion) {
  ExposureSpec e;
  e.shape = PulseShape::kTopHat;
  e.duration_us = 0.1;
  Scene still = MovingDrop({}, e), plain = MicroscopeScene(7);
  plain.source.half_angle_deg = 20;
  plain.source.field_radius_um = kField;
  plain.objects = {SphereObject(9, 1.36, {0, 0, 2})};
  const PlaneResult a = Trace(still, 200000), b = Trace(plain, 200000);
  EXPECT_EQ(a.counts.pixels, b.counts.pixels);
  EXPECT_EQ(a.counters.motion_draws, 0u);
  EXPECT_EQ(a.counters.fates, b.counters.fates);
}

// A 10 um path (10 um/us for 1 us) along x, like a drop at 10 m/s under a 1 us pulse.
TEST(Motion, TopHatPulseGivesTheMeanOfStaticImagesAlongThePath) {
  ExposureSpec e;
  e.shape = PulseShape::kTopHat;
  e.duration_us = 1;
  const int K = 40;  // midpoint rule: positions 0.25 um apart, far below a 1 um object pixel
  std::vector<double> t, w(K, 1.0 / K);
  for (int k = 0; k < K; ++k) t.push_back((k + 0.5) / K - 0.5);
  ExpectMeanOfStatic(MovingDrop({10, 0, 0}, e), t, w);
}

TEST(Motion, GaussianPulseWeightsThePathByItsProfile) {
  ExposureSpec e;
  e.shape = PulseShape::kGaussian;
  e.fwhm_us = 1;
  const double sigma = 1 / 2.3548200450309493;
  const int K = 41;  // +-3.5 sigma in steps of 0.175 sigma (0.6 um at 8.5 um/us)
  std::vector<double> t, w;
  double sum = 0;
  for (int k = 0; k < K; ++k) {
    t.push_back(sigma * (-3.5 + 7.0 * k / (K - 1)));
    w.push_back(std::exp(-0.5 * t.back() * t.back() / (sigma * sigma)));
    sum += w.back();
  }
  for (double& v : w) v /= sum;
  ExpectMeanOfStatic(MovingDrop({0, 8, 3}, e), t, w);
}

// A pulse whose power rises linearly over 1 us: the object's centre_um is its position at the
// power-weighted mean time, 2/3 us; weights proportional to the power at each time.
TEST(Motion, TabulatedPulseIsCentredOnItsPowerWeightedMeanTime) {
  TempDir dir;
  const std::string csv = dir.Write("ramp.csv", "time_us,power\n0,0\n1,1\n");
  const ExposureSpec e = simulate::TabulatedExposure(csv);
  EXPECT_NEAR(e.profile.x.front(), -2.0 / 3, 1e-12);
  EXPECT_NEAR(e.profile.x.back(), 1.0 / 3, 1e-12);
  const int K = 40;
  std::vector<double> t, w;
  double sum = 0;
  for (int k = 0; k < K; ++k) {
    const double s = (k + 0.5) / K;  // time since the start
    t.push_back(s - 2.0 / 3);
    w.push_back(s);
    sum += s;
  }
  for (double& v : w) v /= sum;
  ExpectMeanOfStatic(MovingDrop({-10, 0, 0}, e), t, w);
}

// Objects move each with their own velocity, and a mesh and an index field move with their
// object: a drop along +x, an octahedron mesh (Embree's motion blur) along +y, a Luneburg lens
// (its field's centre follows its surface) along -x and +z, and a static box, under a 1 us
// top-hat pulse. Each static reference image puts every object where it is at t_k.
TEST(Motion, ObjectsMoveEachWithTheirOwnVelocityMeshesAndFieldsIncluded) {
  ExposureSpec e;
  e.shape = PulseShape::kTopHat;
  e.duration_us = 1;
  Scene s = MicroscopeScene(7);
  s.source.half_angle_deg = 20;
  s.source.field_radius_um = kField;
  s.exposure = e;
  simulate::ObjectSpec drop = SphereObject(7, 1.36, {-14, -8, 2});
  drop.velocity_um_per_us = {10, 0, 0};
  auto octahedron = std::make_shared<simulate::TriangleMesh>();
  const double a = 7;
  octahedron->vertices = {{a, 0, 0}, {-a, 0, 0}, {0, a, 0}, {0, -a, 0}, {0, 0, a}, {0, 0, -a}};
  octahedron->triangles = {{0, 2, 4}, {2, 1, 4}, {1, 3, 4}, {3, 0, 4},
                           {2, 0, 5}, {1, 2, 5}, {3, 1, 5}, {0, 3, 5}};
  simulate::ObjectSpec mesh;
  mesh.shape = simulate::ShapeType::kMesh;
  mesh.mesh = octahedron;
  mesh.index = 1.45;
  mesh.center_um = {13, -9, 0};
  mesh.velocity_um_per_us = {0, 8, 0};
  simulate::ObjectSpec lens = LuneburgSphere(7);
  lens.center_um = {2, 14, 0};
  lens.velocity_um_per_us = {-6, 0, 4};
  const simulate::ObjectSpec box = BoxObject({4, 4, 4}, 1.5, {22, 20, 0});
  s.objects = {drop, mesh, lens, box};
  const int K = 40;
  std::vector<double> t, w(K, 1.0 / K);
  for (int k = 0; k < K; ++k) t.push_back((k + 0.5) / K - 0.5);
  ExpectMeanOfStatic(s, t, w);
}

}  // namespace
}  // namespace raymatch::testing
