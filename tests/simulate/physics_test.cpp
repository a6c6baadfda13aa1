// Monte Carlo physics against known answers (Fresnel and Snell, Born and Wolf
// ch. 1.5; the ball lens's focal length; the Debye series of a sphere, van de Hulst, Light
// Scattering by Small Particles, ch. 12; ideal-lens imaging). Fixed seeds make
// every test repeatable; tolerances are stated in shot-noise sigmas (binomial/Poisson).
#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <numeric>
#include <sstream>

#include "raymatch/simulate/tracer.h"
#include "raymatch/simulate/water.h"
#include "stats.h"
#include "temp_dir.h"
#include "test_scenes.h"

namespace raymatch::simulate {
namespace {

constexpr double kPi = 3.14159265358979323846;

Scene BaseScene() { return testing::MicroscopeScene(12345); }
ObjectSpec Sphere(double r, double n) { return testing::SphereObject(r, n); }

uint64_t Fates(const PlaneResult& r, Fate f) { return r.counters.fates[int(f)]; }

// ---- Ball lens: EFL = n D / (4 (n - 1)) from the centre (Hecht, Optics, thick lens).
// A collimated pencil of radius h = 0.15 R is scanned through focus. The RMS spot radius of
// straight rays is exactly quadratic in z, so a parabola fit of RMS^2(z) gives the best-RMS
// focus, which lies between the marginal-ray focus and the paraxial EFL. The marginal focus is
// computed here by an independent 2D trace; the tolerance adds 0.1 um for shot noise and
// pixelisation (0.1 um pixels, ~40k hits per plane).
double MarginalFocus(double R, double n, double h) {
  const double i = std::asin(h / R), r = std::asin(h / R / n);
  // Entry point (z, x) on the circle and direction after refraction, tilted by (i - r) down.
  double z = -R * std::cos(i), x = h, dz = std::cos(i - r), dx = -std::sin(i - r);
  // Second intersection with the circle: solve |p + t d| = R.
  const double b = z * dz + x * dx, c = z * z + x * x - R * R;
  const double t = -b + std::sqrt(b * b - c);
  z += t * dz, x += t * dx;
  // Leaves with total deviation 2 (i - r); crosses the axis at:
  const double dev = 2 * (i - r);
  return z + x / std::tan(dev);
}

/// The best-RMS focus of a collimated pencil of radius h through the scene's object: planes
/// efl - 6 ... efl + 6 um, a least-squares parabola through the RMS spot radius squared.
double BestRmsFocus(Scene s, double efl, double h) {
  s.source.type = SourceType::kCollimated;
  s.source.field_shape = FieldShape::kDisc;
  s.source.field_radius_um = h;
  s.camera.nx = s.camera.ny = 160;
  s.camera.pixel_pitch_um = 2;  // 0.1 um at the object
  Simulator sim(s);
  std::vector<double> zs, rms2;
  for (int k = -6; k <= 6; ++k) {
    const double z = efl + k;
    const PlaneResult r = sim.TracePlane(z, k + 6, 60000);
    double w = 0, mx = 0, my = 0, mxx = 0, myy = 0;
    for (int y = 0; y < r.counts.height; ++y)
      for (int x = 0; x < r.counts.width; ++x) {
        const double c = r.counts.at(x, y), px = (x + 0.5) * 0.1, py = (y + 0.5) * 0.1;
        w += c, mx += c * px, my += c * py, mxx += c * px * px, myy += c * py * py;
      }
    EXPECT_GT(w, 30000) << "spot left the sensor at z = " << z;
    mx /= w, my /= w;
    zs.push_back(z);
    rms2.push_back(mxx / w - mx * mx + myy / w - my * my);
  }
  // Least-squares parabola rms2 = a z^2 + b z + c (normal equations, centred on efl).
  double S[5] = {0}, T[3] = {0};
  for (size_t i = 0; i < zs.size(); ++i) {
    const double u = zs[i] - efl;
    double p = 1;
    for (int k = 0; k < 5; ++k) {
      if (k < 3) T[k] += p * rms2[i];
      S[k] += p;
      p *= u;
    }
  }
  // Solve [[S4 S3 S2],[S3 S2 S1],[S2 S1 S0]] [a b c] = [T2 T1 T0] by Cramer's rule.
  auto det3 = [](double a, double b, double c, double d, double e, double f, double g, double hh,
                 double i) {
    return a * (e * i - f * hh) - b * (d * i - f * g) + c * (d * hh - e * g);
  };
  const double D = det3(S[4], S[3], S[2], S[3], S[2], S[1], S[2], S[1], S[0]);
  const double a = det3(T[2], S[3], S[2], T[1], S[2], S[1], T[0], S[1], S[0]) / D;
  const double b = det3(S[4], T[2], S[2], S[3], T[1], S[1], S[2], T[0], S[0]) / D;
  EXPECT_GT(a, 0);
  return efl - b / (2 * a);
}

TEST(BallLens, FocusesAtEffectiveFocalLength) {
  const double R = 23, n = 1.5, h = 0.15 * R;
  const double efl = n * 2 * R / (4 * (n - 1));
  const double marginal = MarginalFocus(R, n, h);
  Scene s = BaseScene();
  s.objects = {Sphere(R, n)};
  const double z0 = BestRmsFocus(s, efl, h);
  EXPECT_LT(marginal, efl);  // spherical aberration: marginal rays focus closer
  EXPECT_GE(z0, marginal - 0.1) << "EFL " << efl << " marginal " << marginal;
  EXPECT_LE(z0, efl + 0.1) << "EFL " << efl << " marginal " << marginal;
}

// Issue 22: a water ball lens under a spectrum focuses each wavelength where its own index puts
// it. One-line spectra at 400 and 700 nm (IAPWS R9-97, 20 C: n 1.3435 and 1.3310) through the
// spectral path (each ray draws its wavelength): the best foci lie in each index's bracket
// [marginal focus, EFL], and their shift lies between the marginal foci's shift and the EFLs'
// (closed form: EFL = n R / (2 (n - 1))), +-0.15 um (shot noise and pixels of both foci).
TEST(BallLens, WaterFocusShiftsWithTheWavelengthAsItsIndex) {
  const double R = 23, h = 0.15 * R;
  simulate::Dispersion water;
  water.law = simulate::DispersionLaw::kWater;
  water.temperature_K = 293.15;
  water.density_kg_m3 = simulate::WaterDensityTanaka(293.15);
  double focus[2], efl[2], marginal[2];
  const double lines[2] = {0.40, 0.70};
  for (int k = 0; k < 2; ++k) {
    const double n = water.IndexAt(lines[k]);
    efl[k] = n * R / (2 * (n - 1));
    marginal[k] = MarginalFocus(R, n, h);
    Scene s = BaseScene();
    s.objects = {Sphere(R, water.IndexAt(0.55))};  // its constant index: not the one traced
    s.objects[0].dispersion = water;
    s.source.spectrum.type = simulate::SpectrumType::kLines;
    s.source.spectrum.wavelengths_um = {lines[k]};
    s.source.spectrum.weights = {1};
    ASSERT_TRUE(s.is_spectral());
    focus[k] = BestRmsFocus(s, efl[k], h);
    EXPECT_GE(focus[k], marginal[k] - 0.1) << lines[k];
    EXPECT_LE(focus[k], efl[k] + 0.1) << lines[k];
  }
  const double shift = focus[1] - focus[0];
  EXPECT_GT(efl[1] - efl[0], 1.0);  // 1.27 um: red focuses farther
  EXPECT_GE(shift, std::min(efl[1] - efl[0], marginal[1] - marginal[0]) - 0.15) << shift;
  EXPECT_LE(shift, std::max(efl[1] - efl[0], marginal[1] - marginal[0]) + 0.15) << shift;
}

// ---- Debye-series fractions for a sphere in collimated light (van de Hulst, ch. 12).
struct Debye {
  double p0, p1, p2;
};
// Midpoint-rule integrals over the incidence angle, weight sin(2t); 20000 intervals give
// better than 1e-7 (checked against the reference's n = 1.5 example below).
Debye DebyeIntegrals(double n, bool polarized) {
  const int N = 20000;
  Debye d{0, 0, 0};
  for (int k = 0; k < N; ++k) {
    const double t = (k + 0.5) * (kPi / 2) / N, w = std::sin(2 * t) * (kPi / 2) / N;
    const double ci = std::cos(t), ct = std::sqrt(1 - std::pow(std::sin(t) / n, 2));
    const double rs = (ci - n * ct) / (ci + n * ct), rp = (n * ci - ct) / (n * ci + ct);
    const double Rs = rs * rs, Rp = rp * rp, Rm = 0.5 * (Rs + Rp);
    d.p0 += w * Rm;
    if (polarized) {
      d.p1 += w * 0.5 * (std::pow(1 - Rs, 2) + std::pow(1 - Rp, 2));
      d.p2 += w * 0.5 * (std::pow(1 - Rs, 2) * Rs + std::pow(1 - Rp, 2) * Rp);
    } else {  // each interface draws with the unpolarised mean R (Zemax simple ray splitting)
      d.p1 += w * std::pow(1 - Rm, 2);
      d.p2 += w * std::pow(1 - Rm, 2) * Rm;
    }
  }
  return d;
}

TEST(Debye, QuadratureMatchesReferenceExample) {
  const Debye d = DebyeIntegrals(1.5, true);
  EXPECT_NEAR(d.p0, 0.09178, 1e-5);
  EXPECT_NEAR(d.p1, 0.84061, 1e-5);
  EXPECT_NEAR(d.p2, 0.05402, 1e-5);
}

class DebyeFractions : public ::testing::TestWithParam<PartialReflection> {};

TEST_P(DebyeFractions, MatchIntegralsWithinShotNoise) {
  const bool pol = GetParam() == PartialReflection::kPolarized;
  const double n = 1.5, R = 10;
  Scene s = BaseScene();
  s.objects = {Sphere(R, n)};
  s.source.type = SourceType::kCollimated;
  s.source.field_radius_um = R;
  s.trace.partial_reflection = GetParam();
  Simulator sim(s);
  const PlaneResult r = sim.TracePlane(0, 0, 3000000, {});
  const double hits = r.counters.rays_hitting_objects;
  ASSERT_GT(hits, 2.9e6);  // the field is the sphere's disc
  const Debye expect = DebyeIntegrals(n, pol), other = DebyeIntegrals(n, !pol);
  const double got[3] = {r.counters.path_class[0] / hits, r.counters.path_class[1] / hits,
                         r.counters.path_class[2] / hits};
  const double want[3] = {expect.p0, expect.p1, expect.p2};
  for (int k = 0; k < 3; ++k) {
    const double z = (got[k] - want[k]) / testing::BinomialSigma(want[k], hits);
    EXPECT_LT(std::abs(z), 4.5) << "P" << k << " got " << got[k] << " want " << want[k];
  }
  // The two polarisation treatments differ measurably in P1; the simulation must pick its own.
  const double z_other = (got[1] - other.p1) / testing::BinomialSigma(other.p1, hits);
  EXPECT_GT(std::abs(z_other), 6) << "P1 also matches the other treatment: " << other.p1;
}

INSTANTIATE_TEST_SUITE_P(Modes, DebyeFractions,
                         ::testing::Values(PartialReflection::kUnpolarized,
                                           PartialReflection::kPolarized));

// ---- Slab: incoherent multiple reflections transmit (1-R)/(1+R) at normal incidence.
std::string WriteCubeObj(const testing::TempDir& dir) {
  // Unit cube [-0.5, 0.5]^3, outward counter-clockwise winding.
  return dir.Write("cube.obj",
                   "v -0.5 -0.5 -0.5\nv 0.5 -0.5 -0.5\nv 0.5 0.5 -0.5\nv -0.5 0.5 -0.5\n"
                   "v -0.5 -0.5 0.5\nv 0.5 -0.5 0.5\nv 0.5 0.5 0.5\nv -0.5 0.5 0.5\n"
                   "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\n"
                   "f 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n");
}

// The same cube as ASCII STL and PLY (Assimp reads all three formats).
std::string WriteCube(const testing::TempDir& dir, const std::string& ext) {
  const double v[8][3] = {{-.5, -.5, -.5}, {.5, -.5, -.5}, {.5, .5, -.5}, {-.5, .5, -.5},
                          {-.5, -.5, .5},  {.5, -.5, .5},  {.5, .5, .5},  {-.5, .5, .5}};
  const int f[12][3] = {{0, 2, 1}, {0, 3, 2}, {4, 5, 6}, {4, 6, 7}, {0, 1, 5}, {0, 5, 4},
                        {1, 2, 6}, {1, 6, 5}, {2, 3, 7}, {2, 7, 6}, {3, 0, 4}, {3, 4, 7}};
  std::ostringstream os;
  if (ext == "obj") return WriteCubeObj(dir);
  if (ext == "stl") {
    os << "solid cube\n";
    for (auto& t : f) {
      os << " facet normal 0 0 0\n  outer loop\n";
      for (int k : t) os << "   vertex " << v[k][0] << " " << v[k][1] << " " << v[k][2] << "\n";
      os << "  endloop\n endfacet\n";
    }
    os << "endsolid cube\n";
  } else {
    os << "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
          "property float z\nelement face 12\nproperty list uchar int vertex_indices\nend_header\n";
    for (auto& p : v) os << p[0] << " " << p[1] << " " << p[2] << "\n";
    for (auto& t : f) os << "3 " << t[0] << " " << t[1] << " " << t[2] << "\n";
  }
  return dir.Write("cube." + ext, os.str());
}

TEST(MeshFormats, StlAndPlyCubesTransmitLikeTheBox) {
  for (const std::string ext : {"stl", "ply"}) {
    testing::TempDir dir;
    Scene s = BaseScene();
    ObjectSpec o;
    o.shape = ShapeType::kMesh;
    o.mesh_file = WriteCube(dir, ext);
    o.mesh_scale_um = 200;
    o.index = 1.5;
    s.objects = {o};
    s.source.type = SourceType::kCollimated;
    s.source.field_radius_um = 50;
    s.trace.partial_reflection = PartialReflection::kUnpolarized;
    s.trace.max_interactions = 200;
    const uint64_t N = 300000;
    const PlaneResult r = Simulator(s).TracePlane(0, 0, N);
    const double want = (1 - 0.04) / (1 + 0.04);
    const double forward = double(N - Fates(r, Fate::kEscaped)) / N;
    EXPECT_LT(std::abs(forward - want), 4 * testing::BinomialSigma(want, N)) << ext;
  }
}

class Slab : public ::testing::TestWithParam<bool> {};

TEST_P(Slab, TransmitsOneMinusROverOnePlusR) {
  const bool mesh = GetParam();
  testing::TempDir dir;
  const double n = 1.5, Rn = std::pow((n - 1) / (n + 1), 2);
  Scene s = BaseScene();
  ObjectSpec o;
  o.index = n;
  if (mesh) {
    o.shape = ShapeType::kMesh;
    o.mesh_file = WriteCubeObj(dir);
    o.mesh_scale_um = 200;  // a 200 um cube
  } else {
    o.shape = ShapeType::kBox;
    o.semi_axes_um = {100, 100, 10};
  }
  s.objects = {o};
  s.source.type = SourceType::kCollimated;
  s.source.field_radius_um = 50;
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  s.trace.max_interactions = 200;
  Simulator sim(s);
  EXPECT_EQ(sim.has_mesh_bvh(), mesh);
  const uint64_t N = 1000000;
  const PlaneResult r = sim.TracePlane(0, 0, N);
  const double forward = double(N - Fates(r, Fate::kEscaped)) / N;
  const double want = (1 - Rn) / (1 + Rn);
  EXPECT_LT(std::abs(forward - want), 4 * testing::BinomialSigma(want, N))
      << "forward " << forward << " want " << want;
  EXPECT_EQ(Fates(r, Fate::kLostInside), 0u);
  EXPECT_EQ(Fates(r, Fate::kInteractionCap), 0u);
  if (mesh) EXPECT_GT(r.counters.mesh_queries, N);
}

INSTANTIATE_TEST_SUITE_P(AnalyticAndMesh, Slab, ::testing::Bool());

// ---- Flat field: mean = N * (NA/sin theta)^2 * a_pix / (pi Rf^2); variance = mean (Poisson).
TEST(FlatField, MeanAndPoissonVariance) {
  Scene s = BaseScene();
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 27;  // beyond the NA: the stop passes (NA / sin 27)^2 of the light
  s.source.field_radius_um = 60;
  Simulator sim(s);
  const uint64_t N = 4000000;
  const PlaneResult r = sim.TracePlane(0, 0, N);
  const double accept = std::pow(0.42 / std::sin(27 * kPi / 180), 2);
  const double mean_expected = N * accept * 1.0 / (kPi * 60 * 60);
  const PixelStats st = ComputeStats(r.counts);
  const double hits = st.mean * st.count;
  EXPECT_LT(std::abs(st.mean - mean_expected), 4 * mean_expected / std::sqrt(hits))
      << st.mean << " vs " << mean_expected;
  // Sample variance of Poisson(mu) over M pixels has sd ~ mu sqrt(2/(M-1)) for mu >> 1.
  const double sd = st.mean * std::sqrt(2.0 / (st.count - 1));
  EXPECT_LT(std::abs(st.variance - st.mean), 4 * sd) << st.variance << " vs " << st.mean;
  EXPECT_EQ(Fates(r, Fate::kEscaped), 0u);
  EXPECT_NEAR(double(Fates(r, Fate::kOutsideNa)) / N, 1 - accept,
              4 * testing::BinomialSigma(1 - accept, N));
}

// ---- Determinism: the same seed gives a bit-identical image for any thread count.
TEST(Determinism, SameImageForAnyThreadCount) {
  Scene s = BaseScene();
  s.objects = {Sphere(15, 1.333)};
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 25;
  s.trace.partial_reflection = PartialReflection::kPolarized;
  Simulator sim(s);
  RunControl one, two, three;
  one.threads = 1, two.threads = 2, three.threads = 3;
  const PlaneResult a = sim.TracePlane(5, 0, 300000, one);
  const PlaneResult b = sim.TracePlane(5, 0, 300000, two);
  const PlaneResult c = sim.TracePlane(5, 0, 300000, three);
  EXPECT_EQ(a.counts.pixels, b.counts.pixels);
  EXPECT_EQ(a.counts.pixels, c.counts.pixels);
  EXPECT_EQ(a.counters.fates, c.counters.fates);
  // A different plane index draws different numbers (independent exposures).
  const PlaneResult d = sim.TracePlane(5, 1, 300000, one);
  EXPECT_NE(a.counts.pixels, d.counts.pixels);
}

// ---- Only the effects a scene calls for do work.
TEST(Effects, AbsentEffectsDoNoWork) {
  Scene s = BaseScene();
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 20;
  {
    Simulator sim(s);  // no objects, no corrector
    const PlaneResult r = sim.TracePlane(0, 0, 100000);
    EXPECT_EQ(r.counters.shape_queries, 0u);
    EXPECT_EQ(r.counters.fresnel_evaluations, 0u);
    EXPECT_EQ(r.counters.corrector_tests, 0u);
    EXPECT_EQ(r.counters.mesh_queries, 0u);
    EXPECT_FALSE(sim.has_mesh_bvh());
    const auto e = sim.Effects();
    EXPECT_EQ(std::count(e.begin(), e.end(), "refraction"), 0);
  }
  s.objects = {Sphere(10, 1.333)};
  {
    Simulator sim(s);  // sphere, partial reflection off
    const PlaneResult r = sim.TracePlane(0, 0, 100000);
    EXPECT_GT(r.counters.interface_events, 0u);
    EXPECT_EQ(r.counters.fresnel_evaluations, 0u);
    EXPECT_EQ(r.counters.mesh_queries, 0u);
    EXPECT_FALSE(sim.has_mesh_bvh());
  }
  s.trace.partial_reflection = PartialReflection::kUnpolarized;
  s.optics.corrector.enabled = true;
  s.optics.corrector.transmissions = {1, 1, 0.9, 0.8};
  {
    Simulator sim(s);
    const PlaneResult r = sim.TracePlane(0, 0, 100000);
    EXPECT_LE(r.counters.fresnel_evaluations, r.counters.interface_events);  // not on TIR
    EXPECT_GT(r.counters.fresnel_evaluations, 0u);
    EXPECT_GT(r.counters.corrector_tests, 0u);
    EXPECT_GT(Fates(r, Fate::kAbsorbedCorrector), 0u);
    const auto e = sim.Effects();
    EXPECT_EQ(std::count(e.begin(), e.end(), "angular_corrector"), 1);
  }
}

// ---- Corrector: a single zone of transmission T removes 1 - T of the accepted light.
TEST(Corrector, UniformTransmissionScalesTheFlatField) {
  Scene s = BaseScene();
  s.source.type = SourceType::kCone;
  s.source.half_angle_deg = 20;
  s.source.field_radius_um = 60;
  s.optics.corrector.enabled = true;
  s.optics.corrector.transmissions = {0.7};
  Simulator sim(s);
  const uint64_t N = 1000000;
  const PlaneResult r = sim.TracePlane(0, 0, N);
  const double tested = r.counters.corrector_tests - Fates(r, Fate::kOutsideNa);
  const double absorbed = Fates(r, Fate::kAbsorbedCorrector);
  EXPECT_LT(std::abs(testing::BinomialZ(absorbed, tested, 0.3)), 4.0);
}

}  // namespace
}  // namespace raymatch::simulate
